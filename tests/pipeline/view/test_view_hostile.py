"""Issue 36, point 4: the page on loopback, tried as another local account and as a web page
of another site would: no token, a DNS-rebound Host, a websocket Origin equal to its Host or
sent with Sec-Fetch-Site, a run picker given a path, a FIFO or a huge part among the files."""

from __future__ import annotations

import asyncio
import os
import re
import threading
import time
import urllib.error
import urllib.request
import weakref

import pytest


def _model(tmp_path, run=None):
    from pipeline.view.model import ViewModel

    m = ViewModel(tmp_path / "state", tmp_path / "out", None, run, feed=False)
    m.refresh()
    return m


@pytest.fixture
def served(tmp_path):
    """A view server on 127.0.0.1 started with no token given: ``(url, port)``."""
    from pipeline.view.server import make_server

    got = {}

    def run():
        asyncio.set_event_loop(asyncio.new_event_loop())
        srv, url = make_server(_model(tmp_path), 0, "127.0.0.1")
        got["url"], got["loop"] = url, srv.io_loop
        srv.io_loop.start()
        srv.stop()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    deadline = time.time() + 30
    while "url" not in got and time.time() < deadline:
        time.sleep(0.05)
    yield got["url"], int(re.search(r":(\d+)/", got["url"]).group(1))
    got["loop"].add_callback(got["loop"].stop)
    t.join(10)


def _get(url, headers=None):
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers or {}),
                                    timeout=20) as r:
            return r.status, r.read().decode(), r.headers
    except urllib.error.HTTPError as exc:
        return exc.code, "", exc.headers


def _ws(port, session, headers):
    from tornado.httpclient import HTTPRequest
    from tornado.ioloop import IOLoop
    from tornado.websocket import websocket_connect

    async def go():
        conn = await websocket_connect(
            HTTPRequest(f"ws://127.0.0.1:{port}/ws", headers=headers, request_timeout=20),
            subprotocols=["bokeh", session])
        msg = await conn.read_message()
        conn.close()
        return msg

    try:
        return IOLoop.current().run_sync(go, timeout=30)
    except Exception as exc:  # noqa: BLE001 - the refusal, whatever form it takes
        return exc


def test_loopback_has_a_token_too(served):
    """Before: on 127.0.0.1 there was no token: any local account read the daemon's status
    and datasets though STATE is 0700."""
    url, _ = served
    assert "?token=" in url
    base = url.split("?")[0]
    for route in ("", "alive", "metadata"):
        assert _get(base + route)[0] == 403, route
    assert _get(url)[0] == 200


def test_a_dns_rebound_host_and_a_hostile_origin_are_refused(served):
    """Before: `GET /` answered any Host (DNS rebinding), and a websocket whose Origin equals
    its Host, or that sends Sec-Fetch-Site: same-origin, was taken from evil.example."""
    url, port = served
    evil = f"evil.example:{port}"
    assert _get(url, {"Host": evil})[0] == 403
    status, body, headers = _get(url)
    assert status == 200
    cookie = headers["Set-Cookie"].split(";")[0]
    session = re.search(r'"token":"([^"]+)"', body).group(1)
    for hdrs in ({"Host": evil, "Origin": f"http://{evil}"},
                 {"Origin": f"http://{evil}", "Sec-Fetch-Site": "same-origin"},
                 {"Host": evil, "Origin": f"http://{evil}", "Sec-Fetch-Site": "same-origin"}):
        got = _ws(port, session, {**hdrs, "Cookie": cookie})
        assert not isinstance(got, (str, bytes)), hdrs
    ok = _ws(port, session, {"Origin": f"http://127.0.0.1:{port}", "Cookie": cookie})
    assert isinstance(ok, (str, bytes))


def test_the_run_picker_takes_only_runs_found(tmp_path):
    """Before: the picker's value (from the websocket) was taken as a path: `../..` reached
    another run's histograms."""
    from bokeh.document import Document
    from bokeh.models import Select

    from pipeline.view.page import make_document

    m = _model(tmp_path)

    class Ctx:
        request = type("R", (), {"arguments": {}})()

    doc, ctx = Document(), Ctx()
    doc._session_context = weakref.ref(ctx)
    make_document(m, None)(doc)
    pick = next(s for s in doc.select({"type": Select}) if "Run" in (s.title or ""))
    for bad in ("../..", "../../other/run=x", "/etc", "r\x00"):
        pick.value = bad
    assert not any(k.startswith(("..", "/")) or "\x00" in k for k in m.tracks), m.tracks
    assert not m.run_known("../..")


def test_a_fifo_or_a_huge_part_is_not_read(tmp_path):
    """Before: a named pipe among a run's parts hung the server for every viewer, and a
    1 GiB sparse file took it to 2.4 GB."""
    from pipeline.view import datasets

    d = tmp_path / "out" / "histograms" / "date=2026-01-01" / "run=r"
    d.mkdir(parents=True)
    os.mkfifo(d / "part-000000-t000.parquet")
    with open(d / "part-000001-t000.parquet", "wb") as fh:
        fh.truncate(datasets.MAX_PART_BYTES + 1)
    idx = datasets.RunIndex(tmp_path / "out", "r", 16)
    idx.refresh()
    assert idx.files("histograms", 0) == [] and idx.files("histograms", 1) == []
    (tmp_path / "state").mkdir()
    os.mkfifo(tmp_path / "state" / "status.json")
    from pipeline.view.status import read_status

    assert read_status(tmp_path / "state") is None  # (returns at once, no block)
