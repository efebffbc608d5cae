"""The spatial estimator's time a frame over many frames (the issue's goal: a 64 x 64 x
1024 frame in <= 1 s on 2 cores): frames of benchmarks/spatial_scenes.py's grid scene,
straight and turned by 30 degrees, at three cells of Lindell's grid, each timed once
after a warm-up frame. Prints the median, the largest and how many frames took more
than 1 s, with the machine's load.

    python benchmarks/spatial_frame_time.py [--frames 20] [--threads 2]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks import spatial_scenes as gen  # noqa: E402
from stages.ranging.spatial import spatial  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    print(f"command: python benchmarks/spatial_frame_time.py --frames {a.frames} "
          f"--threads {a.threads}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}; {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")
    print()
    print("| scene | signal, background | median s | largest s | over 1 s | load |")
    print("|---|---|---:|---:|---:|---:|")
    for angle in (0.0, 30.0):
        sc = gen.scene(angle_deg=angle)
        for cell in ((2, 50), (5, 10), (10, 2)):
            spatial(gen.histograms(sc, *cell, np.random.default_rng(1000)), gen.BIN_S,
                    gen.SIGMA_S, 1e-3, threads=a.threads)             # the warm-up
            ts = []
            for seed in range(1, a.frames + 1):
                counts = gen.histograms(sc, *cell, np.random.default_rng(seed))
                t = time.perf_counter()
                spatial(counts, gen.BIN_S, gen.SIGMA_S, 1e-3, threads=a.threads)
                ts.append(time.perf_counter() - t)
            ts = np.array(ts)
            print(f"| {'turned 30' if angle else 'grid'} | {cell[0]}, {cell[1]} | "
                  f"{np.median(ts):.2f} | {ts.max():.2f} | {(ts > 1).sum()} of {ts.size} | "
                  f"{os.getloadavg()[0]:.2f} |", flush=True)


if __name__ == "__main__":
    main()
