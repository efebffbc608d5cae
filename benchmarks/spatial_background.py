"""The spatial estimator's false alarms and errors where the background is not flat in
time (issue 35: the per-pixel detection at a stated false-alarm rate, with any
background): empty frames, and the benchmark's scene (benchmarks/spatial_scenes.py),
under a background that is flat, a ramp to 4x, or falls as e^-t or e^-3t over the
window (pile-up of ambient light in counts not corrected for it, an afterpulsing tail).
The signal photons are the scene generator's (``histograms(scene, s, 0, seed)``); the
background is drawn here, Poisson per bin, apart from every estimator's code. "flat
model": the same estimator with its background profile switched off (what it was
before), against "profile": as it is.

    python benchmarks/spatial_background.py [--seeds 1,2] [--p-fa 1e-3]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path
from unittest import mock

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import stages.ranging.spatial as sp  # noqa: E402
from benchmarks.spatial_scenes import BIN_S, N_BINS, SIGMA_S, C, Scene, histograms, scene  # noqa: E402

WINDOW_M = N_BINS * BIN_S * C / 2
J = np.arange(N_BINS)
SHAPES = {"flat": np.ones(N_BINS), "ramp to 4x": 1 + 3 * J / N_BINS,
          "e^-t": np.exp(-J / N_BINS), "e^-3t": np.exp(-3 * J / N_BINS)}


def frame(sc: Scene, signal: float, background: float, shape: np.ndarray, seed: int):
    lam = background * shape / shape.sum()
    rng = np.random.default_rng(10_000 + seed)
    return histograms(sc, signal, 0, seed) + rng.poisson(lam, sc.depth.shape[:2] + (N_BINS,))


def run(counts, p_fa, flat):
    if flat:
        with mock.patch.object(sp, "background_profile", lambda c: None):
            return sp.spatial(counts, BIN_S, SIGMA_S, p_fa, threads=2)
    return sp.spatial(counts, BIN_S, SIGMA_S, p_fa, threads=2)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--p-fa", type=float, default=1e-3)
    args = ap.parse_args()
    seeds = [int(x) for x in args.seeds.split(",")]
    print(f"`python benchmarks/spatial_background.py --seeds {args.seeds} --p-fa {args.p_fa:g}`"
          f"; {platform.node()}, {os.cpu_count()} cores, load {os.getloadavg()[0]:.1f}\n")
    empty = Scene(np.full((64, 64, 2), np.nan), np.zeros((64, 64, 2)))
    print("Empty frames (64 x 64, every detected pixel a false alarm; a pixel tests up to "
          "4 candidates at p_fa each):\n")
    print("| background | photons a pixel | flat model: pixels detected "
          "| profile: pixels detected |")
    print("|---|---:|---:|---:|")
    for name, shape in SHAPES.items():
        for b in (10, 50, 200):
            got = [np.mean([run(frame(empty, 0, b, shape, s), args.p_fa, f).detected[..., 0].mean()
                            for s in seeds]) for f in (True, False)]
            print(f"| {name} | {b} | {got[0]:.4f} | {got[1]:.4f} |", flush=True)
    sc = scene()
    surf = sc.surface
    print("\nThe scene (3,500 surface pixels, 596 empty; seeds averaged): RMSE over every "
          "surface pixel, empty pixels detected, detected surface pixels within 2 sigma:\n")
    print("| background | signal, background photons | flat model: RMSE all m | false surfaces "
          "| 2 sigma | profile: RMSE all m | false surfaces | 2 sigma |")
    print("|---|---|---:|---:|---:|---:|---:|---:|")
    for name, shape in SHAPES.items():
        for s, b in ((10, 2), (5, 50), (2, 50)):
            cols = []
            for flat in (True, False):
                rm, fa, cov = [], [], []
                for seed in seeds:
                    est = run(frame(sc, s, b, shape, seed), args.p_fa, flat)
                    d = np.clip(np.nan_to_num(est.t_s[..., 0] * C / 2, nan=0.0), 0, WINDOW_M)
                    e = np.abs(d[..., None] - sc.depth)
                    err = np.fmin(e[..., 0], e[..., 1])
                    det = est.detected[..., 0]
                    sig = est.sigma_s[..., 0] * C / 2
                    rm.append(np.sqrt(np.mean(err[surf] ** 2)))
                    fa.append(det[~surf].mean())
                    m = surf & det
                    cov.append(np.mean(err[m] < 2 * sig[m]))
                cols.append(f"{np.mean(rm):.4f} | {np.mean(fa) * 100:.2f} % | "
                            f"{np.mean(cov) * 100:.1f} %")
            print(f"| {name} | {s:g}, {b:g} | {cols[0]} | {cols[1]} |", flush=True)


if __name__ == "__main__":
    main()
