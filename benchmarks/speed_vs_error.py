"""Range estimators: speed against error over a grid of scenes.

Grid: M (signal detections per cycle) 0.01, 0.1, 1, 5 x cycles 1e3, 1e4, 1e5 (signal
counts 10 .. 5e5) x SBR 0.01, 1, 100 x the return's place in the window (near its end, the
middle, next to the reset peak). The CRLB is that of time and M both unknown (what every
estimator faces: no one knows the return's strength beforehand). Each cell draws 200
first-photon histograms from the exact model (0.2 ns bins, 0.2 ns jitter, 80 ns window,
20 ns reset period) and runs every estimator: throughput (histograms/s, one core), bias,
RMSE, RMSE over the CRLB, outliers (|error| > 5 CRLB) and detection rate. Writes the cells
as parquet, a Pareto plot of speed against error, and prints a Markdown summary.

    python benchmarks/speed_vs_error.py [--out benchmarks/results] [--pixels 200]

``--off-path`` instead measures the rows off the grid (issue 34): histograms from an
independent generator (1 024 bins of 80 ps, a Gaussian pulse of 440 ps FWHM, S signal and
B background photons, Poisson; its CRLB of time and S both unknown derived here from the
Poisson Fisher information, not from the code's) without cycles, with a measured response
(the calibrate-distance path), with up to 3 returns, and detection probability P_d at
p_fa 1e-3 against S and B beside the 6-bin window test at its measured threshold.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from pipeline.report.figures import speed_error_figure  # noqa: E402
from pipeline.report.report import markdown_table, speed_error_summary  # noqa: E402
from stages.ranging import ESTIMATORS  # noqa: E402
from stages.ranging_eval import PLACES, Setup, draw, score  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results"))
    ap.add_argument("--pixels", type=int, default=200)
    ap.add_argument("--off-path", action="store_true", help="the rows off the grid (issue 34)")
    args = ap.parse_args()
    os.sched_setaffinity(0, {0})
    if args.off_path:
        emit([f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
              *off_path(args.pixels)], args.out / "speed_vs_error_off_path.md")
        return
    import polars as pl

    rng = np.random.default_rng(2024)
    rows = []
    for m in (0.01, 0.1, 1.0, 5.0):
        for cycles in (1_000, 10_000, 100_000):
            for sbr in (0.01, 1.0, 100.0):
                for place, tof in PLACES.items():
                    hist, t, crlb = draw(rng, m, cycles, sbr, tof, args.pixels)
                    for r in score(hist, t, crlb, Setup().sigma_s):
                        rows.append({"m": m, "cycles": cycles, "signal_counts": m * cycles,
                                     "sbr": sbr, "place": place, **r})
    df = pl.DataFrame(rows)
    args.out.mkdir(parents=True, exist_ok=True)
    df.write_parquet(args.out / "speed_vs_error.parquet")
    speed_error_figure(df, args.out / "speed_vs_error.png")
    good, summary, by_m = speed_error_summary(df)
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
             f"#### summary over cells with detection > 90 % and SBR >= 1 "
             f"({good.height // len(ESTIMATORS)} of {df.height // len(ESTIMATORS)} cells)", "",
             markdown_table(summary), "", "#### median RMSE / CRLB by M (same cells)", "",
             markdown_table(by_m)]
    emit(lines, args.out / "speed_vs_error.md")


_N, _BIN, _FWHM = 1024, 80e-12, 440e-12
_SIG = _FWHM / 2.3548200450309493


def _generate(rng, n, s, b, cycles=None):
    """The independent generator: Poisson counts of a bin-integrated Gaussian of s photons
    at a uniform time and b background photons over the window."""
    from scipy.special import ndtr

    from stages.ranging import Histograms

    e = np.arange(_N + 1) * _BIN
    t0 = rng.uniform(100 * _BIN, (_N - 100) * _BIN, n)
    c = rng.poisson(s * np.diff(ndtr((e[None, :] - t0[:, None]) / _SIG), axis=1) + b / _N)
    cyc = np.maximum(c.sum(1), 1) * 1e12 if cycles is None else np.full(n, float(cycles))
    return Histograms(c.astype(np.float64), np.broadcast_to(e, (n, _N + 1)).copy(), cyc,
                      np.ones(c.shape, bool)), t0


def _crlb(s, b, t=512.3 * _BIN):
    """sqrt of [I^-1]_tt, I the Poisson Fisher information of (t, s), numerical
    derivatives of the bin means."""
    from scipy.special import ndtr

    e = np.arange(_N + 1) * _BIN

    def mu(t, s):
        return s * np.diff(ndtr((e - t) / _SIG)) + b / _N

    m, h = mu(t, s), 1e-15
    dt = (mu(t + h, s) - mu(t - h, s)) / (2 * h)
    ds = (mu(t, s * 1.001) - mu(t, s * 0.999)) / (0.002 * s)
    info = np.array([[np.sum(dt * dt / m), np.sum(dt * ds / m)],
                     [np.sum(dt * ds / m), np.sum(ds * ds / m)]])
    return float(np.sqrt(np.linalg.inv(info)[0, 0]))


def _timed(fn, *a):
    import time

    fn(*a)  # (compiles, warms the caches)
    best, out = np.inf, None
    for _ in range(3):
        t = time.perf_counter()
        out = fn(*a)
        best = min(best, time.perf_counter() - t)
    return out, best


def off_path(n: int) -> list[str]:
    from stages.ranging import estimate, estimate_returns
    from stages.ranging.irf import Response, fit_response
    from stages.ranging.multi import select_rows

    rng = np.random.default_rng(34)
    x = np.arange(40)
    gauss = Response(np.exp(-0.5 * ((x - 6) / (_SIG / _BIN)) ** 2), _BIN, "the generator's")
    rows = ["| case | estimator | hist/s | RMSE/CRLB | 2-sigma coverage | signal / truth |",
            "|---|---|---|---|---|---|"]
    for s, b in ((100, 100), (1000, 10240)):
        crlb = _crlb(s, b)
        cases = [("cycles given (1e6)", 1e6, None), ("no cycles", None, None),
                 ("measured response", None, "irf"), ("up to 3 returns", None, "multi")]
        for case, cyc, how in cases:
            h, t0 = _generate(rng, n, s, b, cyc)
            names = ("ml", "matched") if how == "irf" else ("fast", "ml", "matched",
                                                             "centroid", "gaussfit")
            for name in names:
                if name == "gaussfit" and how is not None:
                    continue
                # (gaussfit, one curve_fit a row: on 200 rows of its own)
                hh, tt = (h, t0) if name != "gaussfit" else _generate(rng, min(n, 200), s, b,
                                                                      cyc)
                if how == "irf":
                    r, dt = _timed(fit_response, hh, gauss, name, 1e-3)
                elif how == "multi":
                    r, dt = _timed(estimate_returns, hh, _SIG, name, 1e-3, 3)
                    r = select_rows(r, r.return_index == 0)
                else:
                    r, dt = _timed(estimate, hh, _SIG, name, 1e-3)
                err = r.t_s - tt
                ok = np.isfinite(err)
                if how == "irf":  # (a measured response's time is its mode bin's leading
                    # edge: the offset a calibration's delay takes out)
                    err = err - np.median(err[ok])
                rows.append(f"| S {s}, B {b}: {case} | {name} | {hh.counts.shape[0] / dt:.3g} | "
                            f"{np.sqrt(np.mean(err[ok] ** 2)) / crlb:.2f} | "
                            f"{np.mean(np.abs(err[ok]) < 2 * r.sigma_s[ok]):.3f} | "
                            f"{np.nanmedian(r.signal_counts) / s:.2f} |")
    pd_rows = ["| S | B | window test threshold | window test P_d | fast P_d | ml P_d | "
               "fast, no cycles | ml, no cycles |", "|---|---|---|---|---|---|---|---|"]
    for s, b in ((10, 2), (10, 50), (5, 10), (2, 2), (20, 200), (5, 0.2)):
        c0 = _generate(rng, 20_000, 0, b)[0].counts
        cs = np.concatenate([np.zeros((c0.shape[0], 1)), np.cumsum(c0, 1)], 1)
        m0 = (cs[:, 6:] - cs[:, :-6]).max(1)
        thr = next(k for k in range(1, 1000) if np.mean(m0 >= k) <= 1e-3)
        out = []
        for cyc in (1e6, None):
            h, t0 = _generate(rng, 4 * n, s, b, cyc)
            if cyc is not None:
                cs = np.concatenate([np.zeros((h.counts.shape[0], 1)), np.cumsum(h.counts, 1)], 1)
                out.append(f"{thr} | {np.mean((cs[:, 6:] - cs[:, :-6]).max(1) >= thr):.3f}")
            for name in ("fast", "ml"):
                r = estimate(h, _SIG, name, 1e-3)
                out.append(f"{np.mean(r.detected & (np.abs(r.t_s - t0) < 2 * _FWHM)):.3f}")
        pd_rows.append(f"| {s} | {b} | " + " | ".join(out) + " |")
    return ["#### off the grid (independent generator, CRLB derived apart)", "", *rows, "",
            "#### detection probability at p_fa 1e-3 (a detection within 2 FWHM of the truth)",
            "", *pd_rows]


if __name__ == "__main__":
    main()
