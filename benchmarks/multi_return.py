"""Two surfaces a pixel (a window, a fence): detection and range error of the returns
against their separation and against the weaker surface's share of the counts.

Each cell draws 200 first-photon histograms of two Gaussian returns from the exact model
(``stages.ranging_eval.two_surfaces``: 0.1 ns bins, instrument sigma 0.2 ns, 1 background
count a bin, 1e5 cycles: little pile-up) and ranges them with up to 3 returns a pixel
(``stages.ranging.estimate_returns``, p_fa 1e-3). Separations are in instrument widths
(FWHM = 2.355 sigma = 0.47 ns). Sweep 1: separation 0.5 .. 5 widths, the weaker with 30 %
of 1 000 signal counts (300). Sweep 2: at 3 widths, the weaker's share 0.1 .. 0.5 of
1 000. Then background-only histograms: the share of pixels with any detected return.

    python benchmarks/multi_return.py [--pixels 200] [--estimators fast,ml] [--out FILE]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from stages.ranging import Histograms, estimate_returns  # noqa: E402
from stages.ranging_eval import score_returns, two_surfaces  # noqa: E402

SIGMA, BIN, P_FA = 0.2e-9, 0.1e-9, 1e-3


def cell(estimator: str, sep: float, share: float, total: float, n_pix: int, seed: int):
    rng = np.random.default_rng(seed)
    h, truth = two_surfaces(rng, n_pix, sep, share, total, SIGMA, BIN)
    t0 = time.perf_counter()
    est = estimate_returns(h, SIGMA, estimator, P_FA, 3)
    dt = time.perf_counter() - t0
    return {"estimator": estimator, "sep": sep, "share": share,
            "weak_counts": share * total, **score_returns(est, truth),
            "hist_per_s": n_pix / dt}


def row(r: dict) -> str:
    def f(key, fmt):
        return format(r[key], fmt) if key in r else "-"
    return (f"| {r['estimator']} | {r['sep']:g} | {r['share']:.0%} ({r['weak_counts']:.0f}) | "
            f"{r['both_detected']:.1%} | {r['weaker_detected']:.1%} | "
            f"{f('near_bias_ps', '+.1f')} / {f('near_rms_ps', '.1f')} / "
            f"{f('near_sigma_ps', '.1f')} | {f('near_cover_2sigma', '.0%')} | "
            f"{f('far_bias_ps', '+.1f')} / {f('far_rms_ps', '.1f')} / "
            f"{f('far_sigma_ps', '.1f')} | {f('far_cover_2sigma', '.0%')} | "
            f"{r['hist_per_s']:,.0f} |")


HEAD = ["| estimator | separation (widths) | weaker share (counts) | both detected | "
        "weaker detected | near: bias / RMS / sigma (ps) | near within 2 sigma | "
        "far: bias / RMS / sigma (ps) | far within 2 sigma | histograms/s |",
        "|---|---|---|---|---|---|---|---|---|---|"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pixels", type=int, default=200)
    ap.add_argument("--estimators", default="fast,ml")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    ests = args.estimators.split(",")
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
             f"#### against separation (weaker 30 % of 1 000 counts), {args.pixels} "
             "pixels a cell", "", *HEAD]
    for est in ests:
        for i, sep in enumerate((0.5, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0)):
            lines.append(row(cell(est, sep, 0.3, 1000.0, args.pixels, 100 + i)))
    lines += ["", "#### against the weaker's share (3 widths apart, 1 000 counts)", "", *HEAD]
    for est in ests:
        for i, share in enumerate((0.1, 0.2, 0.3, 0.4, 0.5)):
            lines.append(row(cell(est, 3.0, share, 1000.0, args.pixels, 200 + i)))
    lines += ["", "#### background only (p_fa 1e-3, 3 returns a pixel, 400 bins): pixels with "
              "any detected return", "", "| estimator | counts a bin | pixels | with a "
              "detection | share |", "|---|---|---|---|---|"]
    for est in ests:
        for b in (1e-3, 0.3, 30.0):
            rng = np.random.default_rng(int(b * 1e3) + 9)
            n = 2000
            c = rng.poisson(b, (n, 400)).astype(float)
            h = Histograms(c, np.tile(np.arange(401) * BIN, (n, 1)), np.full(n, 1e9),
                           np.ones_like(c, bool))
            r = estimate_returns(h, SIGMA, est, P_FA, 3)
            k = len(set(r.pixel[r.detected].tolist()))
            lines.append(f"| {est} | {b:g} | {n} | {k} | {k / n:.2%} |")
    emit(lines, args.out)


if __name__ == "__main__":
    main()
