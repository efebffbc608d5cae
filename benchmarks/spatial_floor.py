"""What is left of the spatial estimator's error at few photons (issue 35): the surface
pixels more than 10 cm off, how many of them have no signal photon of their own in the
+-2 sigma test window at the truth, and the RMSE over every surface pixel of oracles
that set those (or the others, or all) to the truth.

The histograms are the benchmark's (benchmarks/spatial_scenes.py); each pixel's own
signal photons are the same draws without the background (``histograms(scene, s, 0,
seed)``: the generator draws the signal before the background). "beside a jump": a
pixel whose 8 nearest hold another surface more than 15 cm away, or empty sky.

    python benchmarks/spatial_floor.py [--seeds 1,2,3,4] [--cell 2,50]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.spatial_scenes import BIN_S, N_BINS, SIGMA_S, C, Scene, histograms, scene  # noqa: E402
from stages.ranging.spatial import WIDTH_TEST, spatial  # noqa: E402

WINDOW_M = N_BINS * BIN_S * C / 2


def beside_jump(sc: Scene) -> np.ndarray:
    d = np.nan_to_num(sc.depth[..., 0], nan=-100.0)   # sky: far from every surface
    h, w = d.shape
    pad = np.pad(d, 1, mode="edge")
    out = np.zeros((h, w), bool)
    for i in (-1, 0, 1):
        for j in (-1, 0, 1):
            out |= np.abs(pad[1 + i:1 + i + h, 1 + j:1 + j + w] - d) > 0.15
    return out & sc.surface


def own_signal(sc: Scene, signal_only: np.ndarray) -> np.ndarray:
    """Each pixel's signal photons within +-WIDTH_TEST sigma of its surfaces' true times."""
    P = np.concatenate([np.zeros(signal_only.shape[:2] + (1,)), signal_only.cumsum(-1)], -1)
    sb = SIGMA_S / BIN_S
    out = np.zeros(signal_only.shape[:2])
    for k in range(sc.depth.shape[-1]):
        tb = np.nan_to_num(2 * sc.depth[..., k] / C / BIN_S, nan=-1e9)
        a = np.clip(np.floor(tb - WIDTH_TEST * sb + 0.5).astype(np.int64), 0, N_BINS)
        z = np.clip(np.floor(tb + WIDTH_TEST * sb + 0.5).astype(np.int64), 0, N_BINS)
        out += (np.take_along_axis(P, z[..., None], -1)
                - np.take_along_axis(P, a[..., None], -1))[..., 0]
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", default="1,2,3,4")
    ap.add_argument("--cell", default="2,50", metavar="S,B")
    args = ap.parse_args()
    s, b = (float(x) for x in args.cell.split(","))
    sc = scene()
    surf, jump = sc.surface, beside_jump(sc)
    print(f"machine: {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; cell ({s:g}, {b:g})\n")
    print("| seed | RMSE all m | > 10 cm | of them with 0 own signal photons | beside a jump | "
          "surface pixels with 0 own (beside a jump) | oracle for the 0-photon ones: RMSE m | "
          "oracle for the others | oracle for all |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for seed in (int(x) for x in args.seeds.split(",")):
        est = spatial(histograms(sc, s, b, seed), BIN_S, SIGMA_S, 1e-3, threads=2)
        d = np.clip(np.nan_to_num(est.t_s[..., 0] * C / 2, nan=0.0), 0.0, WINDOW_M)
        e = np.abs(d[..., None] - sc.depth)
        err = np.where(surf, np.fmin(e[..., 0], e[..., 1]), 0.0)
        bad = surf & (err > 0.1)
        zero = surf & (own_signal(sc, histograms(sc, s, 0, seed)) == 0)

        def rmse(fixed, err=err, surf=surf):
            return float(np.sqrt(np.mean(np.where(fixed, 0.0, err)[surf] ** 2)))

        print(f"| {seed} | {rmse(np.zeros_like(bad)):.4f} | {bad.sum()} | {(bad & zero).sum()} | "
              f"{(bad & jump).sum()} | {zero.sum()} ({(zero & jump).sum()}) | "
              f"{rmse(bad & zero):.4f} | {rmse(bad & ~zero):.4f} | {rmse(bad):.4f} |")


if __name__ == "__main__":
    main()
