"""The page's server: Bokeh's (Tornado) server on one port, its JavaScript served from the
bokeh wheel itself (no CDN, no internet), the model refreshed once a second on its event
loop, and ``/alive`` for the page to notice the server is gone.

Loopback by default; bound to any other address, every page and ``/alive`` need the
``token`` of the printed URL (also written to ``STATE/view.url``, mode 0600).
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
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(url + "\n")
        os.chmod(path, 0o600)
        return path
    except OSError:
        return None


def make_server(model, port: int = 5006, bind: str = "127.0.0.1", token: str | None = None,
                refresh_ms: int = 1000):
    """A started (not yet looping) Bokeh server for ``model``; ``token`` None on loopback
    (one is made for any other address). Returns ``(server, url)``."""
    import hmac

    from bokeh.application import Application
    from bokeh.application.handlers.function import FunctionHandler
    from bokeh.server.server import Server
    from tornado.ioloop import PeriodicCallback
    from tornado.web import RequestHandler

    from pipeline.view.page import make_document

    if token is None and not is_loopback(bind):
        token = secrets.token_urlsafe(24)

    class Alive(RequestHandler):
        def get(self):
            got = self.get_argument("token", "")
            if token is not None and not hmac.compare_digest(got.encode(), token.encode()):
                self.set_status(403)
                return
            self.set_header("Cache-Control", "no-store")
            self.write(json.dumps({"ok": True, "updated": model.updated}))

    port = port or _free_port(bind)
    # the browser's Origin: the loopback names on loopback; any with a token (it guards)
    origins = [f"{h}:{port}" for h in ("localhost", "127.0.0.1", bind)] if token is None \
        else ["*"]
    server = Server({"/": Application(FunctionHandler(make_document(model, token)))},
                    port=port, address=bind, allow_websocket_origin=origins,
                    extra_patterns=[("/alive", Alive)], check_unused_sessions_milliseconds=5000,
                    unused_session_lifetime_milliseconds=15000)
    server.start()
    model.warm()
    model.refresh()
    PeriodicCallback(_safe(model.refresh), refresh_ms).start()
    return server, page_url(bind, server.port, token)


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
