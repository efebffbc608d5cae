"""Calibration, its own uncertainty (issue 33.3): how far the time axis a calibration gives
can be off from its counts alone, stored with it and added to every range's sigma.

The axis at a light is ``tau(x) = T B(x) / B(x_ref)`` (:func:`.timescale.scale_at_light`:
the code boundaries ``B`` scaled so that tau = T falls at ``x_ref``, the light's x_T).
Every code width ``w_j`` of the table is measured with a variance ``v_j``: the binomial
count of Coates' estimate (:func:`.density.width_variance`), combined over the density
tests by inverse variance as the widths are. The widths are independent, so a time's error
is linear in theirs: ``dtau(x) = scale (dB(x) - (x / x_ref) dB(x_ref))`` with
``dB(x) = sum over j < x of dw_j``, and its variance is ``sum_j a_j^2 v_j`` with
``a_j = scale ([j < x] - (x / x_ref) [j < x_ref])`` (``[j < x]`` the share of code j below
x). Where the scale at a light is interpolated between the density tests' points (a
spline through ``T / B(x_T,i)``, :func:`.timescale.scale_refs`), its error is the table's
at *their* x_T, weighted by the spline: ``(x / x_ref) [j < x_ref]`` becomes ``sum_i
weights_i (x / x_T,i) [j < x_T,i]``; between two tests the codes from one x_T to the
other are measured by the dimmer tests only, and their error is no longer left out
(issue 33.3's gap on re-calibrated chips). A range is the difference of two such
times, its return's at the range's light and the zero capture's return at the zero's
light (the delay, eq. 5.3): the codes both share cancel, so the two are taken together
(:func:`range_sigma_s`), not in quadrature.

Codes no test measured (the table continued past its last measured code with the phase
pattern, :func:`.timescale.code_bounds`, and under the dimmest test's reset peak,
:func:`.timescale.continue_table`) have the variance of the random DNL about the pattern
and of the pattern's own error (:func:`pattern_var`): what the pattern cannot know.

The interpolated scale's points have errors of their own besides the table's: each test's
x_T, its reset peak fitted over its own widths, is off by the fit's counts and by the
widths under the peak (:func:`.density.x_t_variance`), and its light is its counted
STARTs while the LSB it measured is the expected light's (``LsbFit.sigma_ps``,
:func:`.lsb_light.point_sigma_ps`). They enter through :func:`point_coefficients`
(``scale_refs``' third array), independent of the widths' counting.
"""

from __future__ import annotations

import numpy as np

from schemas.constants import N_CODES
from stages.calibration.density import beside_dead

#: Codes a block over which :func:`pattern_var` measures the scatter of the widths about
#: the 8-code phase pattern (as ``timescale.CONTINUE_CODES``: the codes whose phase means
#: continue the table).
PATTERN_CODES = 64


def combined_var(*variances) -> np.ndarray:
    """The variance of the inverse-variance mean of independent estimates (NaN or inf:
    not measured by that one); NaN where none measured."""
    inv = np.zeros(np.shape(variances[0]))
    for v in variances:
        v = np.asarray(v, np.float64)
        with np.errstate(divide="ignore", invalid="ignore"):
            inv += np.where(np.isfinite(v) & (v > 0), 1.0 / v, 0.0)
    with np.errstate(divide="ignore"):
        return np.where(inv > 0, 1.0 / inv, np.nan)


def pattern_var(widths: np.ndarray, width_var: np.ndarray) -> np.ndarray:
    """(n_tdc,) variance of a width the table did not measure (the phase pattern's guess,
    :func:`.timescale.code_bounds`, :func:`.timescale.continue_table`): the random DNL
    about the pattern plus the pattern's own error.

    The random DNL is the scatter of the measured widths (finite ``width_var``; dead codes
    and their neighbours left out) about their phase means (code mod 8) over every block
    of ``PATTERN_CODES`` codes (the bow moves the means), less what their counting
    explains; the pattern's error is that DNL and the counting of the last block's codes
    over the codes a phase has there. Over the last block alone (before), the counting of
    the dim tests that measure it (~0.02 LSB^2 a code) left a random DNL of 0.05-0.07 LSB
    at 0.015-0.03 LSB sd: the codes under the dimmest test's reset peak (dead codes and
    their neighbours aside) were off by z RMS 1.38, 5.5 % beyond 3 sigma (zoo chips 3-7, 8
    and 16 TDCs, 422 codes); now 0.98, none (with :func:`.timescale.continue_table`). A
    dead code among those 64 took it to 0.19-0.24 LSB sd. 0 where fewer than a block
    were measured."""
    w = np.asarray(widths, np.float64)
    v = np.asarray(width_var, np.float64)
    out = np.zeros(w.shape[0])
    k = np.arange(w.shape[1])
    for t in range(w.shape[0]):  # per TDC, once per calibration
        fin = np.flatnonzero(np.isfinite(w[t]) & np.isfinite(v[t]) & ~beside_dead(w[t])
                             & (k >= 8))
        if fin.size < PATTERN_CODES:
            continue
        r2, c = [], []
        for lo in range(int(fin[0]), int(fin[-1]) + 1, PATTERN_CODES):
            sel = fin[(fin >= lo) & (fin < lo + PATTERN_CODES)]
            ph = sel % 8
            n = np.bincount(ph, minlength=8)
            if np.any(n < 2):
                continue
            mean = np.bincount(ph, w[t, sel], minlength=8) / n
            # (w - its phase mean)^2 is short by the mean's share of its own scatter
            r2.append((w[t, sel] - mean[ph]) ** 2 * n[ph] / (n[ph] - 1))
            c.append(v[t, sel])
        if not r2:
            continue
        dnl = max(float(np.mean(np.concatenate(r2)) - np.mean(np.concatenate(c))), 0.0)
        sel = fin[-PATTERN_CODES:]  # the codes whose phase means continue the table
        out[t] = dnl + (dnl + float(np.mean(v[t, sel]))) / (sel.size / 8)
    return out


def table_var(widths: np.ndarray, own_var: np.ndarray, fill_var=None) -> np.ndarray:
    """(n_tdc, 512) variance (LSB^2) of every code width of a calibration's table, all
    finite for a calibrated TDC: the kept test's own (``own_var``, from
    :func:`.density.width_variance`) and the other tests' (``fill_var``, from
    :func:`.density.fill_from`) combined by inverse variance, as the widths are; the codes
    neither measured take :func:`pattern_var`."""
    v = combined_var(own_var, *(() if fill_var is None else (fill_var,)))
    pv = pattern_var(widths, v)
    return np.where(np.isfinite(v), v, pv[:, None])


def codes_at(tau_s, tau_edges_s) -> np.ndarray:
    """(n,) fractional codes of times ``tau_s`` (n,) on each row's axis ``tau_edges_s``
    (n, 513), linear within a code; NaN for a NaN time or axis."""
    e = np.asarray(tau_edges_s, np.float64)
    t = np.asarray(tau_s, np.float64)
    with np.errstate(invalid="ignore"):
        k = np.clip((e <= t[:, None]).sum(axis=1) - 1, 0, e.shape[1] - 2)
    r = np.arange(e.shape[0])
    lo, hi = e[r, k], e[r, k + 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = k + np.clip((t - lo) / (hi - lo), 0.0, 1.0)
    return np.where(np.isfinite(t) & np.isfinite(lo) & np.isfinite(hi), x, np.nan)


def width_var_from_inl_error(density) -> np.ndarray:
    """(n_tdc, 512) a width variance for a calibration that stores none (made before issue
    33, or by one density test): the density test's statistical INL error, ``x_T
    sqrt(1/6) / sqrt(H)`` LSB RMS (:data:`.density.INL_RMS_FACTOR`), gives its hits H, and
    a code's width has the variance of its count, about ``x_T / H`` LSB^2."""
    err = np.asarray(density.inl_error_lsb, np.float64)
    x_t = np.asarray(density.x_t, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        v = 6.0 * err ** 2 / x_t
    return np.broadcast_to(np.where(np.isfinite(v), v, np.nan)[:, None],
                           (v.size, N_CODES)).copy()


def _below(x) -> np.ndarray:
    """(n, 512): the share of each code j below fractional code ``x`` (n,)."""
    j = np.arange(N_CODES)[None, :]
    return np.clip(np.asarray(x, np.float64)[:, None] - j, 0.0, 1.0)


def time_coefficients(x, x_ref, scale, refs=None) -> np.ndarray:
    """(n, 512) ``a_j``: seconds of tau at code ``x`` per unit of error in width j, on an
    axis that puts tau = T at ``x_ref`` with ``scale`` seconds per unit; 0 where any of
    them is NaN. ``refs``: where the scale is interpolated between the density tests
    (:func:`.timescale.scale_refs`, ``(codes, weights)`` each (n, n_levels)), its error
    is the table's at the tests' x_T, weighted, instead of at ``x_ref``:
    ``a_j = scale ([j < x] - sum_i weights_i (x / codes_i) [j < codes_i])``; a row whose
    weights are NaN takes ``x_ref``."""
    x, x_ref, scale = (np.asarray(a, np.float64) for a in (x, x_ref, scale))
    good = np.isfinite(x) & np.isfinite(x_ref) & np.isfinite(scale) & (x_ref > 0)
    x, x_ref, scale = (np.where(good, a, 1.0) for a in (x, x_ref, scale))
    ref = (x / x_ref)[:, None] * _below(x_ref)
    if refs is not None:
        codes, weights = (np.asarray(a, np.float64) for a in refs[:2])
        use = good & np.all(np.isfinite(weights), axis=1) & np.all(
            np.isfinite(codes) | (weights == 0), axis=1)
        interp = np.zeros_like(ref)
        for i in range(codes.shape[1]):  # one term a density test (a few)
            c = np.where(use & (weights[:, i] != 0), codes[:, i], 1.0)
            w = np.where(use, weights[:, i], 0.0)
            interp += (w * x / c)[:, None] * _below(c)
        ref = np.where(use[:, None], interp, ref)
    a = scale[:, None] * (_below(x) - ref)
    return np.where(good[:, None], a, 0.0)


def _sum_var(a, width_var, good, points=0.0) -> np.ndarray:
    v = np.nan_to_num(np.asarray(width_var, np.float64), nan=0.0)
    return np.where(good, np.sqrt(np.sum(a * a * v, axis=1) + points), np.nan)


def point_coefficients(x, scale, refs) -> np.ndarray | None:
    """(n, n_levels) seconds of tau at code ``x`` per code of error in each density test's
    x_T, where the scale is their points' spline (``refs`` from
    :func:`.timescale.scale_refs`): ``tau = s B(x)`` with ``s = sum_i w_i T / B(x_T,i)``,
    so ``d tau / d x_T,i = -tau weights_i B'(x_T,i) / B(x_T,i)``, about ``-scale x
    weights_i / x_T,i`` (about one unit a code); 0 where not interpolated. None without
    ``refs`` or without their x_T's variances."""
    if refs is None or len(refs) < 3:
        return None
    codes, weights = (np.asarray(a, np.float64) for a in refs[:2])
    x, scale = np.asarray(x, np.float64), np.asarray(scale, np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        b = -(scale * x)[:, None] * weights / codes
    return np.where(np.isfinite(b), b, 0.0)


def _point_var(b, refs):
    """(n,) ``sum_i b_i^2 var(x_T,i)`` (0 where ``b`` is None)."""
    if b is None:
        return 0.0
    return np.sum(b * b * np.nan_to_num(np.asarray(refs[2], np.float64), nan=0.0), axis=1)


def table_sigma_s(width_var, x, x_ref, scale, refs=None) -> np.ndarray:
    """(n,) standard error (s) of tau at code ``x`` from the table's widths (``refs``: as
    :func:`time_coefficients`) and, where the scale is the density tests' points
    interpolated, from their own x_T (:func:`point_coefficients`; independent of the
    widths' counting: each reset peak's own counts, the widths under it, the test's
    counted light)."""
    good = np.isfinite(np.asarray(x, np.float64)) & np.isfinite(np.asarray(scale, np.float64))
    return _sum_var(time_coefficients(x, x_ref, scale, refs), width_var, good,
                    _point_var(point_coefficients(x, scale, refs), refs))


def range_sigma_s(width_var, x, x_ref, scale, x0, x_ref0, scale0, refs=None,
                  refs0=None) -> np.ndarray:
    """(n,) standard error (s) of a range's time ``tau(x) - tau0(x0)`` from the table: its
    return at code ``x`` on its axis (``x_ref``, ``scale``; ``refs`` where that scale is
    interpolated, :func:`time_coefficients`) against the delay's return at ``x0`` on the
    zero capture's (``x_ref0``, ``scale0``, ``refs0``); the codes both span cancel."""
    a = (time_coefficients(x, x_ref, scale, refs) - time_coefficients(x0, x_ref0, scale0, refs0))
    good = np.isfinite(np.asarray(x, np.float64)) & np.isfinite(np.asarray(x0, np.float64))
    # the tests' x_T are the same for both times: their coefficients are taken together
    b, b0 = point_coefficients(x, scale, refs), point_coefficients(x0, scale0, refs0)
    points = 0.0
    if b is not None or b0 is not None:
        diff = (0.0 if b is None else b) - (0.0 if b0 is None else b0)
        points = _point_var(np.asarray(diff), refs if b is not None else refs0)
    return _sum_var(a, width_var, good, points)


def scale_rel_sigma(spread) -> np.ndarray:
    """(n,) relative standard error of the time scale at a light: the spread of two
    interpolations of the density tests' scales (:func:`.timescale.scale_spread`: where
    the levels leave the LSB against light unresolved, they part). The LSB points are
    interpolated through, not fitted (no residual to take); their own counting is in the
    widths' (the scale is T over a boundary of the table). 0 where not interpolated."""
    return np.nan_to_num(np.asarray(spread, np.float64), nan=0.0)
