"""Whether the edges' lines' posteriors mean what they say (issue 35): every undetected
pixel a line or a corner weighed (stages/ranging/edgelines.py), by the posterior its
final plane's pair leaves to the other plane (the chance ``_line_var`` puts in its
sigma), against how often the truth lies on that other plane. On the grid's scene
(benchmarks/spatial_scenes.py) at a cell, straight and turned.

    python benchmarks/spatial_line_calibration.py [--angles 0 30] [--seeds 1-25]
        [--cell 2,50]

Only pixels whose two planes lie more than 0.3 m apart there count (else either is
right); "wrong": the truth is nearer the other plane than the pixel's own.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.spatial_scenes import BIN_S, SIGMA_S, C, histograms, scene  # noqa: E402
from stages.ranging import spatial as sp  # noqa: E402

EDGES = np.array([0.0, 1e-4, 1e-3, 1e-2, 0.05, 0.2, 0.5, 1.0 + 1e-9])


def weighed(sc, counts):
    """(the posterior of the other plane, whether the truth is on it) of every pixel the
    lines weighed whose two planes differ by more than 0.3 m, from one frame."""
    seen = {}
    line_var = sp._line_var

    def spy(q, A, B, p_a, cat, T):
        seen["a"] = (q, A, B, p_a, cat, T)
        return line_var(q, A, B, p_a, cat, T)

    sp._line_var = spy
    try:
        sp.spatial(counts, BIN_S, SIGMA_S, 1e-3, threads=2)
    finally:
        sp._line_var = line_var
    q, A, B, p_a, cat, T = seen["a"]
    w = cat.shape[1]
    r, c = q // w, q % w
    fin = cat[r, c]
    on = (fin == A) | (fin == B)
    p_other = np.where(fin == A, 1.0 - p_a, p_a)
    other = np.where(fin == A, B, A)
    truth = sc.depth[r, c, 0]
    t_fin = np.take_along_axis(T[r, c], np.clip(fin, 0, None)[:, None], 1)[:, 0] * BIN_S * C / 2
    t_oth = np.take_along_axis(T[r, c], other[:, None], 1)[:, 0] * BIN_S * C / 2
    with np.errstate(invalid="ignore"):
        ok = (on & np.isfinite(truth) & np.isfinite(t_fin) & np.isfinite(t_oth)
              & (np.abs(t_fin - t_oth) > 0.3))
        wrong = np.abs(t_oth - truth) < np.abs(t_fin - truth)
    return p_other[ok], wrong[ok]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--angles", nargs="+", type=float, default=[0.0, 30.0])
    ap.add_argument("--seeds", default="1-25")
    ap.add_argument("--cell", default="2,50", help="signal,background photons a pixel")
    a = ap.parse_args()
    lo, _, hi = a.seeds.partition("-")
    seeds = range(int(lo), int(hi or lo) + 1)
    sig, bg = (float(x) for x in a.cell.split(","))
    print(f"command: python benchmarks/spatial_line_calibration.py --angles "
          f"{' '.join(f'{x:g}' for x in a.angles)} --seeds {a.seeds} --cell {a.cell}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}\n")
    print("| angle | the other plane's posterior | pixels | its mean | on the other plane "
          "| share |")
    print("|---:|---|---:|---:|---:|---:|")
    for ang in a.angles:
        sc = scene(angle_deg=ang)
        got = [weighed(sc, histograms(sc, sig, bg, s)) for s in seeds]
        p = np.concatenate([g[0] for g in got])
        wrong = np.concatenate([g[1] for g in got])
        k = np.digitize(p, EDGES) - 1
        for i in range(len(EDGES) - 1):
            m = k == i
            if not m.any():
                continue
            print(f"| {ang:g} | {EDGES[i]:g}-{min(EDGES[i + 1], 1.0):g} | {m.sum()} "
                  f"| {p[m].mean():.4f} | {wrong[m].sum()} | {wrong[m].mean():.4f} |",
                  flush=True)


if __name__ == "__main__":
    main()
