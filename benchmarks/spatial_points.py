"""Lone points before a scene: one pixel each (a retroreflector, a post's tip, a sign),
which no neighbour shares. The spatial estimator's window plane (step 2) is fitted from
the neighbours only; at a lone point they hold no surface, and its plane is their
background's. Step 2d ranges such a surface by the pixel's own photons. This benchmark
puts ``--points`` points of ``--photons`` photons each, at depths drawn uniformly in
1.5-2.5 m (in front of every surface of benchmarks/spatial_scenes.py's grid scene), on
a 4 x 4 lattice 16 pixels apart (no window holds two), over the scene's histograms at
2 signal photons and each background of ``--backgrounds``; and reports, with step 2d
and without it (``spatial.LONE``), for each point the return nearest its true depth:
detected or not, its error against the true depth and its sigma.

    python benchmarks/spatial_points.py [--seeds 11-13] [--photons 40] [--backgrounds 50 10 2]

The points are drawn here (numpy's Gaussian pulse, as the scene's generator draws its
own); the estimator is given no hint of them.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from itertools import product

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
from benchmarks.spatial_scenes import BIN_S, SIGMA_S, C, histograms, scene  # noqa: E402
from stages.ranging import spatial as sp  # noqa: E402

LATTICE = (6, 22, 38, 54)   # rows and columns of the points (16 pixels apart)


def frame(seed: int, background: float, photons: int):
    """The grid scene's histograms at (2, ``background``) with 16 lone points added;
    returns the counts and each point's true depth (metres) by pixel."""
    rng = np.random.default_rng(seed)
    counts = histograms(scene(), 2, background, seed)
    depth = dict(zip(product(LATTICE, LATTICE), rng.uniform(1.5, 2.5, len(LATTICE) ** 2),
                     strict=True))
    for px, d in depth.items():
        b = np.floor((2 * d / C + rng.normal(0.0, SIGMA_S, photons)) / BIN_S).astype(int)
        counts[px] += np.bincount(b[(b >= 0) & (b < counts.shape[-1])],
                                  minlength=counts.shape[-1])
    return counts, depth


def measure(frames, threads: int):
    """Per point: detected, |error| (m), sigma (m) of its nearest return; and the mean
    frame time (s)."""
    out, dt = [], []
    for counts, depth in frames:
        t0 = time.perf_counter()
        est = sp.spatial(counts, BIN_S, SIGMA_S, 1e-3, threads=threads)
        dt.append(time.perf_counter() - t0)
        for px, d in depth.items():
            t, sg = est.t_s[px] * C / 2, est.sigma_s[px] * C / 2
            k = int(np.nanargmin(np.abs(t - d)))
            out.append((bool(est.detected[px][k]), abs(t[k] - d), sg[k]))
    return np.array(out), float(np.mean(dt))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seeds", default="11-13", help="a range a-b")
    ap.add_argument("--photons", type=int, default=40)
    ap.add_argument("--backgrounds", type=float, nargs="+", default=[50.0, 10.0, 2.0])
    ap.add_argument("--threads", type=int, default=2)
    args = ap.parse_args(argv)
    a, _, b = args.seeds.partition("-")
    seeds = range(int(a), int(b or a) + 1)
    print(f"$ python benchmarks/spatial_points.py --seeds {args.seeds} --photons "
          f"{args.photons} --backgrounds {' '.join(f'{x:g}' for x in args.backgrounds)}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, load "
          f"{os.getloadavg()[0]:.2f}; spatial with {args.threads} thread(s)\n")
    print("| background | step 2d | points | detected | median error mm | 90th error mm "
          "| median sigma mm | largest sigma m | within 2 sigma | frame s |")
    print("|---:|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for bg in args.backgrounds:
        frames = [frame(s, bg, args.photons) for s in seeds]
        for lone in (False, True):
            sp.LONE = lone
            m, dt = measure(frames, args.threads)
            det, err, sig = m[:, 0] > 0, m[:, 1], m[:, 2]
            print(f"| {bg:g} | {'on' if lone else 'off'} | {len(m)} | {det.sum()} | "
                  f"{1e3 * np.median(err):.1f} | {1e3 * np.quantile(err, 0.9):.1f} | "
                  f"{1e3 * np.median(sig):.1f} | {sig.max():.3g} | "
                  f"{100 * np.mean(err < 2 * sig):.0f} % | {dt:.2f} |")
    sp.LONE = True


if __name__ == "__main__":
    main()
