"""A foreign web page, or a client without the token, cannot open the dashboard websocket."""

from __future__ import annotations

import threading
from collections.abc import Iterator
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
import viser
import websockets.exceptions
from websockets.sync.client import connect

from tests.e2e.conftest import Served

PROTOCOL = f"viser-v{viser.__version__}"
EVIL_PAGE = """<!doctype html><html><body><script>
window.result = new Promise((resolve) => {
  const ws = new WebSocket("ws://127.0.0.1:%d/", ["%s"]);
  ws.onopen = () => resolve("open");
  ws.onerror = () => resolve("error");
  ws.onclose = (e) => resolve("closed " + e.code);
});
</script></body></html>"""


@pytest.fixture(scope="module")
def evil_origin(served: Served) -> Iterator[str]:
    """Another web site on this machine (same host, other port: same-site, foreign origin)."""
    page = (EVIL_PAGE % (served.port, PROTOCOL)).encode()

    class Handler(BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            self.send_response(200)
            self.send_header("Content-Type", "text/html")
            self.end_headers()
            self.wfile.write(page)

        def log_message(self, *args: object) -> None:
            pass
    httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    yield f"http://127.0.0.1:{httpd.server_address[1]}"
    httpd.shutdown()


def _status(url: str, headers: dict[str, str]) -> int:
    try:
        with connect(url, subprotocols=[PROTOCOL], additional_headers=headers, open_timeout=10):
            return 101
    except websockets.exceptions.InvalidStatus as exc:
        return exc.response.status_code


def test_websocket_needs_token_and_own_origin(served: Served) -> None:
    ws = f"ws://127.0.0.1:{served.port}/"
    own = f"http://127.0.0.1:{served.port}"
    cookie = f"lasercal_token_{served.port}={served.token}"
    assert _status(ws, {"Origin": own}) == 403                                 # no token
    assert _status(ws, {"Origin": own, "Cookie": f"lasercal_token_{served.port}=x"}) == 403
    assert _status(ws, {"Origin": "http://evil.example", "Cookie": cookie}) == 403
    assert _status(f"{ws}?token={served.token}", {"Origin": "http://evil.example"}) == 403
    assert _status(ws, {"Origin": own, "Cookie": cookie}) == 101               # the dashboard


def test_foreign_page_in_a_logged_in_browser_is_refused(
        served: Served, browser, evil_origin: str) -> None:
    context = browser.new_context()
    page = context.new_page()
    page.goto(served.url)                       # the operator's tab: cookie set
    page.locator("canvas").first.wait_for(timeout=60_000)
    evil = context.new_page()
    console: list[str] = []
    evil.on("console", lambda m: console.append(m.text))
    evil.goto(evil_origin)
    assert evil.evaluate("window.result") in ("error", "closed 1006")
    assert any("403" in line for line in console), console
    context.close()
