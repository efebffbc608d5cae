"""Soak: the daemon for a long run at a fixed rate, its stages' memory sampled throughout.

Replays a capture of synthetic words (5 % hits) repeatedly as one run at ``--rate`` words/s
through ``tcspc daemon`` (journal on with retention, ``--workers`` histogram workers, histograms per
measurement, the range stage when --calibration is given), samples every stage's resident
memory (VmRSS) every 10 s, and reports per stage the RSS after warm-up and at the end, the
largest, and the growth; writes the samples as parquet and a plot.

    python benchmarks/soak.py --minutes 30 --rate 17e6 [--calibration DIR] [--kill-every 3]

With ``--kill-every MIN`` a stage is SIGKILLed every MIN minutes, in turn histogram-0,
histogram-1, the sink (and range); the report then says whether every word sent was
journaled and classified once (nothing lost, nothing counted twice).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from pipeline.io.capture import CaptureWriter  # noqa: E402
from stages.testpattern import pattern_words  # noqa: E402


def rss_mib(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        return None
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=30)
    ap.add_argument("--rate", type=float, default=17e6, help="words/s")
    ap.add_argument("--calibration", default=None)
    ap.add_argument("--warmup", type=float, default=2.0, help="minutes excluded")
    ap.add_argument("--workers", type=int, default=2,
                    help="histogram workers (on 2 cores one is faster: docs/performance.md)")
    ap.add_argument("--kill-every", type=float, default=None,
                    help="SIGKILL a stage every this many minutes (in turn)")
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    args = ap.parse_args()
    import polars as pl

    with tempfile.TemporaryDirectory(dir=Path.cwd()) as d:
        tmp = Path(d)
        block, _ = pattern_words((1 << 24) // 128, 128, hit_prob=0.05, rng=1)
        with CaptureWriter(tmp / "cap", 128) as w:
            for _ in range(4):
                w.write(block)
        n = 4 * block.size
        repeat = int(np.ceil(args.rate * args.minutes * 60 / n))
        topo = tmp / "soak.toml"
        topo.write_text(f"""
[daemon]
state = "{tmp / 'state'}"
journal_keep_gb = 4
[source]
kind = "capture"
capture = "{tmp / 'cap'}"
repeat = {repeat}
rate = {args.rate}
[histogram]
workers = {args.workers}
measurement_cycles = 100000
""" + (f'[range]\ncalibration = "{args.calibration}"\n' if args.calibration else "")
            + f'[sink]\nout = "{tmp / "out"}"\n')
        daemon = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                                   str(topo), "--run", "soak"], stdout=subprocess.PIPE,
                                  stderr=subprocess.DEVNULL, text=True)
        rows, t0 = [], time.time()
        victims = ([f"histogram-{i}" for i in range(args.workers)] + ["sink"]
                   + (["range"] if args.calibration else []))
        kills, next_kill = [], (args.kill_every or 0) * 60
        while daemon.poll() is None:
            time.sleep(min(10, (args.kill_every or 1) * 60 / 4))
            try:
                st = json.loads((tmp / "state" / "status.json").read_text())
            except (OSError, ValueError):
                continue
            if args.kill_every and time.time() - t0 >= next_kill:
                name = victims[len(kills) % len(victims)]
                pid = st["stages"].get(name, {}).get("pid")
                if pid and st["stages"][name].get("alive"):
                    import os
                    import signal

                    os.kill(pid, signal.SIGKILL)
                    kills.append(name)
                next_kill += args.kill_every * 60
            t = (time.time() - t0) / 60
            for name, s in st["stages"].items():
                r = rss_mib(s["pid"]) if s.get("pid") else None
                if r is not None:
                    rows.append({"minute": t, "stage": name, "rss_mib": r,
                                 "restarts": s["restarts"]})
            r = rss_mib(daemon.pid)
            if r is not None:
                rows.append({"minute": t, "stage": "supervisor", "rss_mib": r, "restarts": 0})
        result = json.loads(daemon.stdout.read())
        elapsed = (time.time() - t0) / 60
    df = pl.DataFrame(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    df.write_parquet(args.out / "soak.parquet")
    late = df.filter(pl.col("minute") > args.warmup)
    first = late.filter(pl.col("minute") < args.warmup + 2)
    last = late.filter(pl.col("minute") > late["minute"].max() - 2)
    summary = (first.group_by("stage").agg(pl.col("rss_mib").median().alias("after warm-up"))
               .join(last.group_by("stage").agg(pl.col("rss_mib").median().alias("at end")),
                     on="stage")
               .join(late.group_by("stage").agg(pl.col("rss_mib").max().alias("max"),
                                                pl.col("restarts").max()), on="stage")
               .with_columns(growth_pct=(pl.col("at end") / pl.col("after warm-up") - 1) * 100)
               .sort("stage"))
    _plot(df, args.out / "soak.png")
    from pipeline.report.report import markdown_table

    acc = result["accounting"]
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
             f"{elapsed:.1f} minutes, {acc['words_in']:,} words at {args.rate / 1e6:.1f} M "
             f"words/s target ({acc['words_in'] / (elapsed * 60) / 1e6:.1f} M/s achieved "
             f"over the whole run); accounting balanced: {acc['balanced']}; journal "
             f"segments pruned: {result['journal_segments_pruned']}; restarts: "
             f"{result['restarts'] or 'none'}",
             *([f"stages SIGKILLed: {len(kills)} ({', '.join(kills)}); words sent "
                f"{n * repeat:,}, journaled {acc['words_in']:,}, classified "
                f"{acc['classified']:,}: "
                + ("nothing lost, nothing counted twice" if acc["balanced"]
                   and acc["words_in"] == n * repeat else "MISMATCH")] if args.kill_every
               else []), "",
             f"#### resident memory per process (MiB), warm-up of {args.warmup:g} min excluded",
             "", markdown_table(summary)]
    emit(lines, args.out / "soak.md")


def _plot(df, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import polars as pl

    fig, ax = plt.subplots(figsize=(7, 4))
    for stage in df["stage"].unique().sort():
        s = df.filter(pl.col("stage") == stage)
        ax.plot(s["minute"], s["rss_mib"], label=stage)
    ax.set_xlabel("minutes")
    ax.set_ylabel("RSS (MiB)")
    ax.set_title("soak: resident memory of each process")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.savefig(path, dpi=110, bbox_inches="tight")


if __name__ == "__main__":
    main()
