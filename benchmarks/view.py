"""What the live web page costs the data path: the daemon's throughput with no page, with
the page's server running (``tcspc view`` on the daemon's state and datasets), and with the
page open in a headless browser (Debian's chromium through Playwright) following the run;
runs interleaved, the median of each kept. With ``--screenshots DIR`` it instead runs the
street scene live (the demo's calibration) and saves one screenshot per panel of the page.

    python benchmarks/view.py [--words 128e6] [--repeat 3] [--calibration data/calibration/current]
    python benchmarks/view.py --screenshots docs/img --calibration data/calibration/current
"""

from __future__ import annotations

import argparse
import json
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from benchmarks.stream import run_daemon  # noqa: E402

CHROMIUM = "/usr/bin/chromium"
TAGS = {"no page": "none", "view server, no page open": "server",
        "view server, page open": "page"}
ROOT = Path(__file__).resolve().parents[1]


def tcspc(*args) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "pipeline.cli", *map(str, args)],
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process so far (its threads included)."""
    import os

    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def browser_cpu_s() -> float:
    """CPU seconds so far of every chromium process on the machine (the page's browser)."""
    total = 0.0
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            if b"chromium" not in (d / "cmdline").read_bytes().split(b"\0")[0]:
                continue
            total += cpu_s(int(d.name))
        except (OSError, IndexError, ValueError):
            continue
    return total


def with_view(tmp: Path, capture: Path, calibration: str | None, tag: str, browser=None):
    """One daemon run with ``tcspc view`` on its state (and a page open when ``browser``)."""
    state, out = tmp / f"state-{tag}", tmp / f"out-{tag}"
    state.mkdir(parents=True)
    view = tcspc("view", "--state", state, "--out", out, "--port", 0,
                 *(("--calibration", calibration) if calibration else ()))
    page = None
    try:
        url = view.stdout.readline().strip()
        if browser is not None:
            page = browser.new_page(viewport={"width": 1240, "height": 900})
            page.goto(url)
            page.wait_for_selector('[data-field="daemon-state"]', timeout=60_000)
        cpu0, b0 = cpu_s(view.pid), browser_cpu_s()
        secs, startup, res = run_daemon(tmp, capture, 2, calibration, tag)
        res["view_cpu_s"] = cpu_s(view.pid) - cpu0
        res["browser_cpu_s"] = browser_cpu_s() - b0
        if page is not None:
            shown = page.locator('[data-field="measurement"]')
            res["page_followed"] = shown.count() and tag in shown.first.inner_text()
        return secs, startup, res
    finally:
        if page is not None:
            page.close()
        view.send_signal(signal.SIGTERM)
        view.wait(timeout=30)


def benchmark(args) -> None:

    from pipeline.io.capture import CaptureWriter
    from stages.testpattern import pattern_words

    calibration = args.calibration if Path(args.calibration, "tdc.parquet").exists() else None
    from playwright.sync_api import sync_playwright

    rows = {"no page": [], "view server, no page open": [], "view server, page open": []}
    with tempfile.TemporaryDirectory(dir=Path.cwd()) as d, sync_playwright() as pw:
        tmp = Path(d)
        block, _ = pattern_words((1 << 22) // 128, 128, hit_prob=0.18, rng=1)
        n = int(args.words) // block.size
        with CaptureWriter(tmp / "cap", 128, window_ns=80.0, t_laser_win_ns=200.0) as w:
            for _ in range(n):
                w.write(block)
        words = n * block.size
        browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
        followed, view_cpu, browser_cpu = [], {m: [] for m in rows}, []
        for i in range(args.repeat):
            for mode in rows:  # interleaved: a busy machine's drift falls on every mode
                tag = f"r{i}-{TAGS[mode]}"
                if mode == "no page":
                    secs, _, res = run_daemon(tmp, tmp / "cap", 2, calibration, tag)
                else:
                    page_open = mode == "view server, page open"
                    secs, _, res = with_view(tmp, tmp / "cap", calibration, tag,
                                             browser if page_open else None)
                    view_cpu[mode].append(res["view_cpu_s"] / secs)
                    if page_open:
                        followed.append(bool(res.get("page_followed")))
                        browser_cpu.append(res["browser_cpu_s"] / secs)
                assert res["accounting"]["balanced"], res
                rows[mode].append(words / secs / 1e6)
                print(f"{mode}: {rows[mode][-1]:.1f} M words/s; view server "
                      f"{res.get('view_cpu_s', 0):.2f} CPU s, browser "
                      f"{res.get('browser_cpu_s', 0):.2f} CPU s, in {secs:.1f} s",
                      file=sys.stderr)
        browser.close()
    base = statistics.median(rows["no page"])
    lines = [f"command: `python benchmarks/view.py --words {args.words:.3g} --repeat "
             f"{args.repeat}{' --calibration ' + args.calibration if calibration else ''}`",
             f"machine: {machine()}", "",
             f"The daemon (capture replay of {words:,} words, 2 histogram workers"
             f"{', range' if calibration else ''}, sink, journal on) from its first batch to "
             "its last dataset file; each mode run "
             f"{args.repeat} times, interleaved.", "",
             "| mode | M words/s (median) | runs | vs no page | view server's CPU |",
             "|---|---:|---|---:|---:|"]
    for mode, vals in rows.items():
        med = statistics.median(vals)
        cpu = (f"{100 * statistics.median(view_cpu[mode]):.1f} % of a core"
               if view_cpu[mode] else "-")
        lines.append(f"| {mode} | {med:.1f} | {', '.join(f'{v:.1f}' for v in vals)} | "
                     f"{100 * (med / base - 1):+.1f} % | {cpu} |")
    spread = max(rows["no page"]) - min(rows["no page"])
    lines += ["", f"Run-to-run spread without the page: {spread:.1f} M words/s "
                  f"({100 * spread / base:.0f} % of the median). The open page followed the "
                  f"daemon's run in {sum(followed)} of {len(followed)} runs; the headless "
                  f"browser showing it took {100 * statistics.median(browser_cpu):.1f} % of a "
                  "core (median), on the daemon's machine here."]
    emit(lines, args.out)


def top(page, locator) -> float:
    """The element's top on the page (retried: a Div the server just changed is redrawn)."""
    for _ in range(50):
        box = locator.bounding_box()
        if box is not None:
            return box["y"] + page.evaluate("window.scrollY")
        time.sleep(0.1)
    raise RuntimeError(f"{locator} is not on the page")


def screenshots(args) -> None:
    """The street scene live, the page open, one screenshot per panel into ``args.screenshots``."""
    from playwright.sync_api import sync_playwright

    out = Path(args.screenshots)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=Path.cwd()) as d, sync_playwright() as pw:
        tmp = Path(d)
        cal = Path(args.calibration).resolve()
        (tmp / "topo.toml").write_text(f"""
[daemon]
state = "{tmp / 'state'}"
[source]
kind = "sim"
scene = "{ROOT / 'scenes' / 'street.toml'}"
cycles = {int(args.cycles)}
seed = 1
rate = 2.5e6
[histogram]
workers = 2
measurement_cycles = 20000
calibration = "{cal}"
[range]
calibration = "{cal}"
[sink]
out = "{tmp / 'out'}"
[view]
port = 0
""")
        daemon = tcspc("daemon", "--config", tmp / "topo.toml", "--run", "street")
        try:
            url_file = tmp / "state" / "view.url"
            deadline = time.time() + 60
            while not (url_file.exists() and url_file.read_text().strip()):
                if time.time() > deadline:
                    raise SystemExit("the daemon's view did not start")
                time.sleep(0.2)
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=["--no-sandbox"])
            page = browser.new_page(viewport={"width": 1240, "height": 900})
            page.goto(url_file.read_text().strip())
            page.wait_for_selector('[data-field="distance"]', timeout=120_000)
            time.sleep(args.settle)  # sparklines and a few LSB estimates
            tops = [top(page, page.locator("h2", has_text=t).first)
                    for t in ("1. Health", "2. Sensor", "3. Calibration")]
            start = top(page, page.locator('[data-field="daemon-state"]').first) - 8
            full = page.evaluate("document.documentElement.scrollHeight")
            for name, (a, b) in zip(("health", "sensor", "calibration"),
                                    [(start, tops[1]), (tops[1], tops[2]), (tops[2], full)],
                                    strict=True):
                page.screenshot(path=str(out / f"view_{name}.png"), full_page=True,
                                clip={"x": 0, "y": a, "width": 1240, "height": b - a})
                print(out / f"view_{name}.png")
            browser.close()
        finally:
            daemon.send_signal(signal.SIGTERM)
            print(json.dumps(json.loads(daemon.communicate(timeout=300)[0] or "{}")
                             .get("accounting", {}).get("balanced")))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--words", type=float, default=128e6)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--calibration", default="data/calibration/current")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/view.md"))
    ap.add_argument("--screenshots", default=None, help="Save the page's panels here instead.")
    ap.add_argument("--cycles", type=float, default=2e6,
                    help="Cycles of the street scene for --screenshots (at 2.5 M words/s).")
    ap.add_argument("--settle", type=float, default=60.0,
                    help="Seconds the page runs before the screenshots.")
    args = ap.parse_args()
    if args.screenshots:
        screenshots(args)
    else:
        benchmark(args)


if __name__ == "__main__":
    main()
