"""Range estimators: speed against error over a grid of scenes.

Grid: M (signal detections per cycle) 0.01, 0.1, 1, 5 x cycles 1e3, 1e4, 1e5 (signal
counts 10 .. 5e5) x SBR 0.01, 1, 100 x the return's place in the window (near its end, the
middle, next to the reset peak). The CRLB is that of time and M both unknown (what every
estimator faces: no one knows the return's strength beforehand). Each cell draws 200
first-photon histograms from the exact model (0.2 ns bins, 0.2 ns jitter, 80 ns window,
20 ns reset period) and runs every estimator: throughput (histograms/s, one core), bias,
RMSE, RMSE over the CRLB, outliers (|error| > 5 CRLB) and detection rate. Writes the cells
as parquet, a Pareto plot of speed against error, and prints a Markdown summary.

    python benchmarks/speed_vs_error.py [--out benchmarks/results] [--pixels 200]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from pipeline.report.figures import speed_error_figure  # noqa: E402
from pipeline.report.report import markdown_table, speed_error_summary  # noqa: E402
from stages.ranging import ESTIMATORS  # noqa: E402
from stages.ranging_eval import PLACES, Setup, draw, score  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    ap.add_argument("--pixels", type=int, default=200)
    args = ap.parse_args()
    os.sched_setaffinity(0, {0})
    import polars as pl

    rng = np.random.default_rng(2024)
    rows = []
    for m in (0.01, 0.1, 1.0, 5.0):
        for cycles in (1_000, 10_000, 100_000):
            for sbr in (0.01, 1.0, 100.0):
                for place, tof in PLACES.items():
                    hist, t, crlb = draw(rng, m, cycles, sbr, tof, args.pixels)
                    for r in score(hist, t, crlb, Setup().sigma_s):
                        rows.append({"m": m, "cycles": cycles, "signal_counts": m * cycles,
                                     "sbr": sbr, "place": place, **r})
    df = pl.DataFrame(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    df.write_parquet(args.out / "speed_vs_error.parquet")
    speed_error_figure(df, args.out / "speed_vs_error.png")
    good, summary, by_m = speed_error_summary(df)
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
             f"#### summary over cells with detection > 90 % and SBR >= 1 "
             f"({good.height // len(ESTIMATORS)} of {df.height // len(ESTIMATORS)} cells)", "",
             markdown_table(summary), "", "#### median RMSE / CRLB by M (same cells)", "",
             markdown_table(by_m)]
    emit(lines, args.out / "speed_vs_error.md")


if __name__ == "__main__":
    main()
