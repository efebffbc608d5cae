"""The calibration's own sigma (issue 33.3) against its error per TDC, on the 16-TDC chip of
``benchmarks/spatial_chip.py`` re-calibrated from other simulated captures (``--cal-seed``
N: other fixed errors a TDC). The simulator knows the chip, so each part of a range's
calibration error is measured against the truth and divided by the sigma the calibration
claims for it (z; an honest sigma gives z RMS ~1 pooled over the TDCs and calibrations):

- **table**: the table's ratio ``B(x) / B(x_T,i)`` at codes 50-340 against each density
  test's x_T (a time on the axis at that test's light) against ``table_sigma_s``;
- **scale at x_T**: the axis at the zero capture's and a range capture's light read at the
  chip's true x_T (where tau = T), against ``table_sigma_s`` at that code (the scale
  interpolated between the tests, ``Calibration.scale_refs``);
- **delay**: ``delay_s`` against the truth (the gate's delay and the 1 mm target) over
  ``delay_sigma_ps``;
- **range**: each TDC's mean range error over ``--seeds`` captures of the mirrors at 1.5 and
  2.5 m (reflectivity 0.002: the calibration's error dominates) over the calibration's
  part of sigma_m (``calibration_sigma_s``).

    python benchmarks/calibration_truth.py [--cal-seeds 0 1 2 3 4 5 6] [--seeds 3]
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np
from scipy.constants import c as C_LIGHT

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.spatial_chip import N, scene  # noqa: E402
from pipeline.io.caldir import load_calibration  # noqa: E402
from pipeline.io.capture import Capture  # noqa: E402
from pipeline.offline.ranging import (  # noqa: E402
    calibrated_axis,
    calibration_sigma_s,
    range_state,
)
from pipeline.offline.simulate import simulate_capture, simulated_calibration  # noqa: E402
from stages.calibration import uncertainty  # noqa: E402
from stages.calibration_set import time_axis  # noqa: E402
from stages.histogram import HistogramAccumulator  # noqa: E402
from stages.simulator.chip import make_chip  # noqa: E402

T = 80e-9
CODES = np.arange(513.0)
RATIO_AT = (50.0, 150.0, 250.0, 340.0)


def state_of(path: Path, calib):
    cap = Capture(path)
    acc = HistogramAccumulator(N, calib.bounds)
    for first, words in cap.iter_chunks():
        acc.update(words, first)
    return cap, acc.snapshot()


def at(rows, x) -> np.ndarray:
    """Each row of ``rows`` (n, 513) read at its fractional code ``x`` (n,)."""
    return np.array([np.interp(xi, CODES, r) for r, xi in zip(rows, x, strict=True)])


def table_z(calib, chip) -> np.ndarray:
    """z of ``B(x) / B(x_T,i)`` at ``RATIO_AT`` against every density test's x_T."""
    b, bt = calib.code_bounds, CODES[None, :] + chip.inl_lsb
    fit = calib.lsb_fit
    pts = fit.points_ps()[:, np.argsort(fit.levels)] * 1e-12
    out = []
    for i in range(pts.shape[1]):
        xr = T / pts[:, i]
        for x in RATIO_AT:
            xs = np.full(N, x)
            err = at(b, xs) / at(b, xr) - at(bt, xs) / at(bt, xr)
            said = uncertainty.table_sigma_s(calib.width_var_lsb2, xs, xr, np.ones(N)) / xr
            out.append(err / said)
    return np.concatenate(out)


def scale_z(calib, path: Path) -> np.ndarray:
    """z of the axis at the true x_T of the capture at ``path``."""
    cap, st = state_of(path, calib)
    axis = time_axis(calib, st.hits, st.cycles, T)
    x_t = np.asarray(cap.meta.truth["chip"]["x_t"], np.float64)
    light = float(st.hits.sum() / (N * np.max(st.cycles)))
    refs = calib.scale_refs(T, light, axis.source) if hasattr(calib, "scale_refs") else ()
    said = uncertainty.table_sigma_s(calib.width_var_lsb2, x_t, axis.x_t, axis.scale,
                                     *([refs] if refs != () else []))
    return (at(axis.tau_edges_s, x_t) - T) / said


def one(cal_seed: int, seeds: int) -> dict:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        calib = load_calibration(simulated_calibration(tmp, N, seed=cal_seed))
        chip = make_chip(N, 1)
        d = calib.meta["delay"]
        delay_err = np.asarray(calib.delay_s) - (100e-9 + 2 * 0.001 / C_LIGHT)
        delay_sig = np.asarray(d["delay_sigma_ps"], np.float64) * 1e-12
        truth = np.where(np.arange(N) < 8, 1.5, 2.5)
        err, cal_sig = [], []
        for seed in range(seeds):
            out = tmp / f"r{seed}"
            simulate_capture(scene(0.002), 6000, out, seed=100 + seed)
            cap, st = state_of(out, calib)
            gate = cap.meta.t_laser_win_ns * 1e-9
            est, dist, _, _ = range_state(st, calib, T, gate, "ml")
            rows, axis = calibrated_axis(st, calib, T)
            cal_sig.append(calibration_sigma_s(calib, rows, st, axis, est, T) * C_LIGHT / 2)
            err.append(np.where(est.detected, dist - truth, np.nan))
        return {"table": table_z(calib, chip),
                "scale at the zero's light": scale_z(calib, tmp / "delay"),
                "scale at the range's light": scale_z(calib, tmp / "r0"),
                "delay": delay_err / delay_sig,
                "range": np.nanmean(err, axis=0) / np.nanmean(cal_sig, axis=0),
                "delay sigma ps": delay_sig * 1e12,
                "range sigma mm": np.nanmean(cal_sig, axis=0) * 1e3}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cal-seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4, 5, 6])
    ap.add_argument("--seeds", type=int, default=3)
    a = ap.parse_args()
    print("$ python benchmarks/calibration_truth.py " + " ".join(sys.argv[1:]))
    print(f"load average {os.getloadavg()[0]:.1f}\n")
    parts = ("table", "scale at the zero's light", "scale at the range's light", "delay",
             "range")
    print("| cal-seed | " + " | ".join(f"{p}: z RMS" for p in parts)
          + " | range: share abs(z) > 2 | median delay sigma ps | median range sigma mm |")
    print("|---:|" + "---:|" * (len(parts) + 3))
    pooled: dict = {p: [] for p in parts}
    for cs in a.cal_seeds:
        r = one(cs, a.seeds)
        for p in parts:
            pooled[p].append(r[p])
        print(f"| {cs} | " + " | ".join(f"{np.sqrt(np.nanmean(r[p] ** 2)):.2f}" for p in parts)
              + f" | {np.nanmean(np.abs(r['range']) > 2):.3f} | "
              f"{np.nanmedian(r['delay sigma ps']):.0f} | "
              f"{np.nanmedian(r['range sigma mm']):.1f} |", flush=True)
    z = {p: np.concatenate(v) for p, v in pooled.items()}
    print("| pooled | " + " | ".join(f"{np.sqrt(np.nanmean(z[p] ** 2)):.2f}" for p in parts)
          + f" | {np.nanmean(np.abs(z['range']) > 2):.3f} | | |")


if __name__ == "__main__":
    main()
