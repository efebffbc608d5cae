"""``tcspc range``: a capture and a calibration in, the ranges dataset out (eq. 5.4)."""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.constants import c as C_LIGHT

from pipeline.io.atomic import atomic_path
from pipeline.io.capture import Capture
from schemas.constants import HIT, N_CLASSES, N_CODES, NO_HIT
from schemas.errors import CalibrationError
from schemas.outputs import HISTOGRAMS, RANGES
from stages import calibration as cal
from stages.calibration_set import Calibration, time_axis
from stages.histogram import HistogramAccumulator, HistogramState
from stages.ranging import Estimate, Histograms, estimate_returns, response_from_data
from stages.ranging.multi import MAX_RETURNS, select_rows


def calibrated_axis(state: HistogramState, calibration: Calibration, window_s: float):
    """The calibration's rows of the measurement's TDCs and their time axis at its light
    (``time_axis``); CalibrationError for a calibration without a delay or rows."""
    if not calibration.has_delay:
        raise CalibrationError(f"{calibration.path}: no delay (run `tcspc calibrate delay` "
                               "on a zero-distance capture first)")
    try:
        calib = calibration.rows(state.tdc_offset, state.tdc_offset + state.n_tdc)
    except ValueError as exc:
        raise CalibrationError(str(exc)) from exc
    return calib, time_axis(calib, state.hits, state.cycles, window_s)


def range_state(state: HistogramState, calibration: Calibration, window_s: float,
                t_laser_win_s: float, estimator: str = "ml", sigma_s: float | None = None,
                p_fa: float = 1e-3, in_situ: bool = False, max_returns: int = 1
                ) -> tuple[Estimate, np.ndarray, np.ndarray, str]:
    """Ranges of every pixel of a histogram state with a calibration.

    The time axis from :func:`stages.calibration_set.time_axis` (INL, and the LSB
    polynomial at this measurement's light, eq. 5.1), the delay from the calibration's eq.
    5.3 measurement. With ``in_situ``, the axis's scale comes from the capture's own reset
    peak where that is trustworthy, as ``calibrate delay`` does (the returns located first
    on the polynomial's axis, so that the reset peak's fit keeps clear of them), else
    from the polynomial. ``sigma_s``, the instrument response, defaults to the one
    measured at zero distance (stored with the delay), else the one measured on this
    state's returns (:func:`stages.ranging.width.response_from_data`; one LSB made sigmas
    7-11x too small on a response 4 LSB wide). Up to ``max_returns`` returns a pixel
    (:func:`stages.ranging.multi.estimate_returns`: ``est.pixel`` and
    ``est.return_index`` say whose each row is). A pixel without a delay is not detected,
    a return before the zero (the delay beyond it) is flagged and not detected. Returns
    the estimate, distances and sigmas in metres, and a note for the user ("" when the
    calibration covers this measurement's light).
    """
    calib, axis = calibrated_axis(state, calibration, window_s)
    notes = []

    def run(axis, sigma_s):
        h = Histograms.from_codes(state.hits, axis.tau_edges_s, state.cycles, window_s,
                                  x_t=axis.x_t)
        if sigma_s is None:
            sigma_s = calib.irf_sigma_s
        if not sigma_s:
            sigma_s, how = response_from_data(h)
            notes.append(f"instrument response sigma {sigma_s * 1e12:.1f} ps {how}")
        return estimate_returns(h, sigma_s, estimator, p_fa, max_returns), sigma_s

    est, sigma_s = run(axis, sigma_s)
    if in_situ:
        first = est.return_index == 0
        returns = _codes_of(window_s - est.t_s[first], axis.tau_edges_s, est.detected[first])
        situ = time_axis(calib, state.hits, state.cycles, window_s, in_situ=True,
                         returns=returns)
        if np.any(situ.source == "reset peak"):
            axis, (est, _) = situ, run(situ, sigma_s)
    delay = np.asarray(calib.delay_s, np.float64)[est.pixel]
    distance = cal.distance_m(t_laser_win_s, delay, window_s - est.t_s)
    # a pixel without a delay (flagged by `calibrate delay`, reason in meta.json) has no
    # distance: never a detection with a NaN or a guessed range
    est = dataclasses.replace(est, detected=np.asarray(est.detected, bool) & np.isfinite(delay))
    est, distance = behind_zero(est, distance)
    note = "; ".join(n for n in (axis.note, *notes,
                                 _unresolved(calib, state, axis, est, window_s)) if n)
    cal_s = calibration_sigma_s(calibration, calib, state, axis, est, window_s)
    sigma_s = np.asarray(est.sigma_s, np.float64)
    sigma_s = np.where(np.isfinite(cal_s), np.hypot(sigma_s, cal_s), sigma_s)
    return est, distance, sigma_s * C_LIGHT / 2, note


def calibration_sigma_s(calibration: Calibration, calib: Calibration, state, axis,
                        est: Estimate, window_s: float) -> np.ndarray:
    """Per row of ``est``, the standard error (s) the calibration itself puts on its
    range's time (issue 33.3), NaN where the calibration does not say (one made before it):
    the table's counting noise over the codes between the return (at this light) and the
    delay's return (at the zero's), taken together so the codes both span cancel
    (:func:`stages.calibration.uncertainty.range_sigma_s`); the zero capture's peak fit;
    the time scale's at both lights (the LSB interpolation's spread); and the scale's
    where this capture's light, counted, is off by its binomial error
    (:meth:`Calibration.scale_slope`). ``calib``: the rows of ``calibration`` the state
    covers."""
    from stages.calibration import uncertainty

    u = calibration.meta.get("delay", {}).get("uncertainty")
    px = est.pixel if est.pixel is not None else np.arange(state.n_tdc)
    n = np.size(est.t_s)
    if not u or calib.width_var_lsb2 is None:
        return np.full(n, np.nan)
    rows = state.tdc_offset + px

    def stored(key):
        return np.array([np.nan if v is None else v for v in u[key]], np.float64)[rows]

    x0, xr0, s0, rel0 = (stored(k) for k in ("return_code", "x_t", "scale_s",
                                              "scale_rel_sigma"))
    peak0 = np.array([np.nan if v is None else v for v in
                      calibration.meta["delay"].get("sigma_ps", [None] * calibration.n_tdc)],
                     np.float64)[rows] * 1e-12
    tau = window_s - np.asarray(est.t_s, np.float64)
    x = uncertainty.codes_at(tau, axis.tau_edges_s[px])
    light = cal.light_level(state.hits, state.cycles)
    # where a scale is the density tests' interpolated, its error is the table's at their
    # x_T (the range's at this light, the delay's at the zero's: as `calibrate delay` took it)
    refs = _rows_of(calib.scale_refs(window_s, light, axis.source), px)
    zero = calibration.meta["delay"]
    refs0 = None
    if zero.get("light") is not None and zero.get("scale_from") is not None:
        refs0 = _rows_of(calibration.scale_refs(window_s, float(zero["light"]),
                                                 zero["scale_from"]), rows)
    table = uncertainty.range_sigma_s(calib.width_var_lsb2[px], x, axis.x_t[px],
                                      axis.scale[px], x0, xr0, s0, refs, refs0)
    spread, _ = cal.scale_spread(calib.density, calib.lsb_fit, window_s, light,
                                 calib.scale_splines(window_s))
    rel = np.where(np.asarray(axis.source)[px] == "reset peak", 0.0,
                   uncertainty.scale_rel_sigma(spread[px]))
    # the light the scale is read at is itself counted: its binomial error over the
    # capture's TDC-cycles moves the scale by the LSB's slope (a short capture, where the
    # LSB bends: 0.7 % of 0.13 detections a cycle in 6000 cycles of 16 TDCs, 4e-4 of the
    # scale); not where the capture's own reset peak scales the axis
    cycles = float(np.max(state.cycles)) * state.n_tdc
    sd_n = np.sqrt(max(light * (1.0 - light), 0.0) / max(cycles, 1.0))
    rel_n = np.where(np.asarray(axis.source)[px] == "reset peak", 0.0,
                     np.nan_to_num(np.abs(calib.scale_slope(window_s, light)[px])) * sd_n)
    tau0 = s0 * cal._bound_at(calib.code_bounds[px], x0)
    return np.sqrt(table ** 2 + np.nan_to_num(peak0) ** 2 + (rel * tau) ** 2
                   + (rel_n * tau) ** 2 + np.nan_to_num(rel0 * tau0) ** 2)


def _rows_of(refs, rows):
    """:meth:`Calibration.scale_refs`'s ``(codes, weights)`` at ``rows`` (None stays)."""
    return None if refs is None else tuple(np.asarray(a)[rows] for a in refs)


#: the flag of a return before the zero
#: what an estimator's sigma is worth, where it is not the Fisher information's (ml and
#: fast: 2-sigma coverage 0.95-0.97 from outside, docs/ranging.md): said in `range`'s
#: output and the ranges' metadata (``tcspc.sigma``), issue 34.5
SIGMA_NOTE = {
    "matched": "matched's sigma (the response's over the root of the counts, background "
               "left out) does not cover: 2-sigma coverage 0.81-0.90 measured",
    "centroid": "centroid's sigma (the second moment's) does not cover: 2-sigma coverage "
                "0.34-0.91 measured, less with more counts",
    "gaussfit": "gaussfit's sigma (curve_fit's covariance) does not cover: 2-sigma "
                "coverage 0.25-0.94 measured, 0 under pile-up"}

BEHIND_ZERO = "before the zero (the delay is beyond the return)"
#: how many of its own sigmas an estimate may fall before the zero and still be a target
#: at the zero (the delay's own capture ranges to 0 +- sigma: half of it lands below 0)
AT_ZERO_SIGMAS = 3.0
#: ... and never more than this: a poorly measured return (tens of counts beside the
#: TMF8820's crosstalk, sigma 3-4 mm) 6-10 mm before the zero is not placed at it
AT_ZERO_MAX_M = 2e-3


def behind_zero(est: Estimate, distance_m):
    """No negative distance leaves here.

    An estimate before the zero by no more than ``AT_ZERO_SIGMAS`` of its own sigma (and
    ``AT_ZERO_MAX_M``) is a target at the zero: its distance is 0, it stays detected, and
    (beyond a nanometre of rounding) its flag says how far before the zero it fell.
    Further before the zero the row is flagged, not detected, and its distance NaN (a
    delay beyond the return gave -0.45 m with no warning); a further return
    (``return_index`` > 0) so withdrawn is dropped (such rows are detections)."""
    d = np.asarray(distance_m, np.float64)
    sigma_m = np.asarray(est.sigma_s, np.float64) * C_LIGHT / 2
    with np.errstate(invalid="ignore"):
        neg = d < 0
        tol = np.minimum(AT_ZERO_SIGMAS * np.where(np.isfinite(sigma_m), sigma_m, 0.0),
                         AT_ZERO_MAX_M)
        near = neg & (-d <= tol)
    if not neg.any():
        return est, d
    far = neg & ~near
    flag = np.array(est.flag if est.flag is not None else [""] * d.size, dtype=object)
    for i in np.flatnonzero(near & (d < -1e-9) & (flag == "")):
        flag[i] = f"at the zero: {-d[i] * 1e3:.3g} mm before it, within its noise (distance 0)"
    flag[far] = BEHIND_ZERO
    est = dataclasses.replace(est, detected=np.asarray(est.detected, bool) & ~far, flag=flag)
    d = np.where(far, np.nan, np.where(near, 0.0, d))
    if est.return_index is None:
        return est, d
    keep = (est.return_index == 0) | est.detected
    return select_rows(est, keep), d[keep]


def _unresolved(calib: Calibration, state: HistogramState, axis, est: Estimate,
                window_s: float) -> str:
    """The note for detected targets at a light the density tests' levels do not resolve
    (:func:`stages.calibration.scale_unresolved`, the rule of ``calibrate delay``'s flag,
    with the range fit's sigma), "" otherwise."""
    light = cal.light_level(state.hits, state.cycles)
    px = est.pixel if est.pixel is not None else np.arange(state.n_tdc)
    spread, (lo, hi) = cal.scale_spread(calib.density, calib.lsb_fit, window_s, light,
                                        calib.scale_splines(window_s))
    tau_s = window_s - np.asarray(est.t_s, np.float64)
    bad = (np.asarray(est.detected, bool) & (np.asarray(axis.source)[px] != "reset peak")
           & cal.scale_unresolved(spread[px], tau_s,
                                  cal.density_rows(calib.density, px), est.sigma_s))
    if not bad.any():
        return ""
    return (f"LSB against light not resolved between the density tests at {lo:.3g} and "
            f"{hi:.3g} detections a cycle (this capture: {light:.2g}) on {int(bad.sum())} "
            "detected target(s): they may be off beyond their sigma; add a density test "
            f"near {light:.2g} to `tcspc calibrate lsb`")


def _codes_of(tau_s, tau_edges_s, keep) -> np.ndarray:
    """Fractional codes of times ``tau_s`` on each row's axis (NaN where not ``keep``)."""
    return np.array([np.interp(t, e, np.arange(e.size, dtype=np.float64))
                     if k and np.isfinite(t) and np.all(np.isfinite(e)) else np.nan
                     for t, e, k in zip(tau_s, tau_edges_s, keep, strict=True)])


def ranges_table(measurement: str, est: Estimate, distance_m: np.ndarray,
                 sigma_m: np.ndarray, tdc_offset: int = 0) -> pa.Table:
    """The ``ranges`` rows of an estimate: one a pixel, or one a pixel and return where the
    estimate has several (``est.pixel``, ``est.return_index``)."""
    n = distance_m.size
    pixel = np.arange(n) if est.pixel is None else np.asarray(est.pixel)
    index = np.zeros(n, np.int64) if est.return_index is None else est.return_index
    flag = [""] * n if est.flag is None else [str(f) for f in est.flag]
    return pa.table({
        "measurement": pa.array([measurement] * n, pa.string()),
        "tdc": pa.array(pixel + tdc_offset, pa.uint32()),
        "distance_m": pa.array(distance_m),
        "sigma_m": pa.array(sigma_m),
        "fwhm_m": pa.array(np.asarray(est.fwhm_s, np.float64) * C_LIGHT / 2),
        "signal_counts": pa.array(np.asarray(est.signal_counts, np.float64)),
        "background_per_bin": pa.array(np.asarray(est.background_per_bin, np.float64)),
        "detected": pa.array(np.asarray(est.detected, bool)),
        "estimator": pa.array([est.estimator] * n, pa.string()),
        "return_index": pa.array(index, pa.uint8()),
        "flag": pa.array(flag, pa.string()),
    }, schema=RANGES.schema)


#: The flag of every row ranged with ``--force`` on a capture whose code-density pattern
#: is not the calibration's chip's, and of a TDC that alone disagrees (issue 33.4).
CHIP_MISMATCH = "calibration of another chip (code-density pattern)"
#: A stream's measurement that the run ended inside (a stop, an interrupted or failed run):
#: ranged on what it holds; a resumed run completes it and its ranges replace these.
PARTIAL = "partial measurement: the run ended inside it"
#: A spatial frame ranged without some of its TDCs (their worker's part did not arrive):
#: its neighbours there were missing; the reconciliation ranges it again from the journal.
INCOMPLETE_FRAME = "ranged without some TDCs' part (spatial)"
TDC_MISMATCH = "this TDC's code-density pattern is not the calibration's"
#: A TDC of a matching capture is flagged alone where its own excess is over this many
#: sigmas (and its widths differ by more than a chip's drift): one in ~3.5 million by
#: chance, so 128 TDCs flag none falsely.
TDC_FLAG_SIGMAS = 5.0


def return_codes(calibration: Calibration, state: HistogramState, est: Estimate,
                 window_s: float) -> np.ndarray:
    """(n_tdc, 512) bool: the codes of every return ``est`` detected, to its response's
    reach each side (3 sigmas of the calibration's instrument response, else of the
    return's own width, and 3 codes): not the capture's uniform light."""
    axis = time_axis(calibration.rows(state.tdc_offset, state.tdc_offset + state.n_tdc),
                     state.hits, state.cycles, window_s)
    out = np.zeros(state.hits.shape, bool)
    px = est.pixel if est.pixel is not None else np.arange(state.n_tdc)
    det = np.asarray(est.detected, bool)
    tau = window_s - np.asarray(est.t_s, np.float64)
    code = _codes_of(tau, axis.tau_edges_s[px], det)
    with np.errstate(invalid="ignore"):
        lsb = window_s / axis.x_t[px]
        width = (np.full(px.size, calibration.irf_sigma_s) if calibration.irf_sigma_s
                 else np.asarray(est.fwhm_s, np.float64) / 2.3548)
        reach = 3 * np.nan_to_num(width, nan=2 * np.nanmedian(lsb)) / lsb + 3
    k = np.arange(state.hits.shape[1])
    for p, c, r in zip(px[det], code[det], reach[det], strict=True):
        if np.isfinite(c) and np.isfinite(r):
            out[p] |= np.abs(k + 0.5 - c) <= r
    return out


def check_capture_chip(calibration: Calibration, state: HistogramState, est: Estimate,
                       window_s: float):
    """:func:`stages.calibration.chip_check.check_chip` of a capture's histograms against
    the calibration's widths (and their variance; from its INL error where it stores
    none), its returns left out."""
    from stages.calibration import uncertainty
    from stages.calibration.chip_check import check_chip

    rows = slice(state.tdc_offset, state.tdc_offset + state.n_tdc)
    var = (uncertainty.width_var_from_inl_error(calibration.density)
           if calibration.width_var_lsb2 is None else calibration.width_var_lsb2)[rows]
    return check_chip(state.hits, state.cycles, calibration.density.width_lsb[rows], var,
                      exclude=return_codes(calibration, state, est, window_s))


def mismatch_message(capture, calibration: Calibration, check, tdc_offset: int = 0) -> str:
    """The one line of a refusal: which TDCs disagree, and the pooled evidence."""
    bad = np.flatnonzero(check.disagree) + tdc_offset
    named = ", ".join(str(t) for t in bad[:12]) + (", ..." if bad.size > 12 else "")
    return (f"capture {capture} does not match calibration {calibration.path} "
            f"({calibration.meta.get('calibration_id', '')}): "
            + (f"TDCs {named} ({bad.size} of {check.n_tdc})" if bad.size else
               f"no TDC alone, {int(check.tdc_ok.sum())} TDCs pooled")
            + f"; {check.summary()}; --force ranges it anyway, its rows flagged")


def _flag_rows(est: Estimate, rows: np.ndarray, why: str) -> Estimate:
    """``est`` with ``why`` added to the flag of the rows ``rows`` (bool per row)."""
    if not np.any(rows):
        return est
    n = np.size(est.t_s)
    flag = np.array(est.flag if est.flag is not None else [""] * n, dtype=object)
    flag[rows] = [f"{f}; {why}" if f else why for f in flag[rows]]
    return dataclasses.replace(est, flag=flag)


#: The range stage checks its first measurement and every this many after it against the
#: calibration's chip (:class:`RangeCore`).
CHIP_RECHECK = 20
#: the LSB tracking (:func:`lsb_tracking`, 0.3-1 CPU-s a measurement of 128 TDCs: a
#: density test per TDC) runs on a chip-checked measurement at most once per this many
#: seconds, the first this long after the stage's start: a slow drift needs no more, and
#: neither the first measurement nor the stage's rate pays for it (issue 38.9)
LSB_TRACK_EVERY_S = 60.0
LSB_TRACK_AFTER_S = 10.0

UNDECIDED = ("chip not checked: too few background counts to tell the calibration's "
             "chip from another")


def chip_checked(calibration: Calibration, state: HistogramState, est: Estimate,
                 window_s: float):
    """:func:`check_capture_chip` and its flags: every row ``CHIP_MISMATCH`` where the
    capture is another chip's, else the rows of a TDC that alone disagrees
    ``TDC_MISMATCH``. Returns the flagged estimate, the verdict for the metadata or a
    message header, and the check."""
    chk = check_capture_chip(calibration, state, est, window_s)
    px = est.pixel if est.pixel is not None else np.arange(state.n_tdc)
    verdict = {"verdict": chk.verdict, "summary": chk.summary()}
    if chk.verdict == "mismatch":
        est = _flag_rows(est, np.ones(px.size, bool), CHIP_MISMATCH)
        bad = chk.disagree
    else:
        bad = chk.disagree_at(TDC_FLAG_SIGMAS)
        est = _flag_rows(est, bad[px], TDC_MISMATCH)
    verdict["disagree"] = (np.flatnonzero(bad) + state.tdc_offset).tolist()
    return est, verdict, chk


def range_capture(capture: str | Path, calibration: Calibration, out: str | Path,
                  estimator: str = "ml", sigma_s: float | None = None,
                  p_fa: float = 1e-3, max_returns: int = 1, force: bool = False,
                  check_chip: bool = True, spatial=None) -> tuple[pa.Table, str]:
    """Range a whole capture, up to ``max_returns`` returns a pixel (``tcspc range``: 3 by
    default; 1 here, a row a TDC, for the flows that aggregate per TDC); returns the
    ranges table and the note of :func:`range_state`. ``capture``: a path, or an open
    :class:`Capture` (one read to its last whole cycle is flagged ``tcspc.truncated``).

    With ``check_chip``, the capture's code-density pattern is checked against the
    calibration's (:func:`check_capture_chip`, issue 33.4) before anything is written:
    another chip's calibration raises CalibrationError naming the TDCs that disagree,
    unless ``force``, which ranges it with every row flagged ``CHIP_MISMATCH``; a TDC
    that alone disagrees in a capture that matches is flagged ``TDC_MISMATCH``; a capture
    too dim to tell is ranged, with a note. The verdict is in the metadata
    (``tcspc.chip_check``). ``spatial``, a Geometry: ranged with the neighbours as its
    image (:func:`pipeline.offline.spatial.range_state_spatial`; ``estimator`` unused)."""
    cap = capture if isinstance(capture, Capture) else Capture(capture)
    if calibration.n_tdc != cap.meta.n_tdc:
        raise CalibrationError(f"{calibration.path}: calibrates {calibration.n_tdc} TDCs, "
                               f"{cap.bin_path} has {cap.meta.n_tdc}")
    acc = HistogramAccumulator(cap.meta.n_tdc, calibration.bounds)
    for first, words in cap.iter_chunks():
        acc.update(words, first)
    state = acc.snapshot()
    window_s = cap.meta.window_ns * 1e-9
    if spatial is not None:
        from pipeline.offline.spatial import range_state_spatial

        est, d, s, note = range_state_spatial(state, calibration, window_s,
                                              cap.meta.t_laser_win_ns * 1e-9, spatial,
                                              sigma_s, p_fa, max_returns)
    else:
        est, d, s, note = range_state(state, calibration, window_s,
                                      cap.meta.t_laser_win_ns * 1e-9, estimator, sigma_s,
                                      p_fa, max_returns=max_returns)
    verdict = {}
    if check_chip:
        est, verdict, chk = chip_checked(calibration, state, est, window_s)
        if chk.verdict == "mismatch" and not force:
            raise CalibrationError(mismatch_message(cap.bin_path, calibration, chk))
        if chk.verdict == "undecided":
            note = "; ".join(n for n in (note, UNDECIDED + f" ({chk.summary()})") if n)
    table = ranges_table(cap.name, est, d, s)
    import json

    table = table.replace_schema_metadata({**table.schema.metadata,
                                           **({b"tcspc.chip_check": json.dumps(
                                               verdict).encode()} if verdict else {}),
                                           b"tcspc.calibration": calibration.path.encode(),
                                           b"tcspc.calibration_id": str(calibration.meta.get(
                                               "calibration_id", "")).encode(),
                                           b"tcspc.capture": str(cap.bin_path).encode(),
                                           **({b"tcspc.truncated": b"True"}
                                              if cap.truncated else {})})
    with atomic_path(out) as tmp:
        pq.write_table(table, tmp)
    return table, note


def lsb_tracking(calibration: Calibration, state: HistogramState, window_s: float,
                 min_hits: int = 1000) -> dict | None:
    """The online LSB tracking of one measurement (:func:`stages.calibration.track_lsb`:
    each TDC's uniform background taken as a density test, its returns masked) against the
    calibration's LSB at the measurement's light, for the campaign's verdict (issue 39.3):
    ``median_ps`` of the trusted TDCs' drift, its standard error ``se_ps`` (1.2533 sd /
    sqrt(n), the median's), ``n`` TDCs, ``light``; None where no TDC had ``min_hits``."""
    rows = slice(state.tdc_offset, state.tdc_offset + state.n_tdc)
    light = cal.light_level(state.hits, state.cycles)
    expected, _ = calibration.lsb_s(light)
    tr = cal.track_lsb(state.hits, state.cycles, window_s, np.asarray(expected)[rows],
                       min_hits=min_hits)
    d = tr.drift_ps[np.isfinite(tr.drift_ps)]
    if d.size == 0:
        return None
    se = 1.2533 * float(np.std(d, ddof=1)) / np.sqrt(d.size) if d.size > 1 else float("inf")
    return {"median_ps": float(np.median(d)), "se_ps": se, "n": int(d.size),
            "light": float(light)}


class RangeCore:
    """The range stage: each histograms message (a measurement, or a worker's TDC range of
    one) in, its ranges out, the histograms passed on beside them for the sink. Stateless
    (a measurement is ranged on its own, so a fan-out needs no join), but for ``spatial``:
    there a measurement is ranged as one image, so the parts of a fan-out by TDC range
    are joined first (:class:`pipeline.offline.spatial.FrameGather`, ``hold``)."""

    in_spec = HISTOGRAMS
    out_spec = RANGES

    def __init__(self, calibration: Calibration, estimator: str = "ml",
                 window_ns: float = 80.0, step_id: str = "range",
                 forward_histograms: bool = True, max_returns: int = MAX_RETURNS,
                 check_chip: bool = True, warn=None, spatial=None,
                 track_lsb_every_s: float = LSB_TRACK_EVERY_S,
                 track_lsb_after_s: float = LSB_TRACK_AFTER_S, clock=time.monotonic,
                 hold: int | None = None):
        if not calibration.has_delay:  # fail at start, not on the first message
            raise CalibrationError(f"{calibration.path}: no delay (run `tcspc calibrate "
                                   "delay` on a zero-distance capture first)")
        self.calibration, self.estimator, self.window_ns = calibration, estimator, window_ns
        self.max_returns = max_returns
        self.step_id, self.forward = step_id, forward_histograms
        self.ranged = 0
        self.notes: dict[str, int] = {}  #: what the calibration said, and how often
        #: each measurement's code-density pattern against the calibration's chip
        #: (:func:`chip_checked`): verdict -> measurements; another chip's rows are flagged
        #: ``CHIP_MISMATCH`` (a stream is never refused mid-run: its data are kept) and
        #: ``warn`` is told once
        self.check_chip, self.warn = check_chip, warn
        self.chip_checks: dict[str, int] = {}
        self._unchecked = 0  #: measurements since the last check (after a match)
        self.track_every_s, self.clock = track_lsb_every_s, clock
        #: when the LSB may next be tracked (LSB_TRACK_EVERY_S)
        self._track_at = clock() + track_lsb_after_s
        #: a Geometry: each measurement ranged with its neighbours as that geometry's
        #: image (:func:`pipeline.offline.spatial.range_state_spatial`, issue 35), its
        #: frame gathered from the histogram workers' parts (:class:`FrameGather`, at
        #: most ``hold`` measurements held)
        self.spatial = spatial
        self.gather = None
        if spatial is not None:
            from pipeline.offline.spatial import FrameGather

            self.gather = FrameGather(n_tdc=calibration.n_tdc, **(
                {} if hold is None else {"hold": hold}))
        if spatial is not None and not np.any(spatial.index_of(np.arange(calibration.n_tdc))
                                              >= 0):
            raise CalibrationError(f"geometry {spatial.name}: no pixel for any of the "
                                   f"{calibration.n_tdc} TDCs of {calibration.path}")
        if spatial is None:  # (the spatial estimator is numpy only: nothing to load)
            self._warm_up()

    def _warm_up(self) -> None:
        """Range a made-up measurement of the calibration's first TDCs once, its result
        dropped: the compiled kernels load (numba's cache, ~0.25 CPU-seconds) while the
        stage starts, not on its first measurement (a 3-return fit of 128 TDCs costs a
        tenth of that once loaded)."""
        n = min(2, self.calibration.n_tdc)
        code = np.arange(N_CODES)
        # a flat background of ~2 counts a code and a return of ~900 counts, 3 codes wide,
        # a third of the way into the codes: the path of a measurement with a target
        hits = np.rint(2.0 + 120.0 * np.exp(-0.5 * ((code - N_CODES / 3) / 3.0) ** 2))
        hits = np.repeat(hits[None, :].astype(np.uint64), n, axis=0)
        classes = np.zeros((N_CLASSES, n), np.uint64)
        classes[HIT] = hits.sum(axis=1)
        classes[NO_HIT] = 20_000 - classes[HIT]
        state = HistogramState(hits, classes, int(classes.sum()))
        range_state(state, self.calibration, self.window_ns * 1e-9, self.window_ns * 0.25e-9,
                    self.estimator, max_returns=self.max_returns)

    def process(self, header: dict, batch: pa.RecordBatch) -> list:
        forward = [(header, batch)] if self.forward else []
        if self.gather is not None:  # spatial: ranged once the measurement's frame is whole
            frames = self.gather.add(header, batch)
            return forward + [m for f in frames for m in self._range_frame(f)]
        state = HistogramState.from_table(pa.Table.from_batches([batch]))
        head, table = self._range(header, state)
        return forward + [(head, b) for b in table.to_batches()]

    def _range(self, header: dict, state: HistogramState,
               absent: np.ndarray | None = None) -> tuple[dict, pa.Table]:
        """The ranges header and table of one measurement's histograms (``absent``: the
        TDCs of a spatial frame whose part did not arrive)."""
        window_s = float(header.get("window_ns", self.window_ns)) * 1e-9
        gate_s = float(header["t_laser_win_ns"]) * 1e-9
        if self.spatial is not None:
            from pipeline.offline.spatial import range_state_spatial

            est, d, s, note = range_state_spatial(state, self.calibration, window_s, gate_s,
                                                  self.spatial,
                                                  max_returns=min(self.max_returns, 4),
                                                  absent=absent)
        else:
            est, d, s, note = range_state(state, self.calibration, window_s, gate_s,
                                          self.estimator, max_returns=self.max_returns)
        if note:  # light outside the LSB fit: counted, and in the ranges' header
            self.notes[note] = self.notes.get(note, 0) + 1
        name = str(header.get("measurement", header["run"]))
        chip = None
        # a chip does not change within a run: the first measurement and every
        # CHIP_RECHECK-th are checked (the check costs about as much as ranging), every one
        # once a mismatch was seen; not a frame with a part missing (its filled rows)
        self._unchecked += 1
        if self.check_chip and absent is None and (
                not self.chip_checks or self.chip_checks.get("mismatch", 0) > 0
                or self._unchecked >= CHIP_RECHECK):
            self._unchecked = 0
            est, _, chk = chip_checked(self.calibration, state, est, window_s)
            chip = chk.verdict
            if chip == "mismatch" and not self.chip_checks.get(chip) and self.warn:
                self.warn(mismatch_message(f"measurement {name}", self.calibration, chk,
                                           state.tdc_offset).replace(
                    "--force ranges it anyway", "ranged anyway"))
            self.chip_checks[chip] = self.chip_checks.get(chip, 0) + 1
        drift = None
        if chip is not None and self.clock() >= self._track_at:
            self._track_at = self.clock() + self.track_every_s
            drift = lsb_tracking(self.calibration, state, window_s)
        if header.get("partial"):  # the stream ended inside it: its rows say so
            cyc = header.get("cycles") or [0, 0]
            est = _flag_rows(est, np.ones(np.size(est.t_s), bool),
                             f"{PARTIAL} (cycles {cyc[0]}..{cyc[1]})")
        if absent is not None:  # a frame without some TDCs: its other rows say which
            from pipeline.offline.spatial import _runs

            gone = ", ".join(f"{a + state.tdc_offset}..{b + state.tdc_offset - 1}"
                             for a, b in _runs(absent))
            est = _flag_rows(est, ~absent[est.pixel], f"{INCOMPLETE_FRAME} (TDCs {gone})")
        table = ranges_table(name, est, d, s, state.tdc_offset)
        head = {**header, "schema": RANGES.name, "version": RANGES.version,
                "step": self.step_id,
                "detected": int(np.sum(est.detected & (est.return_index == 0))),
                **({"calibration_note": note} if note else {}),
                **({"chip_check": chip} if chip else {}),
                **({"lsb_drift": drift} if drift else {}),
                **({"calibration_id": self.calibration.meta["calibration_id"]}
                   if self.calibration.meta.get("calibration_id") else {})}
        self.ranged += 1
        return head, table

    def _range_frame(self, frame) -> list:
        """A gathered frame ranged whole, its ranges sent as one message per worker's part
        (the file each part's histograms have beside them: ``part-K-tFIRST``), and one per
        missing part with its TDCs' rows, not detected, flagged; each of a frame with a part
        missing carries ``spatial_missing`` (the missing TDC ranges: the reconciliation
        ranges that measurement again from the journal)."""
        import pyarrow.compute as pc

        head, table = self._range(frame.header, frame.state, frame.absent)
        tdc = table.column("tdc")
        out = []
        for ph, (a, b) in [*frame.parts, *((None, r) for r in frame.missing)]:
            rows = table.filter(pc.and_(pc.greater_equal(tdc, a), pc.less(tdc, b)))
            det = pc.and_(rows.column("detected"), pc.equal(rows.column("return_index"), 0))
            h = {**head, "tdc_range": [a, b], "detected": int(pc.sum(det).as_py() or 0),
                 **({k: ph[k] for k in ("words", "class_counts", "partial", "cycles")
                     if k in ph} if ph is not None else {}),
                 **({"spatial_missing": [list(r) for r in frame.missing]}
                    if frame.missing else {})}
            out += [(h, bt) for bt in rows.to_batches()]
        return out

    def finish(self, header: dict) -> list:
        if self.gather is None:
            return []
        return [m for f in self.gather.flush() for m in self._range_frame(f)]

    @property
    def incomplete_frames(self) -> int:
        """Spatial frames ranged without every worker's part (the stage's metrics)."""
        return 0 if self.gather is None else self.gather.incomplete

    @property
    def held_frames(self) -> int:
        """Spatial frames held while their workers' parts gather (the stage's metrics)."""
        return 0 if self.gather is None else self.gather.held
