"""Calibration, code to time and delay (eqs. 5.3, 5.4): code boundaries, the time scale at a
capture's light (from the LSB fit or measured in situ from the capture's reset peak), the
zero-distance peak's width, the delay and the distance.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from schemas.constants import N_CODES
from stages.calibration.density import DensityResult, beside_dead
from stages.calibration.lsb_light import LsbFit, RowSplines
from stages.calibration.reset_peak import EDGE_MARGIN, RESET_HALF, at_risk_by_code, fit_reset_peak


def histogram_sigma_s(hits: np.ndarray, density: DensityResult, lsb_s=None) -> np.ndarray:
    """Width (sigma) of each TDC's peak: the instrument response at zero distance. The
    background-subtracted counts of +-6 codes around the highest count (away from both
    window edges), at the code centres the density test gives."""
    lsb = density.lsb_s if lsb_s is None else np.asarray(lsb_s)
    centres = (np.arange(N_CODES)[None, :] + np.nan_to_num(density.inl_lsb)
               + 0.5 * (1 + np.nan_to_num(density.dnl_lsb))) * lsb[:, None]
    h = np.asarray(hits, np.float64)
    peak = np.argmax(h[:, 2:-8], axis=1) + 2
    win = np.abs(np.arange(N_CODES)[None, :] - peak[:, None]) <= 6
    w = np.where(win, np.clip(h - np.median(h, axis=1, keepdims=True), 0, None), 0.0)
    tau = (w * centres).sum(1) / np.maximum(w.sum(1), 1e-300)
    var = (w * (centres - tau[:, None]) ** 2).sum(1) / np.maximum(w.sum(1), 1e-300)
    # the centres quantise: remove a bin's uniform variance (LSB^2 / 12)
    return np.sqrt(np.maximum(var - lsb ** 2 / 12, 0.0))


def density_rows(density: DensityResult, rows) -> DensityResult:
    """The results of some TDCs (a worker's range)."""
    import dataclasses

    idx = np.arange(density.n_tdc)[rows]
    return DensityResult(**{f.name: getattr(density, f.name)[rows]
                            for f in dataclasses.fields(DensityResult)
                            if f.name != "reasons" and getattr(density, f.name) is not None},
                         reasons=tuple(density.reasons[i] for i in np.atleast_1d(idx)))


#: Measured codes below the last one whose per-phase mean widths continue the table beyond
#: it (local: the INL bow moves the phase pattern's mean over the window).
CONTINUE_CODES = 64


def _phase_means(w: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """(8,) the mean width of each phase (code mod 8) over codes ``lo..hi-1`` of one TDC's
    widths ``w`` that are finite, live and beside live codes (a dead code's time is in a
    neighbour, which the pattern does not predict); all finite codes where that leaves a
    phase without one, 1.0 where nothing does."""
    k = np.arange(max(int(lo), 0), max(int(hi), 0))
    v = w[k]
    fin = np.isfinite(v)
    near = beside_dead(w)[k]
    out = np.ones(8)
    for p in range(8):
        for sel in (fin & ~near & (k % 8 == p), fin & (k % 8 == p)):
            if sel.any():
                out[p] = float(v[sel].mean())
                break
    return out


def code_bounds(density: DensityResult) -> np.ndarray:
    """(n_tdc, 513) code boundaries in units of the density test's LSB (``k + INL_k``).
    Beyond the last code the tests measured, they continue with the measured phase pattern
    (the mean width of each phase, code mod 8, over the ``CONTINUE_CODES`` codes below it,
    dead codes and their neighbours left out): a dimmer capture's window ends there. One
    unit a code instead (before issue 33) lost each such code's DNL: 13-14 ps of delay on a
    chip of the zoo."""
    k = np.arange(N_CODES + 1, dtype=np.float64)
    inl = np.asarray(density.inl_lsb, np.float64)
    inl = np.concatenate([inl, inl[:, -1:]], axis=1)
    last = np.where(np.isfinite(inl), k[None, :], -1).max(axis=1).astype(np.int64)
    fill = np.take_along_axis(inl, np.maximum(last, 0)[:, None], axis=1)
    out = np.where(np.isfinite(inl), inl, np.where(np.isfinite(fill), fill, 0.0))
    widths = np.asarray(density.width_lsb, np.float64)
    for t in np.flatnonzero((last > CONTINUE_CODES) & (last < N_CODES)):  # per TDC, once
        mean = _phase_means(widths[t], last[t] - CONTINUE_CODES, last[t])
        beyond = np.arange(last[t], N_CODES)
        out[t, last[t] + 1:] = out[t, last[t]] + np.cumsum(mean[beyond % 8] - 1.0)
    return k[None, :] + out


def continue_table(table: DensityResult, tests: list) -> DensityResult:
    """``table`` (the density test kept, filled from ``tests``, the other tests' results)
    carried on over the codes no test measured below the highest x_T of ``tests``: the
    3-4 codes under the dimmest test's reset peak (above the last it measured,
    :data:`.density.OWN_CLEAR_LSB`), where a capture between the two dimmest levels reads
    its x_T and the dimmest test's scale point ``T / B(x_T)`` is read.

    Each such code takes the table's local phase mean (what :func:`code_bounds` continues
    with), except where the dimmest test found a dead code (no count between lit codes):
    that one at zero width, and its neighbours with what the test put there beyond its own
    phase mean (the dead code's time, in the neighbour its reset peak chose,
    :func:`.density._dead_widths`), brought to the table's units. The pattern alone gave a
    dead code there a whole width: the axis between the levels 41-88 ps off on zoo chip 5
    (8 TDCs) where the table's sigma said 5-10 ps (benchmarks/calibration_between_levels.py).
    The code after the dimmest test's x_T takes the pattern too; so does the table's last
    measured code, as :func:`code_bounds` always gave it (measured by the dimmest test
    alone, 2.5-3.5 LSB below its reset peak: 0.1-0.15 LSB sd, the pattern's guess 0.05-0.07;
    kept measured, the axis between the levels erred by 42 ps RMS against 36 on zoo chips
    3-7 at 16 TDCs). Their variance stays the table's (:func:`.uncertainty.table_var`:
    the pattern's where no test measured them, the measurement's at the last code)."""
    tests = [r for r in tests if r is not None]
    if not tests:
        return table
    w = np.array(table.width_lsb, np.float64, copy=True)
    inl = np.array(table.inl_lsb, np.float64, copy=True)
    x_all = np.column_stack([np.where(np.asarray(r.ok, bool), r.x_t, np.nan) for r in tests])
    k = np.arange(N_CODES)
    changed = False
    for t in np.flatnonzero(np.asarray(table.ok, bool)):  # per TDC, once per calibration
        fin = np.flatnonzero(np.isfinite(w[t]) & np.isfinite(inl[t]))
        if fin.size <= CONTINUE_CODES or not np.isfinite(x_all[t]).any():
            continue
        last = int(fin[-1])
        src = tests[int(np.nanargmax(x_all[t]))]
        top = int(np.floor(src.x_t[t]))  # the code holding the dimmest test's x_T
        ws = np.asarray(src.width_lsb[t], np.float64)
        if not last < top < N_CODES - 1 or not np.all(np.isfinite(ws[last:top + 1])):
            continue
        interior = top - EDGE_MARGIN  # the codes of the test's own uniform light
        both = (k < interior) & np.isfinite(w[t]) & np.isfinite(ws) & (w[t] > 0) & (ws > 0)
        if both.sum() < CONTINUE_CODES:
            continue
        ratio = w[t, both].sum() / ws[both].sum()  # its units to the table's
        gap = np.arange(last, top + 2)
        pm = _phase_means(w[t], last - CONTINUE_CODES, last)[gap % 8]
        own = _phase_means(ws, 0, interior)[gap % 8]
        wg = np.append(ws[last:top + 1], np.nan)  # (no width above its x_T)
        # a dead code, its neighbours, and a code holding a dead code's time (wider than
        # its phase mean by about another: its dead neighbour may lie above x_T, where the
        # test keeps no width); the test's other widths there are its phase means, or
        # measured within OWN_CLEAR_LSB of its reset peak (not trusted: taken, the widths
        # there were off by z RMS 1.22 on zoo chips 3-7, 0.98 without)
        dead = np.isfinite(wg) & (wg <= 0)
        near = beside_dead(wg)
        with np.errstate(invalid="ignore"):
            near |= wg - own > 0.5 * float(np.mean(own))
        near &= np.isfinite(wg)
        new = np.where(dead, 0.0, np.where(near, np.maximum(pm + ratio * (wg - own), 0.0), pm))
        w[t, gap] = new
        inl[t, gap[1:]] = inl[t, last] + np.cumsum(new[:-1] - 1.0)
        changed = True
    if not changed:
        return table
    return replace(table, width_lsb=w, dnl_lsb=w - 1.0, inl_lsb=inl)


def _bound_at(bounds: np.ndarray, x) -> np.ndarray:
    """Boundaries read at fractional codes ``x`` (n_tdc,), linearly within a code."""
    x = np.asarray(x, np.float64)
    good = np.isfinite(x)  # a dead or dark TDC has no LSB: NaN stays NaN
    x = np.clip(np.where(good, x, 0.0), 0, N_CODES - 1e-9)
    k = np.floor(x).astype(np.int64)[:, None]
    b0 = np.take_along_axis(bounds, k, axis=1)[:, 0]
    b1 = np.take_along_axis(bounds, k + 1, axis=1)[:, 0]
    return np.where(good, b0 + (x - k[:, 0]) * (b1 - b0), np.nan)


def scale_at_light(density: DensityResult, lsb_s, window_s: float,
                   fit: LsbFit | None = None, light: float | None = None,
                   splines: ScaleSplines | None = None, bounds=None) -> np.ndarray:
    """Seconds per unit of :func:`code_bounds` at a light whose LSB (the window over the
    code span, eq. 5.1's polynomial) is ``lsb_s``: tau = T falls at code ``x_T = T / lsb``,
    which is ``B(x_T)`` units of the density test's boundaries, so the scale is
    ``T / B(x_T)``. (``B(k) * lsb`` instead is off by ``tau INL(x_T) / x_T``: the density
    test's INL is zero at its own x_T only; ~60 ps at mid-window for 0.5 LSB.)

    With ``fit`` and ``light`` inside its levels, the scale itself is interpolated: each
    density test's measured LSB gives its scale ``T / B(T / LSB_i)``, and a cubic spline
    in sqrt(n) through those reads it at ``light``. The scale follows the VCOs' speed,
    smooth in the light; the window LSB does not: as x_T moves across codes it carries
    the INL there (``LSB = scale B(x_T) / x_T``), a ripple of ~0.1 ps (0.3 LSB of INL
    over 395 codes) that no smooth curve through the tests' LSBs follows, and 0.1 ps is
    ~20 ps of range at mid-window. ``splines`` (:func:`scale_splines`) and ``bounds``
    (:func:`code_bounds`): the same, built once for the calibration by the caller."""
    ok = np.asarray(density.ok, bool)
    if _interpolates(fit, light):
        splines = scale_splines(density, fit, window_s) if splines is None else splines
        return np.where(ok, splines.in_sqrt(float(light)), np.nan)
    x_t = window_s / np.asarray(lsb_s, np.float64)
    scale = window_s / _bound_at(code_bounds(density) if bounds is None else bounds, x_t)
    return np.where(ok, scale, np.nan)  # a dead TDC has no axis



def _interpolates(fit: LsbFit | None, light: float | None) -> bool:
    """Whether :func:`scale_at_light` interpolates the tests' scales at ``light``."""
    levels = None if fit is None or fit.levels is None else np.asarray(fit.levels, np.float64)
    return bool(levels is not None and light is not None and levels.size >= 3
                and fit.in_range(light) and np.unique(levels).size == levels.size)


def scale_points(density: DensityResult, fit: LsbFit, window_s: float):
    """The density tests' own scales: ``(levels, scales)``, the levels ascending and
    ``scales`` (n_tdc, n_levels) ``T / B(T / LSB_i)`` in seconds per unit of
    :func:`code_bounds` (NaN where a test flagged the TDC)."""
    bounds = code_bounds(density)
    levels = np.asarray(fit.levels, np.float64)
    order = np.argsort(levels)
    pts = fit.points_ps()[:, order] * 1e-12
    return levels[order], np.column_stack([window_s / _bound_at(bounds, window_s / pts[:, j])
                                           for j in range(pts.shape[1])])


@dataclass(frozen=True)
class ScaleSplines:
    """The density tests' scales (:func:`scale_points`) as splines in sqrt(n) and in n,
    built once for a calibration and a window (:func:`scale_splines`)."""

    levels: np.ndarray
    in_sqrt: RowSplines
    in_n: RowSplines


def _identity(v):
    return v


def scale_splines(density: DensityResult, fit: LsbFit, window_s: float) -> ScaleSplines:
    """What :func:`scale_at_light` and :func:`scale_spread` read at a light, built once."""
    levels, s_pts = scale_points(density, fit, window_s)
    return ScaleSplines(levels, RowSplines(levels, s_pts), RowSplines(levels, s_pts, _identity))


def scale_refs(density: DensityResult, fit: LsbFit | None, window_s: float, light: float,
               splines: ScaleSplines | None = None):
    """Where the scale :func:`scale_at_light` interpolates at ``light`` takes its error
    from (issue 33.3): ``(codes, weights)``, each (n_tdc, n_levels), the density tests'
    x_T = T / LSB_i on the table (their points ``T / B(x_T,i)``) and what each weighs in
    the scale read, ``w_i s_i / s`` (``w_i`` the spline's weights in sqrt(n), ``s_i`` the
    points, ``s`` the scale read; they sum to ~1). The scale's relative error is then
    ``-sum_i weights_i dB(x_T,i) / B(x_T,i)``: at a light between two tests the table's
    error at *their* x_T, not at the light's own (the codes between are measured by the
    dimmer tests only). A third array, (n_tdc, n_levels), is the variance (code^2) of
    those x_T themselves (each test's point, ``LsbFit.sigma_ps``: its reset peak fit and
    its counted light; 0 where the fit does not say). None where the scale is not
    interpolated at ``light`` (the polynomial's or the capture's x_T is then the one
    reference)."""
    if not _interpolates(fit, light):
        return None
    splines = scale_splines(density, fit, window_s) if splines is None else splines
    levels = np.asarray(fit.levels, np.float64)
    order = np.argsort(levels)
    points = fit.points_ps()[:, order]
    codes = window_s / (points * 1e-12)
    _, pts = scale_points(density, fit, window_s)
    w = splines.in_sqrt.weights(float(light))
    s = splines.in_sqrt(float(light))
    with np.errstate(divide="ignore", invalid="ignore"):
        weights = np.nan_to_num(w * pts, nan=0.0) / s[:, None]
        codes_var = (np.zeros_like(codes) if fit.sigma_ps is None else
                     np.nan_to_num((codes * np.asarray(fit.sigma_ps, np.float64)[:, order]
                                    / points) ** 2))
    return codes, np.where(np.isfinite(s)[:, None], weights, np.nan), codes_var


#: When the spread of the scale (:func:`scale_spread`, as ps at a return's tau) flags a
#: delay or a range: over this many of its statistical sigmas (INL x LSB, and for the
#: delay the peak's fit) plus the floor; half the chip sweep's tolerance (4 sigmas + 20
#: ps). Measured there: <= 27 ps on 35 healthy chips' zero-distance captures (sigma ~50
#: ps), 210-1000 ps where a fast-saturating LSB put the delay out of its tolerance.
LSB_SPREAD_SIGMAS, LSB_SPREAD_FLOOR_PS = 2.0, 20.0

def light_level(hits, cycles) -> float:
    """A measurement's light, detections per pixel per cycle (eq. 5.1's n): all its hits
    over its TDCs and its cycles."""
    h = np.asarray(hits)
    return float(h.sum() / (h.shape[0] * max(float(np.max(cycles)), 1.0)))


def scale_unresolved(spread, tau_s, density: DensityResult, sigma_s) -> np.ndarray:
    """Where the scale's spread (:func:`scale_spread`) at a return's ``tau_s`` is more
    than its timing allows: ``LSB_SPREAD_SIGMAS`` of its statistics (INL x LSB and the
    fit's ``sigma_s``) plus ``LSB_SPREAD_FLOOR_PS``. One rule for ``calibrate delay``'s
    flag and ``range``'s note."""
    allowed_ps = (LSB_SPREAD_SIGMAS * np.hypot(density.inl_error_lsb * density.lsb_s,
                                               np.asarray(sigma_s, np.float64)) * 1e12
                  + LSB_SPREAD_FLOOR_PS)
    with np.errstate(invalid="ignore"):
        return np.asarray(spread * np.asarray(tau_s, np.float64) * 1e12 > allowed_ps, bool)


def scale_spread(density: DensityResult, fit: LsbFit | None, window_s: float,
                 light: float, splines: ScaleSplines | None = None
                 ) -> tuple[np.ndarray, tuple[float, float]]:
    """How well the density tests' levels resolve the scale at ``light``: per TDC the
    relative difference between the scale :func:`scale_at_light` reads (a cubic spline in
    sqrt(n) through the tests' scales) and a cubic spline in n through the same points,
    and the two levels ``light`` lies between. NaN (and ``(nan, nan)``) where the scale
    is not interpolated at ``light`` (outside the levels: the caller's note already says).

    Both curves pass through every measured point; they part where the LSB bends
    between two levels faster than the points show, and there neither is to be trusted
    (issue 15: with four levels at 0.02-0.75 detections a cycle and an LSB that
    saturates by 0.15, they differ by 0.5-0.9 % of the scale at 0.24, where the sqrt(n)
    spline is off by 0.25-0.37 %: 170-250 ps of delay at tau = 68 ns). On chips the
    levels resolve (the chip zoo's n_sat >= 0.5) they differ by <= 0.04 % at the
    sweep's captures. The spread says where a curve is unresolved, not how far off
    it is (0.4-0.5 of the spread where the LSB saturates fast, up to ~3x a tiny spread
    elsewhere: the INL's noise in the points), so it flags, it does not correct.
    ``splines``: :func:`scale_splines` of the same, built once by the caller.
    """
    n_tdc = density.n_tdc
    if not _interpolates(fit, light):
        return np.full(n_tdc, np.nan), (float("nan"), float("nan"))
    splines = scale_splines(density, fit, window_s) if splines is None else splines
    levels = splines.levels
    in_sqrt = splines.in_sqrt(float(light))
    in_n = splines.in_n(float(light))
    i = int(np.clip(np.searchsorted(levels, light, side="right") - 1, 0, levels.size - 2))
    return np.abs(in_n / in_sqrt - 1), (float(levels[i]), float(levels[i + 1]))


#: Codes below where the light ends searched for the reset peak.
RESET_SEARCH = 4
#: Codes a return must keep from the reset peak for the in-situ fit to be trusted.
RESET_CLEARANCE = 12


def light_end(hits: np.ndarray, min_per_code: float = 1.0):
    """Where each TDC's uniform light ends: ``(top, step)``, ``top`` one past the last
    populated code, ``step`` True where light lies below it (a median of ``min_per_code``
    or more counts over the 30 codes 10-40 below). Nothing is detected at tau > T, so with
    ambient light the reset peak (tau = T) sits at the top; without it there is no step,
    and the last populated code is a return's tail."""
    h = np.asarray(hits)
    n = h.shape[1]
    populated = h.any(axis=1)
    top = np.where(populated, n - np.argmax(h[:, ::-1] > 0, axis=1), 0)
    lo, hi = np.maximum(top - 40, 0), np.maximum(top - 10, 0)
    level = np.zeros(h.shape[0])
    full = hi - lo == 30  # the 30 codes all on the axis: one median over those rows
    if full.any():
        codes = lo[full, None] + np.arange(30)
        level[full] = np.median(np.take_along_axis(h[full], codes, axis=1), axis=1)
    for i in np.flatnonzero(~full & (hi > lo)):  # light ending in the first 40 codes
        level[i] = np.median(h[i, lo[i]:hi[i]])
    return top, populated & (level >= min_per_code)


def scale_in_situ(hits: np.ndarray, cycles: np.ndarray, density: DensityResult,
                  window_s: float, returns: np.ndarray | None = None,
                  min_counts: float = 100.0, beyond: np.ndarray | None = None):
    """Seconds per unit of :func:`code_bounds` measured on a capture itself: its reset
    peak (tau = T) fitted over the density test's boundaries (:func:`fit_reset_peak`).

    Exact at the capture's own light, without the LSB polynomial; valid where the fitted
    codes are ones the density test measured (its own reset peak's codes are filled from
    the phase means): the capture brighter than the density test by ~15 codes of x_T.

    The reset peak is looked for where the capture's uniform light ends
    (:func:`light_end`: nothing is detected at tau > T), never simply as the highest
    count: a return near the window's beginning can be higher than the reset peak, and a
    dim capture's reset peak lies beyond the density test's. A TDC is declined, with the
    reason, where the capture has no ambient-light step (no reset peak to fit), where a
    return (``returns``: its code, NaN for none) lies within ``RESET_CLEARANCE`` codes of
    the reset peak (the fit would take the return for part of it), where the peak has
    fewer than ``min_counts`` counts, or where the density test did not measure those
    codes. ``beyond`` (a mask of TDCs): there any code the campaign measured will do
    (the table continued over the dimmer tests' codes, ``density_test(combine=True)``),
    so a capture between the tests' levels has its reset peak on measured codes too.

    Returns ``(scale, ok, reason)``; ``reason`` is "" where ``ok``.
    """
    h = np.asarray(hits, np.float64)
    n = h.shape[0]
    bounds = code_bounds(density)
    at_risk = at_risk_by_code(h, cycles)
    x_den = np.nan_to_num(density.x_t, nan=0.0)
    measured_to = np.floor(x_den) - EDGE_MARGIN - 1  # the density test's last measured code
    if beyond is not None:
        fin = np.isfinite(np.asarray(density.width_lsb, np.float64))
        last = np.where(fin.any(axis=1), N_CODES - 1 - np.argmax(fin[:, ::-1], axis=1), 0)
        measured_to = np.where(np.asarray(beyond, bool), np.maximum(last, measured_to),
                               measured_to)
    end, step = light_end(h)
    k = np.arange(N_CODES)[None, :]
    zone = (k >= end[:, None] - 1 - RESET_SEARCH) & (k < end[:, None])
    top = np.argmax(np.where(zone, h, -1), axis=1)
    # the uniform light per unit just below it (median of Coates' density: a target there
    # does not move it)
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = -np.log1p(-np.clip(h / np.maximum(at_risk, 1.0), 0, 1 - 1e-12))
        per_unit = lam / np.diff(bounds, axis=1)
    band = (k >= top[:, None] - 60) & (k <= top[:, None] - 12)
    has_band = np.isfinite(np.where(band, per_unit, np.nan)).any(axis=1)
    u = np.nanmedian(np.where(band | ~has_band[:, None], per_unit, np.nan), axis=1)
    u = np.where(has_band & np.isfinite(u), u, 0.0)
    P, _, A = fit_reset_peak(h, at_risk, bounds, top, u)
    ret = np.full(n, np.nan) if returns is None else np.asarray(returns, np.float64)
    reason = np.full(n, "", dtype=object)
    checks = [  # the last that applies is the one given
        (top + RESET_HALF >= measured_to, "reset peak on codes the density test did not "
                                          "measure (capture not brighter than it)"),
        (np.abs(ret - top) <= RESET_CLEARANCE,
         f"a return within {RESET_CLEARANCE} codes of the reset peak"),
        (~(A >= min_counts), f"reset peak under {min_counts:g} counts"),
        (~np.isfinite(P), "reset peak fit failed"),
        (~step, "no ambient-light step (no reset peak to fit)"),
        (~np.asarray(density.ok, bool), "flagged by the density test"),
    ]
    for bad, why in checks:
        reason[bad] = why
    ok = reason == ""
    return np.where(ok, window_s / np.where(ok, P, 1.0), np.nan), ok, reason


def delay_s(t_laser_win_s: float, tau_peak_s) -> np.ndarray:
    """eq. 5.3: T_delay = T_Laser-Win - TDC_out * LSB (the zero-distance peak's tau)."""
    return t_laser_win_s - np.asarray(tau_peak_s, np.float64)


def distance_m(t_laser_win_s: float, delay, tau_s) -> np.ndarray:
    """eq. 5.4: distance = c/2 (T_Laser-Win - T_delay - TDC_out * LSB)."""
    from scipy.constants import c

    return c / 2 * (t_laser_win_s - np.asarray(delay) - np.asarray(tau_s))
