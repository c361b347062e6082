"""The token + Origin guard in front of viser: every route refuses strangers with 403."""

from __future__ import annotations

import io
import re
import socket
import urllib.error
import urllib.request
from collections.abc import Iterator

import pytest
import viser
import websockets.exceptions
from websockets.sync.client import connect

from app.server import Guard, GuardedServer, is_loopback

PROTOCOL = f"viser-v{viser.__version__}"


class _NoRedirect(urllib.request.HTTPRedirectHandler):
    def redirect_request(self, *args, **kwargs):  # type: ignore[no-untyped-def]
        return None


_OPENER = urllib.request.build_opener(_NoRedirect)


def _get(url: str, headers: dict[str, str] | None = None) -> tuple[int, dict[str, str], bytes]:
    request = urllib.request.Request(url, headers=headers or {})
    try:
        with _OPENER.open(request, timeout=10) as response:
            return response.status, dict(response.headers.items()), response.read()
    except urllib.error.HTTPError as err:
        return err.code, dict(err.headers.items()), err.read()


@pytest.fixture(scope="module")
def server() -> Iterator[GuardedServer]:
    srv = GuardedServer("127.0.0.1", 0)
    srv.start()
    srv.viser.scene.add_box("/probe", dimensions=(1.0, 1.0, 1.0))
    yield srv
    srv.stop()


def _base(srv: GuardedServer) -> str:
    assert srv.guard is not None
    return f"http://127.0.0.1:{srv.guard.port}"


def _cookie(srv: GuardedServer) -> str:
    assert srv.guard is not None
    return f"{srv.guard.cookie_name}={srv.guard.token}"


def test_announce_prints_exact_url_line(server: GuardedServer) -> None:
    out = io.StringIO()
    server.announce(out)
    guard = server.guard
    assert guard is not None
    lines = out.getvalue().splitlines()
    assert f"http://127.0.0.1:{guard.port}/?token={guard.token}" in lines
    assert re.fullmatch(r"[A-Za-z0-9_-]{43}", guard.token)  # 256 random bits


def test_http_without_token_is_403(server: GuardedServer) -> None:
    for path in ("/", "/index.html", "/anything?x=1"):
        status, _, body = _get(_base(server) + path)
        assert status == 403, path
        assert b"<html" not in body.lower()


def test_wrong_token_is_403(server: GuardedServer) -> None:
    assert _get(_base(server) + "/?token=wrong")[0] == 403
    assert _get(_base(server) + "/", {"Cookie": f"{server.guard.cookie_name}=wrong"})[0] == 403


def test_token_becomes_strict_httponly_cookie_and_redirects(server: GuardedServer) -> None:
    status, headers, _ = _get(server.guard.url)
    assert status == 303
    assert headers["Location"] == "/"
    cookie = headers["Set-Cookie"]
    assert cookie.startswith(_cookie(server) + ";")
    assert "HttpOnly" in cookie and "SameSite=Strict" in cookie


def test_cookie_serves_viser_page(server: GuardedServer) -> None:
    status, _, body = _get(_base(server) + "/", {"Cookie": _cookie(server)})
    assert status == 200
    assert b"<html" in body.lower()


def test_foreign_origin_or_host_is_403_even_with_cookie(server: GuardedServer) -> None:
    for headers in ({"Origin": "http://evil.example"},
                    {"Origin": f"http://127.0.0.1:{server.guard.port + 1}"},
                    {"Origin": "null"},
                    {"Host": f"evil.example:{server.guard.port}"}):
        status, _, _ = _get(_base(server) + "/", {"Cookie": _cookie(server), **headers})
        assert status == 403, headers


def _ws(url: str, headers: dict[str, str]):  # type: ignore[no-untyped-def]
    return connect(url, subprotocols=[PROTOCOL], additional_headers=headers, open_timeout=10)


@pytest.mark.parametrize("headers", [
    {},                                                        # no token at all
    {"Origin": "http://evil.example"},                         # foreign page, no token
    {"Cookie": "lasercal_token_1=x"},                          # wrong cookie
])
def test_websocket_without_token_is_403(server: GuardedServer, headers: dict[str, str]) -> None:
    with pytest.raises(websockets.exceptions.InvalidStatus) as info:
        _ws(f"ws://127.0.0.1:{server.guard.port}/", headers)
    assert info.value.response.status_code == 403


def test_websocket_with_cookie_but_foreign_origin_is_403(server: GuardedServer) -> None:
    with pytest.raises(websockets.exceptions.InvalidStatus) as info:
        _ws(f"ws://127.0.0.1:{server.guard.port}/",
            {"Cookie": _cookie(server), "Origin": "http://evil.example"})
    assert info.value.response.status_code == 403


def test_websocket_with_cookie_and_own_origin_reaches_viser(server: GuardedServer) -> None:
    origin = _base(server)
    with _ws(f"ws://127.0.0.1:{server.guard.port}/",
             {"Cookie": _cookie(server), "Origin": origin}) as ws:
        assert ws.subprotocol == PROTOCOL
        first = ws.recv(timeout=10)
        assert isinstance(first, bytes) and len(first) > 0  # viser's msgpack scene backlog


def test_viser_port_itself_refuses_direct_connections(server: GuardedServer) -> None:
    """The loopback viser port is not a way around the guard."""
    port = server.upstream_port
    assert server.viser.get_host() == "127.0.0.1"
    assert _get(f"http://127.0.0.1:{port}/")[0] == 403
    with pytest.raises(websockets.exceptions.InvalidStatus) as info:
        _ws(f"ws://127.0.0.1:{port}/", {"Origin": f"http://127.0.0.1:{port}"})
    assert info.value.response.status_code == 403


def test_guard_rules_for_other_hosts() -> None:
    guard = Guard("192.0.2.7", 8080, token="t")
    assert guard.url == "http://192.0.2.7:8080/?token=t"
    assert guard.origin_ok("http://192.0.2.7:8080") and guard.origin_ok(None)
    assert not guard.origin_ok("http://localhost:8080")  # bound to one address: exact origin
    assert not guard.origin_ok("https://192.0.2.7:8080")
    anywhere = Guard("0.0.0.0", 8080, token="t")         # all interfaces: this machine's names
    assert anywhere.origin_ok(f"http://{socket.gethostname()}:8080")
    assert anywhere.origin_ok("http://127.0.0.1:8080") and anywhere.origin_ok("http://0.0.0.0:8080")
    assert not anywhere.origin_ok("http://evil.example:8080")
    loop = Guard("127.0.0.1", 8080, token="t")
    assert loop.origin_ok("http://localhost:8080") and loop.origin_ok("http://[::1]:8080")
    assert not loop.origin_ok("http://localhost:8081")
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.2")
    assert not loop.token_ok(None) and not loop.token_ok("T") and loop.token_ok("t")


def test_non_loopback_host_prints_warning(capsys: pytest.CaptureFixture[str]) -> None:
    srv = GuardedServer("0.0.0.0", 0)
    try:
        srv.start()
        srv.announce()
    finally:
        srv.stop()
    captured = capsys.readouterr()
    assert "warning: listening on 0.0.0.0" in captured.err
    assert re.search(r"^http://0\.0\.0\.0:\d+/\?token=\S+$", captured.out, re.M)


@pytest.mark.parametrize("argv, message", [
    (["--port", "70000"], "--port must be in 0..65535"),
    (["--session", "/nonexistent-dir/s.db"], "does not exist"),
    (["--sim", "--hardware"], "either --sim or --hardware"),
    (["--workcell", "/nonexistent.toml"], "no such workcell file"),
])
def test_serve_bad_arguments_are_one_error_line(
        argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    from app.cli import main

    assert main(["serve", *argv]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and message in err and err.count("\n") == 1


def test_serve_refuses_a_file_that_is_not_a_session(tmp_path, capsys) -> None:
    from app.cli import main

    bad = tmp_path / "garbage.db"
    bad.write_bytes(b"\x00\x01 not sqlite at all" * 100)
    assert main(["serve", "--session", str(bad)]) == 2
    assert "error: " in capsys.readouterr().err


def test_serve_on_a_busy_port_is_one_error_line(tmp_path) -> None:
    """A port already taken: exit 2 and exactly one ``error:`` line (no aiohttp leftovers)."""
    import socket
    import subprocess
    import sys
    from pathlib import Path

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        out = subprocess.run([sys.executable, "-m", "app", "serve", "--port", str(port),
                              "--session", str(tmp_path / "s.db")], capture_output=True,
                             text=True, timeout=120, cwd=Path(__file__).resolve().parents[2])
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: cannot listen"), out.stderr
