"""The daemon's steady state against the offline command on the same capture, in the same
run (issue 38.9): histograms only (``tcspc daemon``: source -> 2 histogram workers -> sink,
journal on, a measurement per ``--measurement-cycles``; against ``tcspc histogram``) and
with the range stage (-> range (ml, up to 3 returns) -> sink; against ``tcspc range
--calibration``), runs interleaved.

The capture is the demo's street scene (``--data``: what ``make demo`` wrote, its
``raw/street.bin`` and ``calibration/current``, the same chip) ``--times`` times over. The
daemon's steady state is benchmarks/source_path.py's: words from the measurement a fifth of
the way in to the last, over the time between their files (start-up left out); the offline
commands' rate is the capture's words over the command's wall time, start-up included (what
a user waits for). The ratio is the daemon's steady rate over the offline command's.
``tcspc range`` is given ``--force``: the capture's words ``--times`` over are not a
longer measurement's (their counts are the same draw repeated, not Poisson), and its chip
check rightly finds the code-density pattern noisier than the calibration's chip allows.

    python benchmarks/steady_state.py [--data data] [--times 100] [--repeat 2]
        [--capture data/raw/pattern --histograms-only] [--code DIR --code DIR]

``--capture``: another capture (e.g. the demo's test pattern, 5 % hits) instead of the
street scene; ``--histograms-only`` leaves the range rows out (a capture that is not the
calibration's chip).
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.source_path import daemon_run  # noqa: E402


def offline(cmd: list[str], code: Path = ROOT) -> float:
    """The command's wall time, s."""
    t0 = time.perf_counter()
    p = subprocess.run([sys.executable, "-m", "pipeline.cli", *cmd], capture_output=True,
                       text=True, cwd=code, env={**os.environ, "PYTHONPATH": str(code)})
    if p.returncode != 0:
        raise SystemExit(f"tcspc {' '.join(cmd)} failed ({p.returncode}): {p.stderr[-2000:]}")
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT / "data")
    ap.add_argument("--times", type=int, default=100)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--measurement-cycles", type=int, default=20_000)
    ap.add_argument("--capture", type=Path, default=None,
                    help="the capture replayed (default: DATA/raw/street)")
    ap.add_argument("--histograms-only", action="store_true")
    ap.add_argument("--code", type=Path, action="append",
                    help="the checkout whose commands run (default: this one's); given "
                         "twice or more, their runs interleaved, a row each")
    args = ap.parse_args()
    cal = (args.data / "calibration" / "current").resolve()
    src = args.capture or args.data / "raw" / "street"
    if not (args.data / "raw" / "street.bin").exists() or not cal.exists():
        raise SystemExit(f"{args.data}: no raw/street.bin or calibration/current "
                         "(run `make demo` first, or give --data)")
    print("$ python benchmarks/steady_state.py " + " ".join(sys.argv[1:]))
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, load average {os.getloadavg()[0]:.1f} at start")
    from pipeline.io.capture import Capture, CaptureWriter

    codes = args.code or [ROOT]
    whats = ("histograms",) + (() if args.histograms_only else ("ranges",))
    rows: dict[tuple, list[tuple[float, float]]] = {(w, c): [] for w in whats for c in codes}
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        c = Capture(src)
        words = c.read_words(0, c.n_words)
        with CaptureWriter(tmp / "cap", c.meta.n_tdc, c.meta.window_ns,
                           c.meta.t_laser_win_ns, kind="range") as w:
            for _ in range(args.times):
                w.write(words)
        n = words.size * args.times
        del words
        print(f"capture: {src.name} x {args.times}, {n / 1e6:.0f} M words, "
              f"{c.meta.n_tdc} TDCs\n")
        for k in range(args.repeat):
            for what in whats:
                for i, code in enumerate(codes):
                    if what == "histograms":
                        wall = offline(["histogram", str(tmp / "cap.bin"), "--out",
                                        str(tmp / "h.parquet"), "--calibration", str(cal),
                                        "--overwrite"], code)
                    else:
                        wall = offline(["range", str(tmp / "cap.bin"), "--calibration",
                                        str(cal), "--out", str(tmp / "r.parquet"),
                                        "--overwrite", "--force"], code)  # (below)
                    _, acc, _, steady = daemon_run(code, tmp, tmp / "cap.bin", 2,
                                                   f"{what}-{k}-{i}",
                                                   str(cal) if what == "ranges" else None,
                                                   n_tdc=c.meta.n_tdc,
                                                   mc=args.measurement_cycles)
                    assert acc["balanced"], acc
                    rate = steady["words"] / steady["wall"] / 1e6
                    rows[what, code].append((n / wall / 1e6, rate))
                    print(f"  {what} run {k}{f' ({code})' if len(codes) > 1 else ''}: "
                          f"offline {n / wall / 1e6:.1f} M words/s, daemon steady "
                          f"{rate:.1f}, ratio {rate / (n / wall / 1e6):.2f}", flush=True)
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")
    print("\nM words/s, median (min-max) of", args.repeat)
    print("| graph | offline command | daemon, steady state | ratio |")
    print("|---|---:|---:|---:|")
    for (what, code), got in rows.items():
        cmd = "tcspc histogram" if what == "histograms" else "tcspc range"
        off = [o for o, _ in got]
        day = [d for _, d in got]
        rat = [d / o for o, d in got]

        def cell(v):
            return f"{statistics.median(v):.2f} ({min(v):.2f}-{max(v):.2f})"
        graph = "source -> 2 workers -> sink" if what == "histograms" else \
            "source -> 2 workers -> range -> sink"
        label = f"{code}: " if len(codes) > 1 else ""
        print(f"| {label}{graph} (against `{cmd}`) | {cell(off)} | {cell(day)} | "
              f"{cell(rat)} |")


if __name__ == "__main__":
    main()
