"""The page in a real browser (Debian's headless chromium, driven by Playwright): a daemon on a
small simulated scene starts the page with its [view] section; what the page shows must be
what status.json and the datasets say. Then a page started on its own watches a daemon die
and come back. Slow: ``pytest -m slow tests/pipeline/view``."""

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import polars as pl
import pytest

pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
N = 16
SCENE = """
name = "small"
[sensor]
n_pixels = 16
[gate]
t_laser_win_ns = 140.0
delay_ns = 100.0
[[targets]]
pixels = [0, 9]
distance_m = 1.5
reflectivity = 0.002
surface = "mirror"
[[targets]]
pixels = [10, 15]
distance_m = 2.5
reflectivity = 0.004
surface = "mirror"
[[ambient]]
kind = "lux"
lux = 1071.599
"""


@pytest.fixture(scope="module")
def browser():
    sync_api = pytest.importorskip(
        "playwright.sync_api", reason="the browser test needs playwright (pip install -e "
                                      "'.[view-test]')")
    if not os.path.exists(CHROMIUM):
        pytest.skip("the browser test needs Debian's chromium (apt-get install chromium)")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        yield b
        b.close()


def topology(tmp_path, caldir, cycles, rate, view=True):
    (tmp_path / "small.toml").write_text(SCENE)
    text = f"""
[daemon]
state = "{tmp_path / 'state'}"
restarts = 3
[source]
kind = "sim"
scene = "{tmp_path / 'small.toml'}"
cycles = {cycles}
seed = 5
rate = {rate}
[histogram]
workers = 2
measurement_cycles = 10000
calibration = "{caldir}"
[range]
calibration = "{caldir}"
[sink]
out = "{tmp_path / 'out'}"
"""
    if view:
        text += '[view]\nport = 0\nlayout = "8x2"\n'
    path = tmp_path / "topo.toml"
    path.write_text(text)
    return path


def tcspc(*args, **kw):
    return subprocess.Popen([sys.executable, "-m", "pipeline.cli", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, **kw)


def wait_for(what, fn, timeout=60.0, every=0.25):
    deadline = time.time() + timeout
    while time.time() < deadline:
        got = fn()
        if got:
            return got
        time.sleep(every)
    raise AssertionError(f"timed out waiting for {what}")


def field(page, name):
    loc = page.locator(f'[data-field="{name}"]')
    return loc.first.inner_text() if loc.count() else None


def kind(page):
    loc = page.locator('[data-field="daemon-state"]')
    return loc.first.get_attribute("data-kind") if loc.count() else None


def health(page) -> dict:
    """stage -> {health, pid, restarts} as the page shows them."""
    out = {}
    for row in page.locator("tr[data-stage]").all():
        out[row.get_attribute("data-stage")] = {
            k: row.locator(f'td[data-field="{k}"]').inner_text()
            for k in ("health", "pid", "restarts", "queue", "rejected")}
    return out


def num(text):
    return int(re.sub(r"[^\d-]", "", text))


def top(page, locator) -> float:
    """The element's top on the page (retried: a Div the server just changed is redrawn)."""
    return wait_for(f"{locator}", lambda: (locator.bounding_box() or {}).get("y"), 10, 0.1) \
        + page.evaluate("window.scrollY")


def shoot_panels(page, out: Path, prefix: str) -> list[Path]:
    """One screenshot per panel (the page's three sections, the banner with the health)."""
    page.screenshot(path=str(out / f"{prefix}full.png"), full_page=True)
    tops = [top(page, page.locator("h2", has_text=t).first)
            for t in ("1. Health", "2. Sensor", "3. Calibration")]
    full = page.evaluate("document.documentElement.scrollHeight")
    start = top(page, page.locator('[data-field="daemon-state"]').first) - 8
    spans = [(start, tops[1]), (tops[1], tops[2]), (tops[2], full)]
    paths = []
    for name, (a, b) in zip(("health", "sensor", "calibration"), spans, strict=True):
        p = out / f"{prefix}{name}.png"
        page.screenshot(path=str(p), full_page=True,
                        clip={"x": 0, "y": a, "width": 1240, "height": b - a})
        paths.append(p)
    return paths


def dataset(out, schema, run):
    return pl.read_parquet(out / schema / "date=*" / f"run={run}" / "*.parquet")


def test_the_page_shows_what_the_daemon_and_the_datasets_say(tmp_path, browser, caldir):
    topo = topology(tmp_path, caldir, cycles=160_000, rate=160_000)  # ~16 s of data
    state, out = tmp_path / "state", tmp_path / "out"
    daemon = tcspc("daemon", "--config", topo, "--run", "vt")
    try:
        url = wait_for("the daemon's view", lambda: (state / "view.url").exists()
                       and (state / "view.url").read_text().strip(), 60)
        page = browser.new_page(viewport={"width": 1240, "height": 900})
        outside = []
        page.on("request", lambda r: None if r.url.startswith(("http://127.0.0.1",
                                                               "ws://127.0.0.1", "data:"))
                else outside.append(r.url))
        page.goto(url)
        wait_for("a running daemon on the page", lambda: kind(page) == "running", 60)
        # live data: measurements, ranges and the histogram's return mark
        wait_for("a measurement with ranges", lambda: (field(page, "distance") or "").strip(),
                 60)
        wait_for("heartbeats", lambda: all(h["pid"].isdigit() for h in health(page).values())
                 and len(health(page)) == 5, 30)
        st = json.loads((state / "status.json").read_text())
        for name, shown in health(page).items():
            assert num(shown["pid"]) == st["stages"][name]["pid"], name
            assert num(shown["restarts"]) == st["stages"][name]["restarts"], name
        meas = field(page, "measurement")
        name = re.search(r"(vt-m\d{6})", meas).group(1)
        r = dataset(out, "ranges", "vt").filter(pl.col("measurement") == name)
        assert num(field(page, "detected")) == int(r["detected"].sum())
        tdc = num(field(page, "tdc"))
        row = r.filter(pl.col("tdc") == tdc)
        assert float(field(page, "distance")) == pytest.approx(row["distance_m"][0], abs=5e-4)
        assert (tmp_path / "shots").mkdir() is None
        paths = shoot_panels(page, tmp_path / "shots", "live-")
        print("screenshots:", *paths)
        # the end of the run: the accounting identity, as the accounting file says it
        assert daemon.wait(timeout=240) == 0, daemon.stdout.read()
        assert outside == [], f"the page reached outside the machine: {outside}"
    finally:
        if daemon.poll() is None:
            daemon.kill()
    acc = json.loads((out / "accounting" / "run=vt.json").read_text())
    assert acc["balanced"]
    # the daemon's view ended with it: a page started on its own shows the finished run
    view = tcspc("view", "--state", state, "--out", out, "--calibration", caldir,
                 "--port", 0, "--run", "vt", "--layout", "8x2")
    try:
        url = view.stdout.readline().strip()
        page = browser.new_page(viewport={"width": 1240, "height": 900})
        page.goto(url)
        wait_for("the finished run", lambda: kind(page) == "finished", 30)
        wait_for("the final identity", lambda: page.locator(
            '[data-field="identity"][data-holds="true"]').count(), 30)
        assert num(field(page, "journaled")) == acc["words_in"]
        for c, v in acc["classes"].items():
            assert num(field(page, f"n_{c}")) == v
        assert all(h["health"] == "finished" for h in health(page).values())
        shoot_panels(page, tmp_path / "shots", "finished-")
    finally:
        view.send_signal(signal.SIGTERM)
        assert view.wait(timeout=20) == 0


def test_the_page_says_the_daemon_died_and_recovers_when_it_is_back(tmp_path, browser,
                                                                    caldir):
    topo = topology(tmp_path, caldir, cycles=200_000, rate=100_000, view=False)
    state, out = tmp_path / "state", tmp_path / "out"
    view = tcspc("view", "--state", state, "--out", out, "--calibration", caldir, "--port", 0)
    daemon = None
    try:
        url = view.stdout.readline().strip()
        page = browser.new_page(viewport={"width": 1240, "height": 900})
        page.goto(url)
        wait_for("no daemon yet", lambda: kind(page) == "absent", 30)
        assert "No daemon status" in field(page, "daemon-state")
        daemon = tcspc("daemon", "--config", topo, "--run", "vk")
        wait_for("the daemon", lambda: kind(page) == "running", 60)
        wait_for("a measurement", lambda: "vk-m" in (field(page, "measurement") or ""), 60)
        daemon.send_signal(signal.SIGKILL)  # its stages die with it
        daemon.wait()
        wait_for("the page saying so", lambda: kind(page) == "lost", 30)
        text = field(page, "daemon-state")
        assert "is gone" in text and "same --run" in text
        page.screenshot(path=str(tmp_path / "lost.png"))
        daemon = tcspc("daemon", "--config", topo, "--run", "vk")  # back, resuming the run
        wait_for("the page recovering", lambda: kind(page) == "running", 60)
        assert daemon.wait(timeout=300) == 0
        wait_for("the finished run", lambda: kind(page) == "finished", 30)
        wait_for("the final identity", lambda: page.locator(
            '[data-field="identity"][data-holds="true"]').count(), 30)
        # the server itself gone: the page says so (and reloads when it is back)
        view.send_signal(signal.SIGTERM)
        assert view.wait(timeout=20) == 0
        wait_for("the server-lost notice", lambda: page.locator("#server-lost").is_visible(),
                 15)
        assert "not answering" in page.locator("#server-lost").inner_text()
    finally:
        for p in (view, daemon):
            if p is not None and p.poll() is None:
                p.kill()


def test_with_a_token_the_page_opens_with_it_and_only_with_it(tmp_path, browser):
    """Token mode (any address but loopback; here forced on loopback): a real browser opens
    the page from its URL with the token, and its websocket joins with the cookie that URL
    set (the page comes alive); a fresh browser without the token gets the refusal, and
    neither the page nor its websocket works."""
    script = ("import sys; from pathlib import Path\n"
              "from pipeline.view.model import ViewModel\n"
              "from pipeline.view.server import make_server\n"
              "s, url = make_server(ViewModel(Path(sys.argv[1]), Path(sys.argv[2]), None, "
              "None, None), 0, '127.0.0.1', token='tok-' + 'x' * 20)\n"
              "print(url, flush=True); s.io_loop.start()\n")
    view = subprocess.Popen([sys.executable, "-c", script, tmp_path / "state",
                             tmp_path / "out"], stdout=subprocess.PIPE, text=True)
    try:
        url = view.stdout.readline().strip()
        assert "?token=tok-" in url
        bare = url.split("?")[0]
        stranger = browser.new_context().new_page()
        resp = stranger.goto(bare)
        assert resp.status == 403 and "needs the token" in stranger.content()
        owner = browser.new_context(viewport={"width": 1240, "height": 900}).new_page()
        owner.goto(url)
        # the page is alive: the server's first update over the websocket arrives
        wait_for("the page's state over its websocket", lambda: kind(owner) == "absent", 60)
        owner.goto(bare)  # the cookie the token set carries a reload without it
        wait_for("the page again, by its cookie", lambda: kind(owner) == "absent", 60)
        assert stranger.goto(bare).status == 403
    finally:
        view.kill()
        view.wait()
