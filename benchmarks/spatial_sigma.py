"""The spatial estimator's 2-sigma coverage split by detection (issue 35, point 3).

Scenes and histograms from benchmarks/spatial_scenes.py (written apart from the
simulator). For every cell of Lindell's grid and seed: the share of surface pixels whose
reported first return lies within 2 sigma of the nearest true surface, over the detected
ones, the undetected ones (their distance from the relabelling, 3b) and all; the
undetected pixels > 10 cm off and how many of them their sigma covers; the median sigma
of the undetected; and for reference `fast`'s undetected rows on the same histograms
(a per-pixel estimator's sigma of its undetected peak). Prints a Markdown table.

    python benchmarks/spatial_sigma.py [--seeds 1,2,3,4] [--threads 2] [--cells 2,50 10,2]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.spatial import GRID, per_pixel  # noqa: E402
from benchmarks.spatial_scenes import BIN_S, SIGMA_S, C, histograms, scene, window_errors  # noqa: E402
from benchmarks.spatial_undetected import machine_line  # noqa: E402
from stages.ranging import Histograms, estimate  # noqa: E402
from stages.ranging.spatial import spatial  # noqa: E402


def coverage(sc, depth_m, sigma_m, detected) -> dict:
    """Per group (detected, undetected, all surface pixels): (covered, pixels); and the
    undetected > 10 cm off (covered, pixels) and their median sigma (m)."""
    err = window_errors(sc, depth_m)
    sig = sigma_m[sc.surface]
    det = detected[sc.surface]
    cov = err < 2 * sig
    far = ~det & (err > 0.1)
    return {"det": (int(cov[det].sum()), int(det.sum())),
            "und": (int(cov[~det].sum()), int((~det).sum())),
            "all": (int(cov.sum()), int(cov.size)),
            "far": (int(cov[far].sum()), int(far.sum())),
            "med_und": float(np.median(sig[~det])) if (~det).any() else np.nan}


def fast_rows(counts):
    h, w, n = counts.shape
    flat = counts.reshape(-1, n).astype(np.float64)
    hs = Histograms(flat, np.tile(np.arange(n + 1) * BIN_S, (h * w, 1)),
                    np.full(h * w, 1e9), np.ones(flat.shape, bool))
    e = estimate(hs, SIGMA_S, "fast", 1e-3)
    return ((e.t_s * C / 2).reshape(h, w), (e.sigma_s * C / 2).reshape(h, w),
            np.asarray(e.detected).reshape(h, w))


def pct(x):
    c, n = x
    return f"{100 * c / n:.1f} % ({n})" if n else "-"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1,2,3,4")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--cells", nargs="*", metavar="S,B")
    ap.add_argument("--angle", type=float, default=0.0,
                    help="the scene turned by this many degrees")
    args = ap.parse_args()
    cells = ([tuple(float(x) for x in c.split(",")) for c in args.cells] if args.cells
             else GRID)
    seeds = [int(s) for s in args.seeds.split(",")]
    sc = scene(angle_deg=args.angle)
    per_pixel(histograms(sc, 1, 1, 0), "fast")  # compile once
    load0 = os.getloadavg()[0]
    print("| signal | background | seed | detected | undetected | all | undetected > 10 cm "
          "off: covered | median sigma undetected m | fast: undetected |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for s, b in cells:
        for seed in seeds:
            counts = histograms(sc, s, b, seed)
            est = spatial(counts, BIN_S, SIGMA_S, 1e-3, threads=args.threads)
            m = coverage(sc, est.t_s[..., 0] * C / 2, est.sigma_s[..., 0] * C / 2,
                         est.detected[..., 0])
            fd, fs, fdet = fast_rows(counts)
            f = coverage(sc, fd, fs, fdet)
            print(f"| {s:g} | {b:g} | {seed} | {pct(m['det'])} | {pct(m['und'])} | "
                  f"{pct(m['all'])} | {m['far'][0]} of {m['far'][1]} | "
                  f"{m['med_und']:.4f} | {pct(f['und'])} |", flush=True)
    print(machine_line(load0, args.threads))


if __name__ == "__main__":
    main()
