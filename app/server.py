"""Viser behind a token + Origin guard: the only socket a browser can reach is the guard.

Viser has no authentication and no Origin check, so any web page the operator visits could
open its websocket and move the robot. ``lasercal serve`` therefore starts viser on a random
free loopback port and puts an aiohttp reverse proxy (HTTP + websocket) in front of it on the
public ``--host/--port``. The proxy

- prints ``http://HOST:PORT/?token=TOKEN`` at start-up (a fresh random token per run);
- exchanges a valid ``?token=`` for a ``SameSite=Strict; HttpOnly`` cookie and redirects to
  the same URL without the token;
- answers 403 to every HTTP request and websocket upgrade that carries neither a valid token
  nor the cookie, whose ``Origin`` header is not the dashboard's own origin, or whose ``Host``
  header is not one of the dashboard's names (DNS rebinding) -- before anything reaches viser.
"""

from __future__ import annotations

import asyncio
import contextlib
import hmac
import ipaddress
import secrets
import sys
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field
from urllib.parse import urlsplit

import aiohttp
from aiohttp import web

#: Hop-by-hop headers (RFC 9110 section 7.6.1) and those the proxy sets itself.
_HOP_HEADERS = frozenset({
    "connection", "keep-alive", "proxy-authenticate", "proxy-authorization", "te", "trailer",
    "transfer-encoding", "upgrade", "host", "content-length", "cookie", "origin", "referer",
    "sec-websocket-key", "sec-websocket-version", "sec-websocket-extensions",
    "sec-websocket-protocol", "sec-websocket-accept",
})
#: Largest websocket message relayed (viser allows 50 MB, e.g. file transfers and renders).
MAX_WS_MESSAGE = 50 * 1024 * 1024
#: Largest HTTP request body accepted (viser itself only serves GETs).
MAX_HTTP_BODY = 1024 * 1024
LOOPBACK_NAMES = ("127.0.0.1", "localhost", "[::1]")
#: Header by which viser recognises its own proxy (any other local client gets 403).
UPSTREAM_SECRET_HEADER = "X-Lasercal-Upstream"
_SESSION_KEY = web.AppKey("session", aiohttp.ClientSession)
_PATCH_LOCK = threading.Lock()


def is_loopback(host: str) -> bool:
    """True when ``host`` names the loopback interface (127.0.0.0/8, ::1 or 'localhost')."""
    name = host.strip("[]")
    if name == "localhost":
        return True
    try:
        return ipaddress.ip_address(name).is_loopback
    except ValueError:
        return False


def is_wildcard(host: str) -> bool:
    """True for an all-interfaces bind address ('0.0.0.0', '::' or '')."""
    return host.strip("[]") in ("0.0.0.0", "::", "")


def local_names() -> set[str]:
    """This machine's host name, FQDN and their addresses (the names another machine may use
    to reach a server bound to all interfaces)."""
    import socket

    names = {socket.gethostname(), socket.getfqdn()}
    for name in list(names):
        with contextlib.suppress(OSError):
            names.update(str(info[4][0]) for info in socket.getaddrinfo(name, None))
    return {n for n in names if n}


def _host_for_url(host: str) -> str:
    """``host`` as it appears in a URL (IPv6 literals in brackets)."""
    return f"[{host}]" if ":" in host and not host.startswith("[") else host


@dataclass
class Guard:
    """The access rule: a secret token (or its cookie) and an allow-list of origins.

    ``allowed_hosts`` are the ``host:port`` strings the dashboard answers to; an ``Origin`` must be
    ``http://`` + one of them, and the ``Host`` header must be one of them.
    """

    host: str
    port: int
    token: str = field(default_factory=lambda: secrets.token_urlsafe(32))
    extra_hosts: tuple[str, ...] = ()

    @property
    def cookie_name(self) -> str:
        """Cookie name, per port: cookies are shared between ports of one host."""
        return f"lasercal_token_{self.port}"

    @property
    def url(self) -> str:
        """The tokenised start-up URL ``http://HOST:PORT/?token=TOKEN``."""
        return f"http://{_host_for_url(self.host)}:{self.port}/?token={self.token}"

    @property
    def allowed_hosts(self) -> frozenset[str]:
        names: set[str] = {_host_for_url(self.host), *self.extra_hosts}
        if is_loopback(self.host) or is_wildcard(self.host):
            names.update(LOOPBACK_NAMES)
        if is_wildcard(self.host):
            names.update(_host_for_url(n) for n in local_names())
        return frozenset(f"{n}:{self.port}".lower() for n in names)

    def token_ok(self, candidate: str | None) -> bool:
        """Constant-time comparison of ``candidate`` with the token."""
        return candidate is not None and hmac.compare_digest(
            candidate.encode("utf-8", "replace"), self.token.encode())

    def origin_ok(self, origin: str | None) -> bool:
        """No ``Origin`` (a top-level navigation or a non-browser client) or our own origin."""
        if origin is None:
            return True
        parts = urlsplit(origin)
        return parts.scheme == "http" and parts.netloc.lower() in self.allowed_hosts

    def check(self, request: web.Request) -> str | None:
        """Why ``request`` is refused, or None when it may pass."""
        host = request.headers.get("Host", "").lower()
        if host not in self.allowed_hosts:
            return "unknown Host header"
        if not self.origin_ok(request.headers.get("Origin")):
            return "foreign Origin"
        if self.token_ok(request.query.get("token")) or self.token_ok(
                request.cookies.get(self.cookie_name)):
            return None
        return "missing or wrong token"


def _forbidden(reason: str) -> web.Response:
    return web.Response(status=403, text=f"403 Forbidden: {reason}. Open the tokenised URL that "
                        "`lasercal serve` printed.\n")


def build_proxy_app(guard: Guard, upstream_port: int, upstream_secret: str) -> web.Application:
    """aiohttp application that checks ``guard`` and relays to viser on ``127.0.0.1:upstream``.

    Every relayed request carries ``upstream_secret`` in :data:`UPSTREAM_SECRET_HEADER`.
    """
    upstream = f"127.0.0.1:{upstream_port}"
    app = web.Application(client_max_size=MAX_HTTP_BODY)
    session_key = _SESSION_KEY

    async def on_startup(app: web.Application) -> None:
        app[session_key] = aiohttp.ClientSession(
            auto_decompress=False, headers={UPSTREAM_SECRET_HEADER: upstream_secret},
            timeout=aiohttp.ClientTimeout(total=None, sock_connect=10))

    async def on_cleanup(app: web.Application) -> None:
        await app[session_key].close()

    app.on_startup.append(on_startup)
    app.on_cleanup.append(on_cleanup)

    async def handle(request: web.Request) -> web.StreamResponse:
        reason = guard.check(request)
        if reason is not None:
            return _forbidden(reason)
        is_ws = request.headers.get("Upgrade", "").lower() == "websocket"
        if "token" in request.query and not is_ws:
            query = {k: v for k, v in request.query.items() if k != "token"}
            location = request.rel_url.with_query(query)
            response = web.Response(status=303, headers={"Location": str(location)})
            response.set_cookie(guard.cookie_name, guard.token, httponly=True,
                                samesite="Strict", path="/")
            response.headers["Cache-Control"] = "no-store"
            return response
        session = app[session_key]
        if is_ws:
            return await _relay_websocket(request, session, upstream)
        return await _relay_http(request, session, upstream)

    app.router.add_route("*", "/{tail:.*}", handle)
    return app


def _forward_headers(headers: Iterable[tuple[str, str]]) -> dict[str, str]:
    return {k: v for k, v in headers if k.lower() not in _HOP_HEADERS}


async def _relay_http(request: web.Request, session: aiohttp.ClientSession,
                      upstream: str) -> web.StreamResponse:
    body = await request.read()
    url = f"http://{upstream}{request.rel_url}"
    async with session.request(request.method, url, headers=_forward_headers(
            request.headers.items()), data=body or None, allow_redirects=False) as up:
        headers = _forward_headers(up.headers.items())
        response = web.StreamResponse(status=up.status, headers=headers)
        response.headers["Cache-Control"] = "no-store"
        response.headers["X-Frame-Options"] = "DENY"
        response.headers["Referrer-Policy"] = "no-referrer"
        await response.prepare(request)
        async for chunk in up.content.iter_chunked(64 * 1024):
            await response.write(chunk)
        await response.write_eof()
        return response


async def _relay_websocket(request: web.Request, session: aiohttp.ClientSession,
                           upstream: str) -> web.StreamResponse:
    offered = [p.strip() for p in request.headers.get("Sec-WebSocket-Protocol", "").split(",")
               if p.strip()]
    try:
        up = await session.ws_connect(f"ws://{upstream}{request.path}", protocols=offered,
                                      max_msg_size=MAX_WS_MESSAGE, compress=0, autoping=True)
    except aiohttp.ClientError as exc:
        return web.Response(status=502, text=f"dashboard backend unavailable: {exc}\n")
    down = web.WebSocketResponse(protocols=(up.protocol,) if up.protocol else (),
                                 max_msg_size=MAX_WS_MESSAGE, compress=False)
    await down.prepare(request)

    async def pump(src: aiohttp.ClientWebSocketResponse | web.WebSocketResponse,
                   dst: aiohttp.ClientWebSocketResponse | web.WebSocketResponse) -> None:
        async for msg in src:
            if msg.type is aiohttp.WSMsgType.BINARY:
                await dst.send_bytes(msg.data)
            elif msg.type is aiohttp.WSMsgType.TEXT:
                await dst.send_str(msg.data)
            else:
                break
        code = src.close_code if src.close_code is not None else 1000
        if not dst.closed:
            await dst.close(code=code if 1000 <= code < 5000 and code not in (1005, 1006)
                            else 1011)

    tasks = [asyncio.ensure_future(pump(down, up)), asyncio.ensure_future(pump(up, down))]
    try:
        await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        await up.close()
        await down.close()
    return down


def _start_viser_behind_secret(label: str, secret: str):
    """``viser.ViserServer`` on a free loopback port that answers 403 without ``secret``.

    Viser binds with ``websockets.asyncio.server.serve(..., process_request=...)``; during its
    construction we wrap that call so the handshake hook first checks
    :data:`UPSTREAM_SECRET_HEADER`. Thus another local program (or a web page opening
    ``ws://127.0.0.1:<random port>``) cannot bypass the guard. Viser's own banner (which would
    print the internal URL) is swallowed.
    """
    import io
    from unittest import mock

    import viser
    import websockets.asyncio.server as ws_server

    original_serve = ws_server.serve

    def checked(inner):
        def process_request(connection, request):
            got = request.headers.get(UPSTREAM_SECRET_HEADER, "")
            if not hmac.compare_digest(got.encode("utf-8", "replace"), secret.encode()):
                return connection.respond(403, "403 Forbidden: use the lasercal guard URL\n")
            return inner(connection, request) if inner is not None else None
        return process_request

    def serve(handler, *args, **kwargs):
        if getattr(handler, "__module__", "").startswith("viser."):
            kwargs["process_request"] = checked(kwargs.get("process_request"))
        return original_serve(handler, *args, **kwargs)

    with _PATCH_LOCK, mock.patch.object(ws_server, "serve", serve), \
            contextlib.redirect_stdout(io.StringIO()):
        return viser.ViserServer(host="127.0.0.1", port=0, label=label, verbose=False)


class GuardedServer:
    """A :class:`viser.ViserServer` on a loopback ephemeral port behind the guard proxy.

    ``start()`` returns once both listen; ``viser`` is the server the scene and panels use.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, *,
                 label: str = "lasercal", token: str | None = None) -> None:
        self._upstream_secret = secrets.token_urlsafe(32)
        self.viser = _start_viser_behind_secret(label, self._upstream_secret)
        self.upstream_port = self.viser.get_port()
        self._host, self._port = host, port
        self._token = token
        self._loop: asyncio.AbstractEventLoop | None = None
        self._runner: web.AppRunner | None = None
        self._thread: threading.Thread | None = None
        self.guard: Guard | None = None

    def start(self) -> Guard:
        """Bind the proxy (port 0 = any free port); return the guard holding URL and token."""
        ready = threading.Event()
        errors: list[BaseException] = []
        loop = asyncio.new_event_loop()
        self._loop = loop

        async def boot() -> None:
            guard = Guard(self._host, self._port)
            if self._token:
                guard.token = self._token
            # the app reads guard.port lazily, so it can be fixed after binding port 0
            runner = web.AppRunner(build_proxy_app(guard, self.upstream_port,
                                                   self._upstream_secret),
                                   access_log=None, handle_signals=False)
            await runner.setup()
            site = web.TCPSite(runner, self._host, self._port, reuse_address=True)
            try:
                await site.start()
            except BaseException:
                await runner.cleanup()  # closes the upstream client session too
                raise
            sockets = site._server.sockets if site._server else ()  # type: ignore[union-attr]
            if sockets:
                guard.port = int(sockets[0].getsockname()[1])
            self._runner, self.guard = runner, guard

        def run() -> None:
            asyncio.set_event_loop(loop)
            try:
                loop.run_until_complete(boot())
            except BaseException as exc:  # reported to the caller of start()
                errors.append(exc)
                ready.set()
                return
            ready.set()
            loop.run_forever()
            loop.run_until_complete(self._runner.cleanup() if self._runner else asyncio.sleep(0))
            loop.close()

        self._thread = threading.Thread(target=run, name="lasercal-guard", daemon=True)
        self._thread.start()
        ready.wait(30)
        if errors:
            self.stop()
            exc = errors[0]
            from calib_core.errors import InputError
            raise InputError(f"cannot listen on {self._host}:{self._port}: {exc}") from exc
        assert self.guard is not None
        return self.guard

    def announce(self, stream=None) -> None:
        """Print the tokenised URL on its own line (and a warning for a non-loopback host)."""
        out = stream or sys.stdout
        assert self.guard is not None
        if not is_loopback(self._host):
            sys.stderr.write(
                f"warning: listening on {self._host}, reachable from other machines; anyone "
                "with the URL and token can move the robot\n")
        out.write("lasercal dashboard: open this URL in a browser (Ctrl-C stops the server)\n")
        out.write(f"{self.guard.url}\n")
        out.flush()

    def stop(self) -> None:
        """Stop the proxy and viser."""
        if self._loop is not None and self._loop.is_running():
            self._loop.call_soon_threadsafe(self._loop.stop)
        if self._thread is not None:
            self._thread.join(timeout=5)
        import io
        with contextlib.suppress(Exception), contextlib.redirect_stdout(io.StringIO()):
            self.viser.stop()
