"""The token + Origin + Host guard holds on every route of a real ``lasercal serve`` process.

viser serves ``/`` (``index.html``, its only static file: the client build is one file), a
websocket upgrade on any path, and 404 for the rest; the guard must answer 403 before any of
them for every HTTP method and every way of presenting missing, wrong or stolen credentials
(foreign or ``null`` Origin, a DNS-rebinding Host, the cookie of another port). The positive
controls (the operator's own cookie and Origin) show the routes really exist behind the guard.
"""

from __future__ import annotations

import http.client
from collections.abc import Iterator
from pathlib import Path

import pytest
import viser
import websockets.exceptions
from websockets.sync.client import connect

from tests.e2e.conftest import Served, start_serve, stop_serve

PROTOCOL = f"viser-v{viser.__version__}"
ROUTES = ["/", "/index.html", "/?token=", "/assets/index.js", "/favicon.ico", "/manifest.json",
          "/%2e%2e/%2e%2e/etc/passwd", "/..%2f..%2fetc/passwd", "//evil.example/", "/ws",
          "/index.html?token=x&token=y", "/" + "a" * 2000]
METHODS = ["GET", "HEAD", "POST", "PUT", "DELETE", "OPTIONS", "PATCH"]


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    proc, info = start_serve(tmp_path_factory.mktemp("guard"))
    yield info
    assert stop_serve(proc) == 0, "\n".join(info.output)


def _bad_credentials(s: Served) -> dict[str, tuple[str, dict[str, str]]]:
    """name -> (query suffix, headers) that must all be refused."""
    own_host = f"127.0.0.1:{s.port}"
    own = f"http://{own_host}"
    cookie = f"lasercal_token_{s.port}={s.token}"
    return {
        "nothing": ("", {"Host": own_host}),
        "wrong token": (f"token={s.token[:-1]}x", {"Host": own_host}),
        "token in another parameter": (f"Token={s.token}", {"Host": own_host}),
        "token as a bearer header": ("", {"Host": own_host,
                                          "Authorization": f"Bearer {s.token}"}),
        "wrong cookie": ("", {"Host": own_host, "Cookie": f"lasercal_token_{s.port}=x"}),
        "other port's cookie": ("", {"Host": own_host,
                                     "Cookie": f"lasercal_token_{s.port + 1}={s.token}"}),
        "foreign origin + cookie": ("", {"Host": own_host, "Cookie": cookie,
                                         "Origin": "http://evil.example"}),
        "null origin + cookie": ("", {"Host": own_host, "Cookie": cookie, "Origin": "null"}),
        "look-alike origin": ("", {"Host": own_host, "Cookie": cookie,
                                   "Origin": f"{own}.evil.example"}),
        "https origin": ("", {"Host": own_host, "Cookie": cookie,
                              "Origin": f"https://{own_host}"}),
        "other port origin": ("", {"Host": own_host, "Cookie": cookie,
                                   "Origin": f"http://127.0.0.1:{s.port + 1}"}),
        "foreign origin + token": (f"token={s.token}", {"Host": own_host,
                                                        "Origin": "http://evil.example"}),
        "rebinding host + cookie": ("", {"Host": f"evil.example:{s.port}", "Cookie": cookie}),
        "rebinding host + token": (f"token={s.token}", {"Host": f"evil.example:{s.port}"}),
        "host without port": ("", {"Host": "127.0.0.1", "Cookie": cookie}),
    }


def _http(s: Served, method: str, path: str, headers: dict[str, str]) -> tuple[int, bytes]:
    conn = http.client.HTTPConnection("127.0.0.1", s.port, timeout=10)
    try:
        conn.request(method, path, body=b"x" if method in ("POST", "PUT", "PATCH") else None,
                     headers=headers)
        response = conn.getresponse()
        return response.status, response.read()
    finally:
        conn.close()


def _with_query(path: str, query: str) -> str:
    if not query:
        return path
    return f"{path}{'&' if '?' in path else '?'}{query}"


def test_every_route_and_method_refuses_bad_credentials(served: Served) -> None:
    refused = 0
    for name, (query, headers) in _bad_credentials(served).items():
        for path in ROUTES:
            for method in METHODS:
                status, body = _http(served, method, _with_query(path, query), headers)
                assert status == 403, (name, method, path, status)
                assert b"viser" not in body.lower() and b"<html" not in body.lower()
                refused += 1
    print(f"\n{refused} HTTP requests with bad credentials: all 403")


def test_the_routes_exist_behind_the_guard(served: Served) -> None:
    own = {"Host": f"127.0.0.1:{served.port}",
           "Cookie": f"lasercal_token_{served.port}={served.token}"}
    status, body = _http(served, "GET", "/", own)
    assert status == 200 and b"<html" in body.lower()
    assert _http(served, "GET", "/index.html", own)[0] == 200
    assert _http(served, "GET", "/assets/index.js", own)[0] == 404       # viser's own 404
    assert _http(served, "GET", "/%2e%2e/%2e%2e/etc/passwd", own)[0] == 404
    status, _ = _http(served, "GET", f"/?token={served.token}", {"Host": own["Host"]})
    assert status == 303                                                 # token -> cookie


def _ws_status(url: str, headers: dict[str, str]) -> int:
    try:
        with connect(url, subprotocols=[PROTOCOL], additional_headers=headers,
                     open_timeout=10):
            return 101
    except websockets.exceptions.InvalidStatus as exc:
        return exc.response.status_code


def test_websocket_upgrade_refused_on_every_path(served: Served) -> None:
    base = f"ws://127.0.0.1:{served.port}"
    for name, (query, headers) in _bad_credentials(served).items():
        extra = {k: v for k, v in headers.items() if k != "Host"}
        host = headers["Host"]
        for path in ("/", "/index.html", "/ws", "/x/y"):
            url = _with_query(f"{base}{path}", query)
            if host != f"127.0.0.1:{served.port}":
                status = _raw_upgrade(served, _with_query(path, query), headers)
            else:
                status = _ws_status(url, extra)
            assert status == 403, (name, path, status)
    own = {"Origin": f"http://127.0.0.1:{served.port}",
           "Cookie": f"lasercal_token_{served.port}={served.token}"}
    assert _ws_status(f"{base}/", own) == 101                       # the operator's tab


def _raw_upgrade(s: Served, path: str, headers: dict[str, str]) -> int:
    """A websocket upgrade with an arbitrary Host header (DNS rebinding)."""
    return _http(s, "GET", path, {**headers, "Upgrade": "websocket", "Connection": "Upgrade",
                                  "Sec-WebSocket-Version": "13",
                                  "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==",
                                  "Sec-WebSocket-Protocol": PROTOCOL})[0]


def test_session_file_not_served(served: Served) -> None:
    """The session database next to the server is never reachable over HTTP."""
    own = {"Host": f"127.0.0.1:{served.port}",
           "Cookie": f"lasercal_token_{served.port}={served.token}"}
    name = Path(served.session).name
    for path in (f"/{name}", f"/../{name}", f"/%2e%2e/{name}"):
        assert _http(served, "GET", path, own)[0] == 404
