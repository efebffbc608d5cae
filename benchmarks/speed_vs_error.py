"""Range estimators: speed against error over a grid of scenes.

Grid: M (signal detections per cycle) 0.01, 0.1, 1, 5 x cycles 1e3, 1e4, 1e5 (signal
counts 10 .. 5e5) x SBR 0.01, 1, 100 x the return's place in the window (near its end, the
middle, next to the reset peak). Each cell draws 200 first-photon histograms from the exact
model (0.2 ns bins, 0.2 ns jitter, 80 ns window, 20 ns reset period) and runs every
estimator: throughput (histograms/s, one core), bias, RMSE, RMSE over the CRLB, outliers
(|error| > 5 CRLB) and detection rate. Writes the cells as parquet, a Pareto plot of speed
against error, and prints a Markdown summary.

    python benchmarks/speed_vs_error.py [--out benchmarks/results] [--pixels 200]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
import warnings
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from stages.models.tcspc import crlb_tof, first_photon_histogram  # noqa: E402
from stages.ranging import ESTIMATORS, Histograms, estimate  # noqa: E402

W, B, SG, RESET = 80e-9, 0.2e-9, 0.2e-9, 20e-9
PLACES = {"window end": 77e-9, "middle": 40e-9, "next to reset peak": 3e-9}


def cell(rng, m, cycles, sbr, tof, n_pix):
    bg = m / (sbr * W)
    t = tof + rng.uniform(-0.5, 0.5, n_pix) * B  # random phase on the bin grid
    h = first_photon_histogram(m, t, SG, bg, W, B, RESET)
    p = np.concatenate([h.p_reset[:, None], h.p, h.p_none[:, None]], 1)
    d = np.array([rng.multinomial(cycles, pi / pi.sum()) for pi in p])
    counts = d[:, 1:-1].astype(float)
    valid = np.ones_like(counts, bool)
    valid[:, :1] = valid[:, -1:] = False
    edges = np.tile(np.arange(counts.shape[1] + 1) * B, (n_pix, 1))
    hist = Histograms(counts, edges, (cycles - d[:, 0]).astype(float), valid)
    crlb = float(np.median(crlb_tof(cycles, m, t, SG, bg, W, B, RESET)))
    return hist, t, crlb


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
                    hist, t, crlb = cell(rng, m, cycles, sbr, tof, args.pixels)
                    for est in ESTIMATORS:
                        with warnings.catch_warnings():
                            warnings.simplefilter("ignore")
                            t0 = time.perf_counter()
                            r = estimate(hist, SG, est)
                            dt = time.perf_counter() - t0
                        err = r.t_s - t
                        det = r.detected
                        e = err[det] if det.any() else err
                        rows.append({
                            "m": m, "cycles": cycles, "signal_counts": m * cycles,
                            "sbr": sbr, "place": place, "estimator": est,
                            "hist_per_s": args.pixels / dt, "detected": float(det.mean()),
                            "bias_ps": float(np.mean(e) * 1e12),
                            "rmse_ps": float(np.sqrt(np.mean(e ** 2)) * 1e12),
                            "crlb_ps": crlb * 1e12,
                            "rmse_over_crlb": float(np.sqrt(np.mean(e ** 2)) / crlb),
                            "outliers_5crlb": float(np.mean(np.abs(e) > 5 * crlb)),
                            "coverage_2sigma": float(np.mean(np.abs(e) < 2 * r.sigma_s[det]))
                            if det.any() else float("nan")})
    df = pl.DataFrame(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    df.write_parquet(args.out / "speed_vs_error.parquet")
    _pareto(df, args.out / "speed_vs_error.png")
    good = df.filter((pl.col("detected") > 0.9) & (pl.col("sbr") >= 1))
    summary = (good.group_by("estimator").agg(
        pl.col("hist_per_s").median().alias("median hist/s"),
        pl.col("rmse_over_crlb").median().alias("median RMSE/CRLB"),
        pl.col("rmse_over_crlb").quantile(0.9).alias("90th pct RMSE/CRLB"),
        pl.col("bias_ps").abs().median().alias("median |bias| ps"),
        pl.col("outliers_5crlb").mean().alias("outliers > 5 CRLB"),
        pl.col("coverage_2sigma").median().alias("2-sigma coverage"))
        .sort("median RMSE/CRLB"))
    by_m = (good.group_by("estimator", "m").agg(pl.col("rmse_over_crlb").median())
            .pivot(on="m", index="estimator", values="rmse_over_crlb").sort("estimator"))
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
             f"#### summary over cells with detection > 90 % and SBR >= 1 "
             f"({good.height // len(ESTIMATORS)} of {df.height // len(ESTIMATORS)} cells)", "",
             _markdown(summary), "", "#### median RMSE / CRLB by M (same cells)", "",
             _markdown(by_m)]
    emit(lines, args.out / "speed_vs_error.md")


def _markdown(df) -> str:
    cols = df.columns
    out = ["| " + " | ".join(map(str, cols)) + " |", "|" + "---|" * len(cols)]
    for row in df.iter_rows():
        out.append("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v)
                                     for v in row) + " |")
    return "\n".join(out)


def _pareto(df, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import polars as pl

    fig, ax = plt.subplots(figsize=(7, 4.5))
    good = df.filter((pl.col("detected") > 0.9) & (pl.col("sbr") >= 1))
    for est in ESTIMATORS:
        d = good.filter(pl.col("estimator") == est)
        pts = ax.scatter(d["hist_per_s"], d["rmse_over_crlb"], s=8, alpha=0.4, label=est)
        ax.scatter([d["hist_per_s"].median()], [d["rmse_over_crlb"].median()], s=160,
                   marker="*", edgecolor="k", color=pts.get_facecolor()[0][:3])
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.axhline(1.2, ls="--", c="grey", lw=0.8)
    ax.set_xlabel("histograms per second (one core)")
    ax.set_ylabel("RMSE / CRLB")
    ax.set_title("range estimators: speed against error (stars: medians)")
    ax.legend()
    fig.savefig(path, dpi=110, bbox_inches="tight")


if __name__ == "__main__":
    main()
