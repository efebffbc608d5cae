"""Whether the edges' lines' posteriors mean what they say (issue 35): every undetected
pixel a line or a corner weighed (stages/ranging/edgelines.py), by the posterior its
final plane's pair leaves to the other plane (the chance ``_line_var`` puts in its
sigma), against how often the truth lies on that other plane. On the grid's scene
(benchmarks/spatial_scenes.py) at a cell, straight and turned.

    python benchmarks/spatial_line_calibration.py [--angles 0 30] [--seeds 1-25]
        [--cell 2,50] [--probe edge12 edge45 triangle ... [--refl checker]]

``--probe``: scenes of the outside probe (benchmarks/probe_scenes.py, written apart from
the grid's scene the lines were built on: edges at 12 and 45 degrees, an acute
triangle, posts, wires, a sphere); ``--angles`` with no angle leaves the grid out.

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

from benchmarks import probe_scenes  # noqa: E402
from benchmarks.spatial_scenes import BIN_S, SIGMA_S, C, histograms, scene  # noqa: E402
from stages.ranging import spatial as sp  # noqa: E402

EDGES = np.array([0.0, 1e-4, 1e-3, 1e-2, 0.05, 0.2, 0.5, 1.0 + 1e-9])


def weighed(depth, counts, bin_s=BIN_S, sigma_s=SIGMA_S, tie=None):
    """(the posterior of the other plane, whether the truth is on it) of every pixel the
    lines weighed whose two planes differ by more than 0.3 m, from one frame; ``depth``
    (h, w): the truth, the first surface's range a pixel (m; NaN: none); ``tie`` (h, w):
    pixels left out (an edge through the pixel's centre)."""
    seen = {}
    line_var = sp._line_var

    def spy(q, A, B, p_a, cat, T):
        seen["a"] = (q, A, B, p_a, cat, T)
        return line_var(q, A, B, p_a, cat, T)

    sp._line_var = spy
    try:
        sp.spatial(counts, bin_s, sigma_s, 1e-3, threads=2)
    finally:
        sp._line_var = line_var
    q, A, B, p_a, cat, T = seen["a"]
    w = cat.shape[1]
    r, c = q // w, q % w
    fin = cat[r, c]
    on = (fin == A) | (fin == B)
    p_other = np.where(fin == A, 1.0 - p_a, p_a)
    other = np.where(fin == A, B, A)
    truth = depth[r, c]
    t_fin = np.take_along_axis(T[r, c], np.clip(fin, 0, None)[:, None], 1)[:, 0] * bin_s * C / 2
    t_oth = np.take_along_axis(T[r, c], other[:, None], 1)[:, 0] * bin_s * C / 2
    with np.errstate(invalid="ignore"):
        ok = (on & np.isfinite(truth) & np.isfinite(t_fin) & np.isfinite(t_oth)
              & (np.abs(t_fin - t_oth) > 0.3))
        wrong = np.abs(t_oth - truth) < np.abs(t_fin - truth)
    if tie is not None:
        ok &= ~tie[r, c]
    return p_other[ok], wrong[ok]


def ties(f, h: int = 64, w: int = 64) -> np.ndarray:
    """The pixels of a probe scene ``f`` whose centre lies on an edge (to 1e-6 of a
    pixel: the truth there is decided by rounding; the 45-degree edge runs through the
    centres of its diagonal): the range a millionth of a pixel away, in any of the four
    diagonal directions, differs from the centre's by over 0.3 m, or is sky where the
    centre is not, or the reverse."""
    rr, cc = np.mgrid[0:h, 0:w] + 0.5
    mid = f(rr, cc, h, w)
    out = np.zeros((h, w), bool)
    for dr in (-1e-6, 1e-6):
        for dc in (-1e-6, 1e-6):
            x = f(rr + dr, cc + dc, h, w)
            with np.errstate(invalid="ignore"):
                out |= (np.isfinite(x) != np.isfinite(mid)) | (np.abs(x - mid) > 0.3)
    return out


def _frames(a, sig, bg, seeds):
    """(the row's name, [(truth, counts, bin_s, sigma_s)] of each seed) for every scene
    asked for: the grid's at each angle, then the outside probe's."""
    for ang in a.angles:
        sc = scene(angle_deg=ang)
        yield f"grid {ang:g}", ((sc.depth[..., 0], histograms(sc, sig, bg, s), BIN_S,
                                 SIGMA_S, None) for s in seeds)
    for name in a.probe:
        f = probe_scenes.SCENES[name]
        tie = ties(f)

        def one(s, f=f, tie=tie):
            counts, tr = probe_scenes.histograms(f, 64, 64, sig, bg, s, refl=a.refl)
            return tr[..., 0], counts, probe_scenes.BIN_S, probe_scenes.SIGMA_S, tie
        yield f"{name} ({a.refl}; {int(tie.sum())} centres on an edge left out)", (
            one(s) for s in seeds)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--angles", nargs="*", type=float, default=[0.0, 30.0],
                    help="the grid's scene turned by these (degrees)")
    ap.add_argument("--probe", nargs="*", default=[], choices=sorted(probe_scenes.SCENES),
                    help="and these scenes of the outside probe (64 x 64)")
    ap.add_argument("--refl", default="flat", choices=["flat", "checker", "ramp"],
                    help="the probe scenes' reflectance")
    ap.add_argument("--seeds", default="1-25")
    ap.add_argument("--cell", default="2,50", help="signal,background photons a pixel")
    a = ap.parse_args()
    lo, _, hi = a.seeds.partition("-")
    seeds = range(int(lo), int(hi or lo) + 1)
    sig, bg = (float(x) for x in a.cell.split(","))
    print(f"command: python benchmarks/spatial_line_calibration.py --angles "
          f"{' '.join(f'{x:g}' for x in a.angles)}"
          + (f" --probe {' '.join(a.probe)} --refl {a.refl}" if a.probe else "")
          + f" --seeds {a.seeds} --cell {a.cell}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}\n")
    print("| scene | the other plane's posterior | pixels | its mean | on the other plane "
          "| share |")
    print("|---|---|---:|---:|---:|---:|")
    for name, frames in _frames(a, sig, bg, seeds):
        got = [weighed(*f) for f in frames]
        p = np.concatenate([g[0] for g in got])
        wrong = np.concatenate([g[1] for g in got])
        k = np.digitize(p, EDGES) - 1
        for i in range(len(EDGES) - 1):
            m = k == i
            if not m.any():
                continue
            print(f"| {name} | {EDGES[i]:g}-{min(EDGES[i + 1], 1.0):g} | {m.sum()} "
                  f"| {p[m].mean():.4f} | {wrong[m].sum()} | {wrong[m].mean():.4f} |",
                  flush=True)


if __name__ == "__main__":
    main()
