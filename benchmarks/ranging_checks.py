"""What the checks at the door cost: each estimator with its arguments checked and its
result flagged (``estimate``) against its bare kernel (``fn.unchecked``), side by side in
one process, on first-photon histograms of the exact model (400 bins of 0.2 ns, M = 0.1,
SBR 10, 10 000 cycles).

    python benchmarks/ranging_checks.py [--pixels 2000] [--repeat 7]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import machine  # noqa: E402
from stages.ranging import ESTIMATOR_FUNCS  # noqa: E402
from stages.ranging_eval import Setup, draw  # noqa: E402


def best(fn, repeat: int) -> float:
    out = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        out = min(out, time.perf_counter() - t0)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pixels", type=int, default=2000)
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--estimators", default="fast,ml,matched,centroid")
    args = ap.parse_args()
    setup = Setup()
    h, _, _ = draw(np.random.default_rng(1), 0.1, 10_000, 10.0, 40e-9, args.pixels, setup)
    print(f"command: `python {' '.join(sys.argv)}`\nmachine: {machine()}\n")
    print("| estimator | checked (histograms/s) | bare kernel (histograms/s) | checked / bare |")
    print("|---|---|---|---|")
    for name in args.estimators.split(","):
        fn = ESTIMATOR_FUNCS[name]
        fn(h, setup.sigma_s)  # compile
        rounds = [(best(lambda fn=fn: fn(h, setup.sigma_s), args.repeat),
                   best(lambda fn=fn: fn.unchecked(h, setup.sigma_s, 1e-3), args.repeat))
                  for _ in range(3)]  # interleaved, so a change of the machine's load
        checked = min(r[0] for r in rounds)  # falls on both
        bare = min(r[1] for r in rounds)
        print(f"| {name} | {args.pixels / checked:,.0f} | {args.pixels / bare:,.0f} | "
              f"{bare / checked:.2f} |")


if __name__ == "__main__":
    main()
