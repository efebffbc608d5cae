"""The page's server: Bokeh's (Tornado) server on one port, its JavaScript served from the
bokeh wheel itself (no CDN, no internet), the model refreshed once a second on its event
loop, and ``/alive`` for the page to notice the server is gone.

Loopback by default; on any address, loopback included (every local account can reach a
loopback port), every route needs the ``token`` of the URL in ``STATE/view.url`` (mode
0600): the page, ``/alive``, Bokeh's ``/ws``, ``/metadata`` and ``/autoload.js`` (an auth
provider: the token in the query, or the HttpOnly, SameSite cookie the page's first load
sets, which the browser sends on the websocket too), so a Bokeh session id seen in a page
does not join its session without the token. Every such request's ``Host`` must name an
address the page serves (a DNS-rebound name is refused) and the websocket's ``Origin`` must
be one of them too, whatever ``Sec-Fetch-Site`` says (its names and addresses, or
``$BOKEH_ALLOW_WS_ORIGIN``). Only Bokeh's own static JavaScript is served without them.
"""

from __future__ import annotations

import ipaddress
import json
import os
import secrets
from pathlib import Path

LOOPBACK_NAMES = {"localhost", "ip6-localhost"}


def is_loopback(host: str) -> bool:
    if host in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def page_url(host: str, port: int, token: str | None) -> str:
    shown = "127.0.0.1" if host in ("", "0.0.0.0") else host
    shown = f"[{shown}]" if ":" in shown else shown
    return f"http://{shown}:{port}/" + (f"?token={token}" if token else "")


def write_url(state: Path, url: str) -> Path | None:
    """STATE/view.url (0600): where an operator finds the page's URL and its token."""
    try:
        state.mkdir(parents=True, exist_ok=True)
        path = state / "view.url"
        # (never through a link: one planted there would choose the file truncated)
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC | os.O_NOFOLLOW, 0o600)
        with os.fdopen(fd, "w") as fh:
            os.fchmod(fh.fileno(), 0o600)
            fh.write(url + "\n")
        return path
    except OSError:
        return None


def make_server(model, port: int = 5006, bind: str = "127.0.0.1", token: str | None = None,
                refresh_ms: int = 1000):
    """A started (not yet looping) Bokeh server for ``model``; ``token`` None: one is made
    (on loopback too). Returns ``(server, url)``."""

    from bokeh.application import Application
    from bokeh.application.handlers.function import FunctionHandler
    from bokeh.server.server import Server
    from tornado.ioloop import PeriodicCallback
    from tornado.web import RequestHandler

    from pipeline.view.page import make_document

    token = token or secrets.token_urlsafe(24)
    port = port or _free_port(bind)
    origins = ws_origins(bind, port)
    auth = TokenAuth(token, origins)

    class Alive(RequestHandler):
        def get(self):
            if auth.user(self) is None:
                self.set_status(403)
                return
            self.set_header("Cache-Control", "no-store")
            self.write(json.dumps({"ok": True, "updated": model.updated}))

    server = Server({"/": Application(FunctionHandler(make_document(model, token)))},
                    port=port, address=bind, allow_websocket_origin=origins,
                    extra_patterns=[("/alive", Alive)], check_unused_sessions_milliseconds=5000,
                    unused_session_lifetime_milliseconds=15000, auth_provider=auth)
    server.start()
    model.warm()
    model.refresh()
    PeriodicCallback(_safe(model.refresh), refresh_ms).start()
    return server, page_url(bind, server.port, token)


def _token_auth_class():
    from bokeh.server.auth_provider import AuthProvider
    from tornado.web import RequestHandler
    from tornado.websocket import WebSocketHandler

    from pipeline.view.page import COOKIE

    class Forbidden(RequestHandler):
        def get(self):
            self.set_status(403)
            self.set_header("Cache-Control", "no-store")
            self.write("<h1>Forbidden</h1><p>This page needs the token of its URL "
                       "(STATE/view.url).</p>")

    class _TokenAuth(AuthProvider):
        """Bokeh's hook on every session route (page, /ws, /metadata, /autoload.js): the
        user is known when the request names a served address in its Host (and, on the
        websocket, in its Origin) and carries the token, in the query or the cookie."""

        def __init__(self, token: str, hosts: list[str]):
            self.token = token
            self.hosts = {h.lower() for h in hosts}
            super().__init__()

        @property
        def get_user(self):
            return self.user

        @property
        def login_url(self):
            return "/forbidden"

        @property
        def login_handler(self):
            return Forbidden

        def user(self, handler):
            import hmac
            from urllib.parse import urlparse

            hosts = self.hosts | {h.strip().lower() for h in os.environ.get(
                "BOKEH_ALLOW_WS_ORIGIN", "").split(",") if h.strip()}
            if handler.request.host.lower() not in hosts:
                return None  # (DNS rebinding: a name of the attacker's for our address)
            if isinstance(handler, WebSocketHandler) or \
                    handler.request.headers.get("Upgrade", "").lower() == "websocket":
                origin = handler.request.headers.get("Origin", "")
                if urlparse(origin).netloc.lower() not in hosts:
                    return None  # (tornado skips its check when Origin equals Host)
            query = handler.get_argument("token", None)
            for got in (query, handler.get_cookie(COOKIE)):
                if got and hmac.compare_digest(got.encode(), self.token.encode()):
                    if got is query and not isinstance(handler, WebSocketHandler):
                        # the websocket carries no query: the browser sends this instead
                        handler.set_cookie(COOKIE, got, httponly=True, samesite="Strict",
                                           path="/")
                    return "operator"
            return None

    return _TokenAuth


def TokenAuth(token: str, hosts: list[str]):  # noqa: N802 - made on first use (bokeh)
    """The auth provider that asks every session route for ``token`` and a Host (and a
    websocket's Origin) among ``hosts`` (``host:port``)."""
    return _token_auth_class()(token, hosts)


def ws_origins(bind: str, port: int) -> list[str]:
    """The websocket Origins allowed (``host:port``): the loopback names, the address bound,
    and on a non-loopback address this host's names and addresses (a page from any other
    origin cannot open the websocket)."""
    import socket

    # (IPv6 literals are left out: Bokeh's allowlist parses HOST:PORT on the first colon)
    hosts = {"localhost", "127.0.0.1"}
    if bind not in ("", "0.0.0.0") and ":" not in bind:
        hosts.add(bind)
    if not is_loopback(bind):
        names = {socket.gethostname(), socket.getfqdn()}
        hosts |= names
        for name in names:
            try:
                hosts |= {a[0] for *_, a in socket.getaddrinfo(name, None, socket.AF_INET)}
            except OSError:
                pass
    return sorted(f"{h}:{port}" for h in hosts)


def _free_port(bind: str) -> int:
    import socket

    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as s:
        s.bind((bind, 0))
        return s.getsockname()[1]


def _safe(fn):
    """A refresh that fails (a file half there, a disk error) is logged and tried again."""
    import logging

    log = logging.getLogger("tcspc.view")

    def call():
        try:
            fn()
        except Exception:  # noqa: BLE001 - the page must outlive one bad refresh
            log.exception("refresh failed; trying again in a second")

    return call
