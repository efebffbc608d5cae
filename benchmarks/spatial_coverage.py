"""The spatial estimator's first returns over many scenes: detected pixels' RMSE and 2-sigma
coverage, pixels > 10 cm off, undetected pixels' coverage (issue 35; docs/ranging.md "A
small depth step inside the window").

Scenes by name as ``benchmarks/spatial_undetected.py``'s ``frame``: the project's
(``grid``, ``turned``), the outside probe's (``sphere``, ``cylinder``, ``flatwall``,
``fence``, ...) and ``stripesCM`` (stripes 8 pixels wide of two planes CM apart), all
written apart from the simulator. For every scene and cell, the seeds together: the
detected first returns on surface pixels, their RMSE (those within 10 cm of a true
surface), the share within 2 sigma of the nearest true surface, the surface pixels
whose first return is > 10 cm off (detected or not) and how many of them lie within 2
sigma, and the undetected first returns' 2-sigma share. It calls only ``spatial``, so
the same script measures an older checkout (``PYTHONPATH=that checkout``). Prints a
Markdown table.

    python benchmarks/spatial_coverage.py [--scenes grid sphere stripes12]
        [--cells 10,2 2,10 2,50] [--seeds 13,14] [--threads 2]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.spatial_scenes import BIN_S, SIGMA_S, C  # noqa: E402
from benchmarks.spatial_undetected import begin, frame, frames_args, machine_line  # noqa: E402
from stages.ranging.spatial import spatial  # noqa: E402

SCENES = ["grid", "turned", "sphere", "cylinder", "flatwall", "steep10cm", "grazing", "fence",
          "edge12", "triangle", "stripes3", "stripes6", "stripes12", "stripes18"]


def first_returns(counts, depth, threads: int) -> dict:
    """|error| (m) and sigma (m) of the detected and the undetected first returns on
    surface pixels (the nearer of a pixel's true surfaces)."""
    e = spatial(counts, BIN_S, SIGMA_S, 1e-3, threads=threads)
    d = e.t_s[..., 0] * C / 2
    s = e.sigma_s[..., 0] * C / 2
    err = np.fmin(np.abs(d - depth[..., 0]), np.abs(d - np.nan_to_num(depth[..., 1], nan=1e9)))
    surf = np.isfinite(depth[..., 0]) & np.isfinite(d)
    det = e.detected[..., 0] & surf
    return {"det": (err[det], s[det]), "und": (err[surf & ~det], s[surf & ~det])}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="*", default=SCENES)
    frames_args(ap, ["10,2", "2,10", "2,50"], "13,14")
    root = Path(sys.modules["stages.ranging.spatial"].__file__).resolve().parents[2]
    rev = subprocess.run(["git", "-C", str(root), "rev-parse", "--short", "HEAD"],
                         capture_output=True, text=True).stdout.strip() or "?"
    args, seeds, load0 = begin(ap, "spatial_coverage.py",
                               lambda a: f"--scenes {' '.join(a.scenes)}",
                               f"   # spatial at {rev}")
    print("| scene | signal, background | detected | RMSE cm | within 2 sigma "
          "| > 10 cm off | of them within 2 sigma | undetected | undetected within 2 sigma |")
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|")
    for name in args.scenes:
        for cell in args.cells:
            sig, bg = (float(x) for x in cell.split(","))
            got = [first_returns(*frame(name, sig, bg, s), args.threads) for s in seeds]
            e, s, eu, su = (np.concatenate([g[k][i] for g in got])
                            for k, i in (("det", 0), ("det", 1), ("und", 0), ("und", 1)))
            on = e < 0.1
            und = f"{100 * np.mean(eu < 2 * su):.1f} %" if eu.size else "-"
            # the pixels > 10 cm off, detected or not, whose 2 sigma reaches their error
            # (the aggregate share can hold while the wrong labels are confident)
            off = np.concatenate([e[~on] < 2 * s[~on], eu[eu >= 0.1] < 2 * su[eu >= 0.1]])
            print(f"| {name} | {cell.replace(',', ', ')} | {e.size:,} "
                  f"| {np.sqrt(np.mean(e[on] ** 2)) * 100:.2f} | {100 * np.mean(e < 2 * s):.1f} % "
                  f"| {off.size} | {int(off.sum())} | {eu.size:,} | {und} |", flush=True)
    print(machine_line(load0, args.threads))


if __name__ == "__main__":
    main()
