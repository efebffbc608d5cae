"""The per-pixel estimators' false alarms and detections where the background is not flat
in time (issue 35): rows of one bin axis (generic histograms: 1 024 bins of 80 ps, the
spatial benchmark's pulse) under a background that is flat, a ramp to 4x, or falls as
e^-t or e^-3t over the window (pile-up of ambient light in counts not corrected for it,
an afterpulsing tail). Background alone (every detected row a false alarm), and returns
of S photons at uniform times in half the rows (detected within 2 FWHM of the truth).
The counts are drawn here, Poisson per bin, apart from the estimators' code. "flat
model": the estimator with its time profile switched off (what it was before),
"profile": as it is (``stages.ranging.detection.time_profile``).

    python benchmarks/per_pixel_background.py [--seeds 1,2] [--rows 4096] [--p-fa 1e-3]
"""

from __future__ import annotations

import argparse
import importlib
import os
import platform
import sys
from pathlib import Path
from unittest import mock

import numpy as np
from scipy.special import ndtr

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import stages.ranging.detection as det  # noqa: E402
from benchmarks.spatial_scenes import BIN_S, N_BINS, SIGMA_S  # noqa: E402
from stages.ranging import Histograms, estimate  # noqa: E402

# (the package's ``fast`` is the function)
FAST = importlib.import_module("stages.ranging.fast")
J = np.arange(N_BINS)
SHAPES = {"flat": np.ones(N_BINS), "ramp to 4x": 1 + 3 * J / N_BINS,
          "e^-t": np.exp(-J / N_BINS), "e^-3t": np.exp(-3 * J / N_BINS)}
NAMES = ("fast", "ml", "matched")
FWHM_S = SIGMA_S * 2 * np.sqrt(2 * np.log(2))


def rows(n, background, shape, signal, seed):
    """n rows: ``background`` photons a row under ``shape``; ``signal`` photons at a
    uniform time (100 bins from either end) in every second row."""
    rng = np.random.default_rng(20_000 + seed)
    e = np.arange(N_BINS + 1) * BIN_S
    t0 = rng.uniform(100 * BIN_S, (N_BINS - 100) * BIN_S, n)
    has = np.arange(n) % 2 == 1 if signal else np.zeros(n, bool)
    mu = background * shape / shape.sum() + (signal * has)[:, None] * np.diff(
        ndtr((e[None, :] - t0[:, None]) / SIGMA_S), axis=1)
    c = rng.poisson(mu).astype(np.float64)
    h = Histograms(c, np.broadcast_to(e, (n, N_BINS + 1)).copy(), np.full(n, 1e9),
                   np.ones(c.shape, bool))
    return h, t0, has


def run(h, name, p_fa, flat):
    if flat:
        with mock.patch.object(det, "time_profile", lambda h: None), \
                mock.patch.object(FAST, "time_profile", lambda h: None):
            return estimate(h, SIGMA_S, name, p_fa)
    return estimate(h, SIGMA_S, name, p_fa)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--rows", type=int, default=4096)
    ap.add_argument("--p-fa", type=float, default=1e-3)
    args = ap.parse_args()
    seeds = [int(x) for x in args.seeds.split(",")]
    n = args.rows
    run(rows(64, 50, SHAPES["flat"], 0, 0)[0], "fast", args.p_fa, False)  # compile
    print(f"`python benchmarks/per_pixel_background.py --seeds {args.seeds} --rows {n} "
          f"--p-fa {args.p_fa:g}`; {platform.node()}, {os.cpu_count()} cores, load "
          f"{os.getloadavg()[0]:.1f}\n")
    print(f"Background alone ({n} rows a batch, seeds {args.seeds}; every detected row a "
          f"false alarm; p_fa {args.p_fa:g}): rows detected, flat model / profile, and "
          "whether the batch's profile test called it not flat (of the seeds):\n")
    print("| background | photons a row | not flat | "
          + " | ".join(f"{x}: flat model | profile" for x in NAMES) + " |")
    print("|---|---:|---:|" + "---:|---:|" * len(NAMES))
    for shape_name, shape in SHAPES.items():
        for b in (10, 50, 200):
            hs = [rows(n, b, shape, 0, s)[0] for s in seeds]
            gated = sum(det.time_profile(h) is not None for h in hs)
            cells = []
            for name in NAMES:
                for flat in (True, False):
                    cells.append(np.mean([run(h, name, args.p_fa, flat).detected.mean()
                                          for h in hs]))
            print(f"| {shape_name} | {b} | {gated}/{len(seeds)} | "
                  + " | ".join(f"{100 * c:.3f} %" for c in cells) + " |", flush=True)
    print("\nReturns of S photons in every second row (uniform times), B background "
          "photons a row: rows with a return detected within 2 FWHM, flat model / "
          "profile; and the empty rows detected (flat model / profile):\n")
    print("| background | S, B | " + " | ".join(
        f"{x}: found | found | empty | empty" for x in NAMES) + " |")
    print("|---|---|" + "---:|---:|---:|---:|" * len(NAMES))
    for shape_name, shape in SHAPES.items():
        for s, b in ((10, 50), (20, 200)):
            cells = []
            for name in NAMES:
                found, empty = {}, {}
                for flat in (True, False):
                    f, z = [], []
                    for seed in seeds:
                        h, t0, has = rows(n, b, shape, s, seed)
                        e = run(h, name, args.p_fa, flat)
                        ok = e.detected & (np.abs(e.t_s - t0) < 2 * FWHM_S)
                        f.append(ok[has].mean())
                        z.append(e.detected[~has].mean())
                    found[flat], empty[flat] = np.mean(f), np.mean(z)
                cells += [found[True], found[False], empty[True], empty[False]]
            print(f"| {shape_name} | {s}, {b} | "
                  + " | ".join(f"{100 * c:.2f} %" for c in cells) + " |", flush=True)


if __name__ == "__main__":
    main()
