"""The undetected pixels taken from the detected ones around them (issue 35; step 5's
second part, ``stages.ranging.spatial.UNDET_TOL``): before and after, on the same
histograms.

The project's scenes (benchmarks/spatial_scenes.py: ``grid``, and ``turned``, the same
turned by 30 degrees), the outside probe's (benchmarks/probe_scenes.py: ``sphere``,
``fence``, ...), both written apart from the simulator, and ``stripes12``,
``stripes18``: stripes of two planes 12 or 18 cm apart (an outside review's case);
``diagonalCM`` (stripes at 31 degrees), ``slantA_CM`` (stripes 8 pixels wide, CM
apart, their edges at A degrees to the rows: 0 along them, 90 along the columns),
``rstripesCM`` (``stripesCM`` along the rows) and ``domeboxCM`` (a box on a dome).
For every scene, cell and the seeds together: the undetected first returns on surface
pixels, the RMSE of those within 10 cm of a true surface ("on the surface"), and the
share of all of them within 2 sigma of the nearest true surface, with the step off
(``UNDET_TOL`` 0) and on (its default). Detected pixels are not touched by the step
(their figures are the same). Prints a Markdown table.

    python benchmarks/spatial_undetected.py [--scenes grid turned] [--cells 2,10 2,50]
        [--seeds 9,10,11,12] [--threads 2]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import benchmarks.probe_scenes as probe  # noqa: E402
from benchmarks.spatial_scenes import BIN_S, SIGMA_S, C, histograms, scene  # noqa: E402
from stages.ranging import spatial as sp  # noqa: E402


def stripes(gap_m: float):
    """Vertical stripes 8 pixels wide of two planes ``gap_m`` apart in depth (5 m, slanted
    1 cm a column and 0.5 cm a row): edges a pulse width or two deep."""
    def f(r, c, h, w):
        return 5.0 + 0.01 * c + 0.005 * r + gap_m * ((np.floor(c).astype(int) // 8) % 2)
    return f


def diagonal(gap_m: float):
    """Stripes along r + 0.6 c (edges at 31 degrees to the rows, 7.7 pixels apart
    across them: between the window's halves' directions, and two edges in some
    windows) of two planes ``gap_m`` apart (6 m, slanted)."""
    def f(r, c, h, w):
        return (6.0 - 0.004 * c + 0.008 * r
                + gap_m * ((np.floor(r + 0.6 * c).astype(int) // 9) % 2))
    return f


def slant(angle_deg: float, gap_m: float):
    """Stripes 8 pixels wide across, their edges at ``angle_deg`` to the rows (0: along
    the rows, 90: along the columns), of two planes ``gap_m`` apart (6 m, slanted): a
    step at any angle to the pixel grid."""
    a = np.deg2rad(angle_deg)

    def f(r, c, h, w):
        across = r * np.cos(a) - c * np.sin(a)
        return (6.0 - 0.004 * c + 0.008 * r
                + gap_m * ((np.floor(across / 8.0).astype(int)) % 2))
    return f


def dome_box(gap_m: float):
    """A dome (4 m, curving away) with a box ``gap_m`` proud of it on its middle."""
    def f(r, c, h, w):
        base = 4.0 + 0.0004 * ((r - 30) ** 2 + (c - 34) ** 2)
        return base - gap_m * ((r > 20) & (r < 44) & (c > 14) & (c < 40))
    return f


def frame(name: str, sig: float, bg: float, seed: int):
    """(counts, depth (h, w, 2) metres, NaN: none) of a scene by name."""
    if name in ("grid", "turned"):
        sc = scene(angle_deg=30.0 if name == "turned" else 0.0)
        return histograms(sc, sig, bg, seed), sc.depth
    if name.startswith("rstripes"):         # rstripes12: stripes12 along the rows
        counts, depth = frame(name[1:], sig, bg, seed)
        return counts.swapaxes(0, 1).copy(), depth.swapaxes(0, 1).copy()
    if name.startswith("stripes"):          # stripes12: 12 cm apart
        f = stripes(int(name[7:]) / 100.0)
    elif name.startswith("diagonal"):       # diagonal9: 9 cm apart
        f = diagonal(int(name[8:]) / 100.0)
    elif name.startswith("slant"):          # slant12_9: at 12 degrees, 9 cm apart
        a, g = name[5:].split("_")
        f = slant(float(a), int(g) / 100.0)
    elif name.startswith("domebox"):        # domebox12: the box 12 cm proud
        f = dome_box(int(name[7:]) / 100.0)
    else:
        f = probe.SCENES[name]
    counts, tr = probe.histograms(f, 64, 64, sig, bg, seed)
    return counts, np.concatenate([tr[..., :1], np.full(tr.shape[:2] + (1,), np.nan)], -1)


def undetected(counts, depth, threads: int) -> tuple[np.ndarray, np.ndarray]:
    """The undetected first returns on surface pixels: |error| and sigma (metres)."""
    e = sp.spatial(counts, BIN_S, SIGMA_S, 1e-3, threads=threads)
    d = e.t_s[..., 0] * C / 2
    s = e.sigma_s[..., 0] * C / 2
    err = np.fmin(np.abs(d - depth[..., 0]), np.abs(d - np.nan_to_num(depth[..., 1], nan=1e9)))
    m = np.isfinite(depth[..., 0]) & np.isfinite(d) & ~e.detected[..., 0]
    return err[m], s[m]


def frames_args(ap: argparse.ArgumentParser, cells: list[str], seeds: str) -> None:
    """The spatial benchmarks' shared options: ``--cells S,B ...``, ``--seeds`` and
    ``--threads``."""
    ap.add_argument("--cells", nargs="*", metavar="S,B", default=cells)
    ap.add_argument("--seeds", default=seeds)
    ap.add_argument("--threads", type=int, default=2)


def begin(ap: argparse.ArgumentParser, script: str, lead, note: str = "") -> tuple:
    """Parse the options, echo the command (``lead(args)``: the script's own options
    before the shared ones; ``note`` after it) and return (args, seeds, the load before
    the run)."""
    args = ap.parse_args()
    print(f"$ python benchmarks/{script} {lead(args)} --cells {' '.join(args.cells)} "
          f"--seeds {args.seeds}{note}\n")
    return args, [int(x) for x in args.seeds.split(",")], os.getloadavg()[0]


def machine_line(load0: float, threads: int) -> str:
    """The table's last line: the cores and the load before and after the run."""
    return (f"\nmachine: {os.cpu_count()} cores, load {load0:.2f} before, "
            f"{os.getloadavg()[0]:.2f} after; spatial with {threads} thread(s)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", default=["grid", "turned"],
                    help="grid, turned, stripesCM (e.g. stripes12), or the probe's: "
                    + ", ".join(probe.SCENES))
    frames_args(ap, ["2,10", "2,50", "5,10", "5,50"], "9,10,11,12")
    args, seeds, load0 = begin(ap, "spatial_undetected.py",
                               lambda a: f"--scenes {' '.join(a.scenes)}")
    print("| scene | signal, background | undetected pixels | RMSE on the surface, cm "
          "(off -> on) | within 2 sigma (off -> on) |")
    print("|---|---|---:|---|---|")
    on = sp.UNDET_TOL
    try:
        for name in args.scenes:
            for cell in args.cells:
                sig, bg = (float(x) for x in cell.split(","))
                got = {}
                for tol in (0.0, on):
                    sp.UNDET_TOL = tol
                    errs, sigs = zip(*(undetected(*frame(name, sig, bg, s), args.threads)
                                       for s in seeds), strict=True)
                    err, sg = np.concatenate(errs), np.concatenate(sigs)
                    near = err < 0.1
                    got[tol] = (err.size, np.sqrt(np.mean(err[near] ** 2)) * 100,
                                100 * np.mean(err < 2 * sg))
                a, b = got[0.0], got[on]
                print(f"| {name} | {cell.replace(',', ', ')} | {a[0]:,} | {a[1]:.2f} -> "
                      f"{b[1]:.2f} | {a[2]:.1f} -> {b[2]:.1f} % |", flush=True)
    finally:
        sp.UNDET_TOL = on
    print(machine_line(load0, args.threads))


if __name__ == "__main__":
    main()
