"""``tcspc range``: a capture and a calibration in, the ranges dataset out (eq. 5.4)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.constants import c as C_LIGHT

from pipeline.io.atomic import atomic_path
from pipeline.io.caldir import read_bounds, read_tdc_table
from pipeline.io.capture import Capture
from pipeline.offline.calibrate import lsb_at, read_density
from schemas.errors import CalibrationError
from schemas.outputs import HISTOGRAMS, RANGES
from schemas.words import N_CODES
from stages import calibration as cal
from stages.histogram import HistogramAccumulator, HistogramState
from stages.ranging import Estimate, Histograms, estimate


def time_axis(state: HistogramState, caldir: str | Path, window_s: float,
              in_situ: bool = False, density: cal.DensityResult | None = None,
              returns: np.ndarray | None = None):
    """The calibrated time axis of a histogram state: per-code tau edges (n_tdc, 513), the
    code where tau = T falls (x_T), the scale (seconds per unit of the density test's code
    boundaries) and where each TDC's scale came from (with the reason where the capture's
    own reset peak was declined).

    The code boundaries are the density test's (INL); their scale at this measurement's
    light comes from the LSB polynomial (eq. 5.1) read where the window's end falls
    (:func:`stages.calibration.scale_at_light`), or, with ``in_situ``, from the capture's
    own reset peak, looked for where its uniform light ends and trusted only where the
    density test measured those codes and no return (``returns``: each TDC's return code,
    NaN for none) lies close to it (:func:`stages.calibration.scale_in_situ`).
    ``density``: the directory's density test when the caller has read it already (the
    range stage does, per measurement).
    """
    if density is None:
        density, _ = read_density(caldir)
    rows = slice(state.tdc_offset, state.tdc_offset + state.n_tdc)  # a worker's TDC range
    if rows.stop > density.n_tdc:
        raise CalibrationError(f"{caldir}: calibrates {density.n_tdc} TDCs, the histograms "
                               f"reach TDC {rows.stop - 1}")
    density = cal.density_rows(density, rows)
    light = float(state.hits.sum() / (state.n_tdc * max(state.cycles.max(), 1)))
    bounds = cal.code_bounds(density)
    scale = cal.scale_at_light(density, lsb_at(caldir, light)[rows], window_s)
    source = np.full(state.n_tdc, "lsb polynomial", dtype=object)
    if in_situ:
        own, ok, why = cal.scale_in_situ(state.hits, state.cycles, density, window_s,
                                         returns=returns)
        scale = np.where(ok, own, scale)
        source = np.where(ok, "reset peak", "lsb polynomial: " + why.astype(str)) \
            .astype(object)
    tau_edges = bounds * scale[:, None]
    x_t = _x_t(tau_edges, window_s)
    # ... unless the data say otherwise: nothing lies beyond the reset peak, so where the
    # uniform light ends (the last populated code, with light below it) bounds it. A
    # calibration whose LSB is off for this light (a single density test used at another
    # light) would otherwise leave the reset peak inside the searched codes, where it wins
    # as a false target. Without ambient light there is no such step: the last populated
    # code is then a return's tail, and bounding x_T there masked the return itself.
    return tau_edges, _bounded_by_light(state.hits, x_t), scale, source


def _bounded_by_light(hits: np.ndarray, x_t: np.ndarray) -> np.ndarray:
    """x_T bounded by where the uniform light ends, where the light shows a step there
    (:func:`stages.calibration.light_end`)."""
    top, step = cal.light_end(hits)
    return np.where(step, np.minimum(x_t, top), x_t)


def _x_t(tau_edges: np.ndarray, window_s: float) -> np.ndarray:
    """Where tau = T falls on the code axis (fractional code), per TDC."""
    k = np.clip((tau_edges <= window_s).sum(axis=1) - 1, 0, N_CODES - 1)
    r = np.arange(tau_edges.shape[0])
    return k + (window_s - tau_edges[r, k]) / (tau_edges[r, k + 1] - tau_edges[r, k])


def range_state(state: HistogramState, caldir: str | Path, window_s: float,
                t_laser_win_s: float, estimator: str = "ml", sigma_s: float | None = None,
                p_fa: float = 1e-3) -> tuple[Estimate, np.ndarray, np.ndarray]:
    """Ranges of every pixel of a histogram state with a calibration.

    The time axis from :func:`time_axis` (INL, and the LSB polynomial at this
    measurement's light, eq. 5.1), the delay from the calibration's eq. 5.3 measurement.
    ``sigma_s``, the instrument response, defaults to the one measured at zero distance
    (stored with the delay), else 1 LSB. Returns the estimate, distances and sigmas in
    metres.
    """
    density, meta = read_density(caldir)
    tdc = read_tdc_table(caldir)
    rows = slice(state.tdc_offset, state.tdc_offset + state.n_tdc)
    if rows.stop > tdc.num_rows:
        raise CalibrationError(f"{caldir}: calibrates {tdc.num_rows} TDCs, the histograms "
                               f"reach TDC {rows.stop - 1}")
    delay = tdc.column("delay_ps").to_numpy(zero_copy_only=False)[rows]
    if delay is None or np.all(np.isnan(np.asarray(delay, np.float64))):
        raise CalibrationError(f"{caldir}: no delay (run `tcspc calibrate delay` on a "
                               "zero-distance capture first)")
    delay_s = np.asarray(delay, np.float64) * 1e-12
    tau_edges, x_t, _, _ = time_axis(state, caldir, window_s, density=density)
    if sigma_s is None:
        sigma_s = float(meta.get("delay", {}).get(
            "irf_sigma_s", np.median(np.diff(tau_edges, axis=1))))
    h = Histograms.from_codes(state.hits, tau_edges, state.cycles, window_s, x_t=x_t)
    est = estimate(h, sigma_s, estimator, p_fa)
    tau = window_s - est.t_s
    distance = cal.distance_m(t_laser_win_s, delay_s, tau)
    # a pixel without a delay (flagged by `calibrate delay`, reason in meta.json) has no
    # distance: never a detection with a NaN or a guessed range
    est = dataclasses.replace(est, detected=np.asarray(est.detected, bool)
                              & np.isfinite(delay_s))
    return est, distance, est.sigma_s * C_LIGHT / 2


def ranges_table(measurement: str, est: Estimate, distance_m: np.ndarray,
                 sigma_m: np.ndarray, tdc_offset: int = 0) -> pa.Table:
    n = distance_m.size
    return pa.table({
        "measurement": pa.array([measurement] * n, pa.string()),
        "tdc": pa.array(np.arange(n) + tdc_offset, pa.uint16()),
        "distance_m": pa.array(distance_m),
        "sigma_m": pa.array(sigma_m),
        "fwhm_m": pa.array(est.fwhm_s * C_LIGHT / 2),
        "signal_counts": pa.array(np.asarray(est.signal_counts, np.float64)),
        "background_per_bin": pa.array(np.asarray(est.background_per_bin, np.float64)),
        "detected": pa.array(np.asarray(est.detected, bool)),
        "estimator": pa.array([est.estimator] * n, pa.string()),
    }, schema=RANGES.schema)


def range_capture(capture: str | Path, caldir: str | Path, out: str | Path,
                  estimator: str = "ml", sigma_s: float | None = None,
                  p_fa: float = 1e-3) -> pa.Table:
    cap = Capture(capture)
    acc = HistogramAccumulator(cap.meta.n_tdc, read_bounds(caldir, cap.meta.n_tdc))
    for first, words in cap.iter_chunks():
        acc.update(words, first)
    est, d, s = range_state(acc.snapshot(), caldir, cap.meta.window_ns * 1e-9,
                            cap.meta.t_laser_win_ns * 1e-9, estimator, sigma_s, p_fa)
    table = ranges_table(cap.name, est, d, s)
    table = table.replace_schema_metadata({**table.schema.metadata,
                                           b"tcspc.calibration": str(Path(caldir)).encode(),
                                           b"tcspc.capture": str(cap.bin_path).encode()})
    with atomic_path(out) as tmp:
        pq.write_table(table, tmp)
    return table


class RangeCore:
    """The range stage: each histograms message (a measurement, or a worker's TDC range of
    one) in, its ranges out, the histograms passed on beside them for the sink. Stateless:
    a measurement is ranged on its own, so a fan-out needs no join."""

    in_spec = HISTOGRAMS
    out_spec = RANGES

    def __init__(self, caldir: str | Path, estimator: str = "ml", window_ns: float = 80.0,
                 step_id: str = "range", forward_histograms: bool = True):
        read_density(caldir)  # fail at start, not on the first message
        self.caldir, self.estimator, self.window_ns = Path(caldir), estimator, window_ns
        self.step_id, self.forward = step_id, forward_histograms
        self.ranged = 0

    def process(self, header: dict, batch: pa.RecordBatch) -> list:
        import warnings

        state = HistogramState.from_table(pa.Table.from_batches([batch]))
        window_s = float(header.get("window_ns", self.window_ns)) * 1e-9
        gate_s = float(header["t_laser_win_ns"]) * 1e-9
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # light outside the LSB fit: noted in the header
            est, d, s = range_state(state, self.caldir, window_s, gate_s, self.estimator)
        name = str(header.get("measurement", header["run"]))
        table = ranges_table(name, est, d, s, state.tdc_offset)
        head = {**header, "schema": RANGES.name, "version": RANGES.version,
                "step": self.step_id, "detected": int(np.sum(est.detected))}
        self.ranged += 1
        out = [(head, b) for b in table.to_batches()]
        return ([(header, batch)] if self.forward else []) + out

    def finish(self, header: dict) -> list:
        return []
