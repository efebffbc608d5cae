"""The page and its server without a browser: the [view] section, the document a session
gets (bad input said plainly), the token, and the JavaScript served from the wheel."""

import asyncio
import json
import threading
import time
import urllib.error
import urllib.request
import weakref

import pytest

from pipeline.stream.topology import TopologyError, load_topology

pytest.importorskip("bokeh")


def topo_text(tmp_path, view=""):
    (tmp_path / "s.toml").write_text('name = "s"\n[sensor]\nn_pixels = 16\n')
    return f"""
[daemon]
state = "{tmp_path / 'state'}"
[source]
kind = "sim"
scene = "{tmp_path / 's.toml'}"
[histogram]
artifacts = "count-as-hits"
[sink]
out = "{tmp_path / 'out'}"
{view}"""


def test_the_view_section_is_read_and_checked(tmp_path):
    path = tmp_path / "t.toml"
    path.write_text(topo_text(tmp_path))
    assert load_topology(path).view is None
    path.write_text(topo_text(tmp_path, '[view]\nport = 0\nlayout = "8x2"\n'))
    topo = load_topology(path, "r")
    assert topo.view == {"port": 0, "bind": "127.0.0.1", "layout": "8x2"}
    from pipeline.stream.sidecar import view_args

    assert view_args(topo)[1:] == [
        "--state", str(topo.state), "--out", str(tmp_path / "out"), "--run", "r", "--port", "0",
        "--bind", "127.0.0.1", "--layout", "8x2"]
    for bad in ('port = 70000', 'port = "x"', 'layout = "16"', 'colour = "red"'):
        path.write_text(topo_text(tmp_path, f"[view]\n{bad}\n"))
        with pytest.raises(TopologyError, match=r"\[view\]"):
            load_topology(path)


def model_on(tmp_path, run=None):
    from pipeline.view.model import ViewModel

    m = ViewModel(tmp_path / "state", tmp_path / "out", None, run, feed=False)
    m.refresh()
    return m


def page_of(model, token=None, args=None):
    from bokeh.document import Document

    from pipeline.view.page import make_document

    class Ctx:  # what Bokeh's session context offers the page
        request = type("R", (), {"arguments": args or {}})()

    doc, ctx = Document(), Ctx()
    doc._session_context = weakref.ref(ctx)
    make_document(model, token)(doc)
    doc._ctx = ctx  # (kept alive with the document)
    return doc


def texts(doc) -> str:
    from bokeh.models import Div

    return " ".join(d.text for d in doc.select({"type": Div}))


def test_nothing_anywhere_is_said_plainly(tmp_path):
    doc = page_of(model_on(tmp_path))
    t = texts(doc)
    assert "No daemon status" in t and "No run under" in t


def test_a_missing_run_and_an_empty_one(tmp_path, vd):
    t = texts(page_of(model_on(tmp_path, run="ghost")))
    assert "ghost: not found" in t
    (tmp_path / "state").mkdir()
    (tmp_path / "state" / "status.json").write_text(json.dumps(vd.status(time.time())))
    t = texts(page_of(model_on(tmp_path)))  # the daemon's run, nothing written yet
    assert f"Run {vd.RUN} running" in t and "no measurement written yet" in t


def test_the_page_follows_the_newest_measurement_and_a_daemon_that_dies(tmp_path, vd,
                                                                       monkeypatch):
    monkeypatch.setattr("pipeline.view.page.SENSOR_EVERY_S", 0.0)
    out = tmp_path / "out"
    (tmp_path / "state").mkdir()
    st = tmp_path / "state" / "status.json"
    st.write_text(json.dumps(vd.status(time.time(), source={"pid": 1, "health": "ok",
                                                         "restarts": 0})))
    for first in (0, 8):
        vd.write_part(out, vd.RUN, 0, first, vd.hits_for(8))
    model = model_on(tmp_path)
    doc = page_of(model)
    page = doc._ctx  # noqa: F841 - keeps the session context alive
    assert f"{vd.RUN}-m000000" in texts(doc) and "RUNNING" in texts(doc)
    for first in (0, 8):
        vd.write_part(out, vd.RUN, 1, first, vd.hits_for(8))
    st.write_text(json.dumps({**vd.status(time.time() - 30), "pid": 2**22 + 12345}))
    model.refresh()
    [cb.callback() for cb in doc.session_callbacks]  # the page's once-a-second update
    t = texts(doc)
    assert f"{vd.RUN}-m000001" in t and "LOST" in t and "is gone" in t
    st.write_text(json.dumps(vd.status(time.time())))  # the daemon is back
    model.refresh()
    [cb.callback() for cb in doc.session_callbacks]
    assert "RUNNING" in texts(doc)


def test_a_page_without_the_token_is_refused(tmp_path):
    m = model_on(tmp_path)
    assert "Forbidden" in texts(page_of(m, token="s3cret"))
    assert "Forbidden" not in texts(page_of(m, token="s3cret", args={"token": [b"s3cret"]}))


@pytest.fixture
def server(tmp_path):
    """``server(token=None)``: a view server in a thread; returns its URL."""
    from pipeline.view.server import make_server

    stops = []

    def start(token=None):
        got = {}

        def run():
            asyncio.set_event_loop(asyncio.new_event_loop())
            srv, url = make_server(model_on(tmp_path), 0, "127.0.0.1", token=token)
            got["url"], got["loop"] = url, srv.io_loop
            srv.io_loop.start()
            srv.stop()

        t = threading.Thread(target=run, daemon=True)
        t.start()
        deadline = time.time() + 30
        while "url" not in got and time.time() < deadline:
            time.sleep(0.05)
        stops.append((got["loop"], t))
        return got["url"]

    yield start
    for loop, t in stops:
        loop.add_callback(loop.stop)
        t.join(10)


def get(url):
    try:
        with urllib.request.urlopen(url, timeout=20) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, ""


def test_the_page_s_javascript_comes_from_the_server_not_a_cdn(server):
    url = server()
    code, html = get(url)
    assert code == 200 and "tcspc view" in html
    scripts = [line for line in html.splitlines() if "<script src=" in line]
    assert scripts and all('src="/static/' in s for s in scripts), scripts
    base, token = url.split("?token=")  # (a token on loopback too: issue 36)
    code, js = get(base + "static/js/bokeh.min.js")
    assert code == 200 and len(js) > 100_000
    assert get(base + "alive")[0] == 403
    assert get(base + "alive?token=" + token)[0] == 200


def test_alive_needs_the_token_when_there_is_one(server):
    url = server(token="tok")
    assert url.endswith("?token=tok")
    base = url.split("?")[0]
    assert get(base + "alive")[0] == 403
    assert get(base + "alive?token=tok")[0] == 200


def test_with_no_page_open_only_the_status_is_read(tmp_path, vd):
    from pipeline.view.model import IDLE_S, ViewModel

    for first in (0, 8):
        vd.write_part(tmp_path / "out", vd.RUN, 0, first, vd.hits_for(8))
    m = ViewModel(tmp_path / "state", tmp_path / "out", None, feed=False)
    m.refresh(now=time.time() + IDLE_S + 1)
    assert m.runs == [] and m.tracks == {}
    doc = page_of(m)  # a page opens: everything is read at once
    assert f"{vd.RUN}-m000000" in texts(doc) and [r["run"] for r in m.runs] == [vd.RUN]
