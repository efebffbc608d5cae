"""Small depth steps: where the spatial estimator's detected pixels' sigma does not hold
(issue 35; an outside review's finding, 2026-12-06).

Stripes 8 pixels wide of two planes a step apart in depth (5 m, slanted 1 cm a column
and 0.5 cm a row; ``benchmarks/spatial_undetected.py``'s ``stripes`` generator, written
apart from the simulator), 64 x 64 x 1024 bins of 80 ps, the project's Gaussian pulse
(sigma 2.8 cm in range). For every step and cell, the seeds together: the detected
first returns, their RMSE (those within 10 cm of their own surface) and the share
within 2 sigma of their own surface. Prints a Markdown table.

    python benchmarks/spatial_steps.py [--steps 3 6 9 12 15 18 21 24 30 40]
        [--cells 10,2 2,10] [--seeds 9,10] [--threads 2]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.spatial_scenes import BIN_S, SIGMA_S, C  # noqa: E402
from benchmarks.spatial_undetected import begin, frame, frames_args, machine_line  # noqa: E402
from stages.ranging.spatial import spatial  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--steps", nargs="*", type=int, metavar="CM",
                    default=[3, 6, 9, 12, 15, 18, 21, 24, 30, 40])
    frames_args(ap, ["10,2", "2,10"], "9,10")
    args, seeds, load0 = begin(ap, "spatial_steps.py",
                               lambda a: f"--steps {' '.join(map(str, a.steps))}")
    print("| signal, background | step cm | step / pulse sigma | detected | RMSE cm "
          "| within 2 sigma |")
    print("|---|---:|---:|---:|---:|---:|")
    sig_cm = SIGMA_S * C / 2 * 100
    for cell in args.cells:
        sig, bg = (float(x) for x in cell.split(","))
        for step in args.steps:
            err, sg = [], []
            for seed in seeds:
                counts, depth = frame(f"stripes{step}", sig, bg, seed)
                e = spatial(counts, BIN_S, SIGMA_S, 1e-3, threads=args.threads)
                det = e.detected[..., 0]
                err.append(np.abs(e.t_s[..., 0] * C / 2 - depth[..., 0])[det])
                sg.append((e.sigma_s[..., 0] * C / 2)[det])
            err, sg = np.concatenate(err), np.concatenate(sg)
            near = err < 0.1
            print(f"| {cell.replace(',', ', ')} | {step} | {step / sig_cm:.1f} | {err.size:,} "
                  f"| {np.sqrt(np.mean(err[near] ** 2)) * 100:.2f} "
                  f"| {100 * np.mean(err < 2 * sg):.1f} % |", flush=True)
    print(machine_line(load0, args.threads))


if __name__ == "__main__":
    main()
