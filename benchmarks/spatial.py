"""Spatial ranging against the per-pixel estimators across Lindell 2018's grid.

Scenes and histograms from benchmarks/spatial_scenes.py (64 x 64 pixels, 1024 bins of
80 ps, a 440 ps FWHM Gaussian pulse; written apart from the simulator). For every cell
of signal {10, 5, 2} x background {2, 10, 50} photons a pixel: the spatial estimator
(stages/ranging/spatial.py) and the per-pixel ones (fast, ml, matched) on the same
histograms, and the best per-pixel one with 25x the photons. Per estimator: the time of a
frame, the depth RMSE over every pixel that has a surface (each estimator's distance for
it, detected or not, put in the window), the share of them off by more than 10 cm, the
RMSE over the pixels it detects, the share of surface pixels it
detects, false surfaces (empty pixels detected), and for the spatial estimator the share
of its detected surface pixels within 2 sigma of the truth. Prints a Markdown table.

    python benchmarks/spatial.py [--seed 1] [--threads 2] [--cells 2,50 10,2]
        [--spatial-only]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.spatial_scenes import (  # noqa: E402
    BIN_S,
    SIGMA_S,
    C,
    histograms,
    scene,
    window_errors,
)
from stages.ranging import Histograms, estimate  # noqa: E402
from stages.ranging.spatial import spatial  # noqa: E402

GRID = [(s, b) for s in (10, 5, 2) for b in (2, 10, 50)]
PER_PIXEL = ("fast", "ml", "matched")


def score(sc, depth_m, detected, sigma_m=None):
    """(A distance outside the window, or none, is put at the window's nearer end.)
    ``cover``: the detected surface pixels within 2 sigma (spatial only)."""
    err = window_errors(sc, depth_m)
    det = detected[sc.surface]
    cover = (float(np.mean(err[det] < 2 * sigma_m[sc.surface][det]))
             if sigma_m is not None and det.any() else np.nan)
    return {"rmse_m": float(np.sqrt(np.mean(err ** 2))), "cover": cover,
            "rmse_det_m": float(np.sqrt(np.mean(err[det] ** 2))) if det.any() else np.nan,
            "detected": float(det.mean()), "false": float(detected[~sc.surface].mean()),
            "outliers": float(np.mean(err > 0.1))}


def per_pixel(counts, name):
    h, w, n = counts.shape
    flat = counts.reshape(-1, n).astype(np.float64)
    hs = Histograms(flat, np.tile(np.arange(n + 1) * BIN_S, (h * w, 1)),
                    np.full(h * w, 1e9), np.ones(flat.shape, bool))
    t = time.perf_counter()
    e = estimate(hs, SIGMA_S, name, 1e-3)
    dt = time.perf_counter() - t
    return (e.t_s * C / 2).reshape(h, w), np.asarray(e.detected).reshape(h, w), dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cells", nargs="*", metavar="S,B",
                    help="only these cells of the grid, e.g. 2,50 10,2")
    ap.add_argument("--spatial-only", action="store_true",
                    help="leave the per-pixel estimators out")
    ap.add_argument("--angle", type=float, default=0.0,
                    help="the scene turned by this many degrees (its edges then lie along "
                         "no row, column or diagonal)")
    args = ap.parse_args()
    cells = ([tuple(float(x) for x in c.split(",")) for c in args.cells] if args.cells
             else GRID)
    sc = scene(angle_deg=args.angle)
    per_pixel(histograms(sc, 1, 1, 0), "fast")  # compile once, outside the timings
    spatial(histograms(sc, 1, 1, 0)[:16, :16], BIN_S, SIGMA_S)
    rows = []
    for s, b in cells:
        counts = histograms(sc, s, b, args.seed)
        t = time.perf_counter()
        est = spatial(counts, BIN_S, SIGMA_S, 1e-3, threads=args.threads)
        dt = time.perf_counter() - t
        rows.append((s, b, "spatial", dt, score(sc, est.t_s[..., 0] * C / 2,
                                                 est.detected[..., 0],
                                                 est.sigma_s[..., 0] * C / 2)))
        if args.spatial_only:
            print(f"done {s}, {b}", file=sys.stderr)
            continue
        for name in PER_PIXEL:
            d, det, dt = per_pixel(counts, name)
            rows.append((s, b, name, dt, score(sc, d, det)))
        d, det, dt = per_pixel(histograms(sc, 25 * s, 25 * b, args.seed), "fast")
        rows.append((s, b, "fast, 25x photons", dt, score(sc, d, det)))
        print(f"done {s}, {b}", file=sys.stderr)
    print(f"machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; "
          f"spatial with {args.threads} thread(s); seed {args.seed}; scene turned "
          f"{args.angle:g} degrees\n")
    print("| signal | background | estimator | frame s | RMSE all m | off > 10 cm | "
          "RMSE detected m | detected | false surfaces | within 2 sigma |")
    print("|---:|---:|---|---:|---:|---:|---:|---:|---:|---:|")
    for s, b, name, dt, m in rows:
        cover = "" if np.isnan(m["cover"]) else f"{100 * m['cover']:.1f} %"
        print(f"| {s:g} | {b:g} | {name} | {dt:.2f} | {m['rmse_m']:.4f} | "
              f"{100 * m['outliers']:.1f} % | {m['rmse_det_m']:.4f} | "
              f"{100 * m['detected']:.1f} % | {100 * m['false']:.2f} % | {cover} |")


if __name__ == "__main__":
    main()
