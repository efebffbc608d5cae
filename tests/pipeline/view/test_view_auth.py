"""The page off loopback, probed as another local user would (issue 26.9): the token on every
route and on the websocket, the websocket's origins restricted, the token never logged."""

from __future__ import annotations

import re
import subprocess
import sys
import time
import urllib.error
import urllib.request

import pytest


@pytest.fixture(scope="module")
def page_server(tmp_path_factory):
    """``tcspc view`` bound to every interface (so with a token), its log a file."""
    d = tmp_path_factory.mktemp("view")
    (d / "state").mkdir()
    log = open(d / "view.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "view", "--state",
                             d / "state", "--out", d / "out", "--bind", "0.0.0.0", "--port",
                             "0", "--nice", "0"], stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.time() + 60
        while not (d / "state" / "view.url").exists():
            assert proc.poll() is None, (d / "view.log").read_text()
            assert time.time() < deadline, "the page never started"
            time.sleep(0.1)
        url = (d / "state" / "view.url").read_text().strip()
        token = url.split("?token=")[1]
        port = int(re.search(r":(\d+)/", url).group(1))
        yield {"dir": d, "url": url, "token": token, "port": port,
               "base": f"http://127.0.0.1:{port}"}
    finally:
        proc.terminate()
        proc.wait(timeout=10)
        log.close()


def get(url, cookie=None):
    req = urllib.request.Request(url, headers={"Cookie": cookie} if cookie else {})
    try:
        with urllib.request.urlopen(req, timeout=20) as r:
            return r.status, r.read().decode(), r.headers
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode(), exc.headers


def ws_open(port, session_token, origin=None, cookie=None):
    """Open Bokeh's websocket with ``session_token``; the server's first message (the ACK)
    when it takes the connection, else the error."""
    from tornado.httpclient import HTTPRequest
    from tornado.ioloop import IOLoop
    from tornado.websocket import websocket_connect

    headers = {**({"Origin": origin} if origin else {}), **({"Cookie": cookie} if cookie
                                                            else {})}

    async def go():
        conn = await websocket_connect(
            HTTPRequest(f"ws://127.0.0.1:{port}/ws", headers=headers, request_timeout=20),
            subprotocols=["bokeh", session_token])
        msg = await conn.read_message()
        conn.close()
        return msg

    try:
        return IOLoop.current().run_sync(go, timeout=30)
    except Exception as exc:  # noqa: BLE001 - the refusal, whatever form it takes
        return exc


def test_every_route_and_the_websocket_need_the_token(page_server):
    base, token, port = page_server["base"], page_server["token"], page_server["port"]
    for route in ("/", "/alive", "/metadata", "/autoload.js?bokeh-autoload-element=x"):
        status, body, _ = get(base + route)
        assert status == 403, (route, status)
    status, body, _ = get(f"{base}/?token={'x' * len(token)}")
    assert status == 403
    status, body, headers = get(f"{base}/?token={token}")
    assert status == 200
    cookie = headers["Set-Cookie"].split(";")[0]
    assert "httponly" in headers["Set-Cookie"].lower()
    assert get(f"{base}/alive", cookie)[0] == 200
    session = re.search(r'"token":"([^"]+)"', body).group(1)  # what the page's HTML shows
    origin = f"http://127.0.0.1:{port}"
    # the session id seen in the HTML, without the page's token: refused
    assert not isinstance(ws_open(port, session, origin), str)
    # a page of another origin, even with the cookie: refused
    assert not isinstance(ws_open(port, session, "http://evil.example", cookie), str)
    # the page itself (its origin, the cookie its first load set): taken
    assert isinstance(ws_open(port, session, origin, cookie), (str, bytes))


def test_the_token_is_never_logged(page_server):
    time.sleep(0.5)
    log = (page_server["dir"] / "view.log").read_text()
    assert "view.url" in log and page_server["token"] not in log
