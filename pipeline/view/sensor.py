"""The sensor as the page shows it: the array's layout, per-pixel maps, a histogram's marks
(the reset peak and the detected return) and the calibration in use with the drift of the
online LSB estimate (``tcspc calibrate track``'s measurement, on every measurement).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from stages import calibration as cal
from stages.calibration import RESET_SEARCH

#: A pixel counting more than this many times the array's median hits per cycle is hot.
HOT_FACTOR = 5.0


def default_layout(n_tdc: int) -> tuple[int, int]:
    """(columns, rows) of the array: 16 x 8 for 128 TDCs, a power-of-two width about twice
    the height otherwise."""
    if n_tdc <= 0:
        return (1, 1)
    cols = 2 ** math.ceil(math.log2(math.sqrt(2 * n_tdc)))
    return cols, math.ceil(n_tdc / cols)


def parse_layout(text: str | None, n_tdc: int) -> tuple[int, int]:
    """``"16x8"`` (columns x rows) or None for :func:`default_layout`; TDC t sits at column
    ``t % columns``, row ``t // columns`` (row 0 at the top)."""
    if not text:
        return default_layout(n_tdc)
    try:
        cols, rows = (int(x) for x in text.lower().split("x"))
    except ValueError:
        raise ValueError(f"layout {text!r}: use COLUMNSxROWS, e.g. 16x8") from None
    if cols < 1 or rows < 1:
        raise ValueError(f"layout {text!r}: columns and rows must be at least 1")
    if cols * rows < n_tdc:
        raise ValueError(f"layout {text!r} has {cols * rows} places for {n_tdc} TDCs")
    return cols, rows


def pixel_xy(tdc, layout: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    cols, _ = layout
    tdc = np.asarray(tdc, np.int64)
    return tdc % cols, tdc // cols


def geometry_xy(tdc, geom) -> tuple[np.ndarray, np.ndarray, tuple[int, int]]:
    """Column and row of each TDC on a geometry's array (NaN: the geometry has no pixel
    for it), and the array as (columns, rows)."""
    i = geom.index_of(np.asarray(tdc, np.int64))
    ok = i >= 0
    j = np.maximum(i, 0)
    return (np.where(ok, geom.col[j], np.nan), np.where(ok, geom.row[j], np.nan),
            (int(geom.cols), int(geom.rows)))


def pixel_flags(n_hit, cycles) -> tuple[np.ndarray, np.ndarray]:
    """(dead, hot) per TDC: dead counts no hit in a measurement that read it; hot counts
    more than ``HOT_FACTOR`` times the array's median hits per cycle."""
    n_hit = np.asarray(n_hit, np.float64)
    cycles = np.asarray(cycles, np.float64)
    rate = np.divide(n_hit, cycles, out=np.zeros_like(n_hit), where=cycles > 0)
    med = float(np.median(rate)) if rate.size else 0.0
    dead = (cycles > 0) & (n_hit == 0)
    hot = (rate > HOT_FACTOR * med) if med > 0 else np.zeros(rate.shape, bool)
    return dead, hot


def reset_peak_codes(counts: np.ndarray) -> np.ndarray:
    """Per TDC the reset peak's code (tau = T: where the uniform light ends, the highest
    count of the last codes populated), -1 for an empty histogram."""
    h = np.asarray(counts)
    top, _ = cal.light_end(h)
    k = np.arange(h.shape[1])[None, :]
    zone = (k >= top[:, None] - 1 - RESET_SEARCH) & (k < top[:, None])
    code = np.argmax(np.where(zone, h, -1), axis=1)
    return np.where(top > 0, code, -1)


@dataclass(frozen=True)
class RunConstants:
    """What turns a distance back into a code: the run's window and gate."""

    window_s: float
    t_laser_win_s: float | None
    #: why the gate is unknown ("" when it is known)
    why: str = ""


def run_constants(journal_dir, run: str) -> RunConstants:
    """From the run's journal (``RUN.meta.json``); an 80 ns window and no gate without it,
    ``why`` saying what is missing (the view reads it again until it appears)."""
    from pipeline.stream.journal import run_meta

    meta = run_meta(journal_dir, run) if journal_dir else {}
    gate = meta.get("t_laser_win_ns")
    why = ""
    if gate is None:
        path = Path(journal_dir or "") / f"{run}.meta.json"
        if not journal_dir or not Path(journal_dir).is_dir():
            why = f"no journal at {journal_dir} (yet)"
        elif not path.exists():
            why = f"{path} not written (yet): the run has not reached the journal"
        else:
            why = f"{path} holds no gate (t_laser_win_ns)"
    return RunConstants(float(meta.get("window_ns", 80.0)) * 1e-9,
                        None if gate is None else float(gate) * 1e-9, why)


def return_codes(meas, ranges, calibration, consts: RunConstants) -> tuple[np.ndarray, str]:
    """Per TDC of ``meas`` the code of its detected return (fractional, NaN where none), and
    a note ("" when every detection could be placed).

    eq. 5.4 backwards: tau = T_Laser-Win - T_delay - 2 d / c, then the code boundary tau
    falls on, on the time axis the range stage used (each worker's TDC rows at their own
    light: :func:`stages.calibration_set.time_axis`)."""
    from scipy.constants import c as C_LIGHT

    from stages.calibration_set import time_axis

    n = meas.tdc.size
    out = np.full(n, np.nan)
    if ranges is None or ranges.height == 0:
        return out, "no ranges for this measurement (a run without a range stage, or not "\
                    "written yet)"
    if calibration is None:
        return out, "return not marked: no calibration given (--calibration)"
    if consts.t_laser_win_s is None:
        return out, f"return not marked: the run's gate is unknown: {consts.why or 'no journal'}"
    if calibration.n_tdc < int(meas.tdc.max()) + 1:
        return out, (f"return not marked: the calibration has {calibration.n_tdc} TDCs, "
                     f"the run {int(meas.tdc.max()) + 1}")
    pos = {int(t): i for i, t in enumerate(meas.tdc)}
    dist = dict(zip(ranges["tdc"].to_list(), ranges["distance_m"].to_list(), strict=True))
    det = dict(zip(ranges["tdc"].to_list(), ranges["detected"].to_list(), strict=True))
    for first, rows in meas.groups:
        idx = [pos[t] for t in range(first, first + rows) if t in pos]
        if len(idx) != rows:
            continue
        axis = time_axis(calibration.rows(first, first + rows), meas.counts[idx],
                         meas.cycles[idx], consts.window_s)
        for j, i in enumerate(idx):
            t = int(meas.tdc[i])
            if not det.get(t) or not np.isfinite(dist.get(t, np.nan)):
                continue
            tau = (consts.t_laser_win_s - calibration.delay_s[t]
                   - 2 * dist[t] / C_LIGHT)
            edges = axis.tau_edges_s[j]
            if np.isfinite(tau) and edges[0] <= tau <= edges[-1]:
                out[i] = float(np.interp(tau, edges, np.arange(edges.size)))
    return out, ""


def calibration_frames(calibration, light: float | None = None) -> dict:
    """The calibration's LSB per TDC (at its density test's light, and at ``light`` from eq.
    5.1 when given) and its INL (``inl_lsb``: (n_tdc, 512), NaN above the window)."""
    d = calibration.density
    lsb_now = None
    note = ""
    if light is not None and np.isfinite(light):
        lsb_s, note = calibration.lsb_s(light)
        lsb_now = lsb_s * 1e12
    inl = np.asarray(d.inl_lsb, np.float64)
    with np.errstate(invalid="ignore"):
        rms = np.sqrt(np.nanmean(inl ** 2, axis=1))
    return {"tdc": np.arange(d.n_tdc), "lsb_ps": np.asarray(d.lsb_s) * 1e12,
            "lsb_at_light_ps": lsb_now, "light": light, "note": note,
            "inl_lsb": inl, "inl_rms_lsb": rms, "ok": np.asarray(d.ok, bool),
            "delay_ps": np.asarray(calibration.delay_s) * 1e12, "path": calibration.path}


def light_of(meas) -> float:
    """Detections per pixel per cycle of a measurement (eq. 5.1's n)."""
    return float(meas.counts.sum() / (max(meas.tdc.size, 1) * max(int(meas.cycles.max()), 1)))


def lsb_drift(meas, calibration, window_s: float, min_hits: int = 1000) -> dict:
    """The online LSB estimate of one measurement (each TDC's uniform background taken as a
    density test, its returns masked: :func:`stages.calibration.track_lsb`) against the
    calibration's LSB at the measurement's light: median and 10 / 90 % of the per-TDC drift
    in ps over the TDCs that had ``min_hits`` and whose estimate can be trusted; those left
    out are ``flagged`` (TDC -> why: :func:`stages.calibration.track_lsb`)."""
    if calibration is None or calibration.n_tdc < int(meas.tdc.max()) + 1:
        return {"k": meas.k, "n": 0}
    light = light_of(meas)
    expected, _ = calibration.lsb_s(light)
    tr = cal.track_lsb(meas.counts, meas.cycles, window_s, expected[meas.tdc],
                       min_hits=min_hits)
    flagged = {int(meas.tdc[i]): tr.why[i] for i in np.flatnonzero(tr.flagged)}
    d = tr.drift_ps[np.isfinite(tr.drift_ps)]
    if d.size == 0:
        return {"k": meas.k, "n": 0, "light": light, "flagged": flagged}
    lo, med, hi = np.percentile(d, [10, 50, 90])
    with np.errstate(invalid="ignore"):
        lsb_ps = float(np.nanmedian(np.where(tr.flagged, np.nan, tr.lsb_s)) * 1e12)
    return {"k": meas.k, "n": int(d.size), "light": light, "median_ps": float(med),
            "p10_ps": float(lo), "p90_ps": float(hi), "lsb_ps": lsb_ps, "flagged": flagged}
