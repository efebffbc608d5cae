"""More than one surface a pixel: up to K returns (a window or a fence before the target).

Deflation by masking (a Gaussian response: the simulator's chip, ``--irf-ps``; with a
measured one, :mod:`stages.ranging.multi_irf` subtracts the found returns' whole responses
instead): the strongest return is found as by one estimator; the bins within
:data:`MASK_WIDTHS` instrument sigmas of it are masked (``valid`` False: still counted in
the at-risk numbers, so pile-up is handled as for one return) and the estimator searches
what is left; a found return's time is then refitted with every other return masked (a
neighbour inside its fitting window pulled it). Returns are ordered by signal counts
(0 the strongest).

False alarms: return k + 1 is searched only where return k was detected, each test at
``p_fa`` over the bins left, against the background plus the tails of the returns found
before it (:func:`_beyond_tails`: a return of 16 000 counts puts ~7 counts a bin just past
its mask, which a flat background of 0.3 a bin calls a return). On a background-only
histogram every detection needs the first test to fire, so a pixel's false-alarm
probability is that of one return (<= p_fa);
on a pixel with real returns only the test after the last real one can be false, again
<= p_fa.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from scipy.special import ndtr

from stages.ranging._numba import numba
from stages.ranging.detection import bin_of, poisson_tail, tested_bin
from stages.ranging.histograms import Estimate, Histograms
from stages.ranging.irf import Response
from stages.ranging.registry import estimate
from stages.ranging.validation import check_histograms, check_p_fa, check_sigma
from stages.ranging.width import return_fwhm

#: returns a pixel may have unless told otherwise
MAX_RETURNS = 3
#: half-width of the mask around a found return, in instrument sigmas (a Gaussian's
#: counts beyond 3 sigma: 0.3 %)
MASK_WIDTHS = 3.0


#: what :class:`Histograms` derives row by row (the same on any of its rows)
_PER_ROW = ("at_risk", "widths", "centres", "lam")


def _derived(h: Histograms, out: Histograms, rows, bin_s: bool) -> Histograms:
    """``out`` (``h``'s ``rows``) with what ``h`` derived already (at risk, widths,
    centres, intensity; ``bin_s`` too when ``out`` has all of ``h``'s rows): not derived again."""
    for name in _PER_ROW + (("bin_s",) if bin_s else ()):
        if name in h.__dict__:
            v = h.__dict__[name]
            out.__dict__[name] = v if name == "bin_s" else v[rows]
    return out


def _rows(h: Histograms, rows, valid=None) -> Histograms:
    if not isinstance(rows, slice) and len(rows) == h.counts.shape[0] and (
            np.array_equal(rows, np.arange(len(rows)))):
        rows = slice(None)  # every row, in order: views, not copies (the same numbers)
    return _derived(h, Histograms(h.counts[rows], h.edges_s[rows], h.cycles[rows],
                                  h.valid[rows] if valid is None else valid),
                    rows, isinstance(rows, slice) and rows == slice(None))


def _masked(h: Histograms, times: list[np.ndarray], half_s: float) -> np.ndarray:
    """``h``'s valid bins less those within ``half_s`` of any of ``times`` (per row)."""
    cen = h.centres
    keep = np.asarray(h.valid, bool).copy()
    if numba is not None and keep.shape == cen.shape and keep.ndim == 2 and all(
            np.shape(t) == keep.shape[:1] for t in times):
        cen = np.ascontiguousarray(cen, np.float64)
        for t in times:
            _mask_near(keep, cen, np.ascontiguousarray(t, np.float64), float(half_s))
        return keep
    for t in times:  # (a row without the return, its time NaN, keeps its bins)
        t = np.asarray(t, np.float64)
        live = np.flatnonzero(np.isfinite(t))
        rows = slice(None) if live.size == t.size else live
        keep[rows] &= ~(np.abs(cen[rows] - t[rows, None]) <= half_s)
    return keep


if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _mask_near(keep, cen, t, half_s):
        """:func:`_masked`'s step a row at a time: the bins within ``half_s`` of ``t``
        (a row whose ``t`` is not finite keeps its bins), the same comparisons."""
        for p in range(t.size):
            if not math.isfinite(t[p]):
                continue
            for j in range(cen.shape[1]):
                if abs(cen[p, j] - t[p]) <= half_s:
                    keep[p, j] = False


def _beyond_tails(sub: Histograms, t_s, found_t, found_m, sigma_s, bg_rate, p_fa):
    """Return k's detection against what background and the returns found before it put
    in its tested bin (:func:`tested_bin` of the bins left): ``found_t``, ``found_m`` their
    times and detections per cycle (Gaussian responses of ``sigma_s``), ``bg_rate`` per
    second; the Poisson tail at ``p_fa`` over the bins left, as the estimators test."""
    rows = np.arange(sub.counts.shape[0])
    q = tested_bin(sub.counts, sub.valid, bin_of(sub.edges_s, t_s, np.zeros(rows.size, int)))
    lo, hi = sub.edges_s[rows, q], sub.edges_s[rows, q + 1]
    lam = bg_rate * (hi - lo)
    for t, m in zip(found_t, found_m, strict=True):
        lam = lam + np.nan_to_num(m * (ndtr((hi - t) / sigma_s) - ndtr((lo - t) / sigma_s)))
    b = np.maximum(sub.at_risk[rows, q], 0.0) * -np.expm1(-lam)
    n_bins = np.maximum(np.asarray(sub.valid).sum(axis=1), 1)
    # (an estimate that slid into a found return's mask, its bin and neighbours masked,
    # was tested on a masked bin's count, the found return's own: not a surface)
    return (poisson_tail(sub.counts[rows, q], b) <= p_fa / n_bins) & np.asarray(
        sub.valid, bool)[rows, q]


_NUMERIC = ("t_s", "sigma_s", "fwhm_s", "signal_counts", "background_per_bin")


def _columns(est: Estimate, n_pix: int, rows=None) -> dict:
    """An estimate's per-pixel columns, on all ``n_pix`` pixels (``rows``: the pixels it
    was computed on; the others NaN, undetected, unflagged)."""
    rows = np.arange(n_pix) if rows is None else rows
    out = {}
    for name in _NUMERIC:
        col = np.full(n_pix, np.nan)
        col[rows] = np.asarray(getattr(est, name), np.float64)
        out[name] = col
    out["detected"] = np.zeros(n_pix, bool)
    out["detected"][rows] = np.asarray(est.detected, bool)
    out["flag"] = np.full(n_pix, "", dtype=object)
    if est.flag is not None:
        out["flag"][rows] = est.flag
    return out


def estimate_returns(h: Histograms, sigma_s: float, estimator: str = "ml",
                     p_fa: float = 1e-3, max_returns: int = MAX_RETURNS,
                     response: Response | None = None, first: Estimate | None = None,
                     single=None) -> Estimate:
    """Up to ``max_returns`` returns per pixel, each with its own detection at ``p_fa``
    (see the module docstring). Returns the estimate, one row per pixel and return
    (pixel-major, ``pixel`` and ``return_index``, 0 the strongest; every pixel has its row
    0, detected or not, and a row k > 0 only for a detected return k).
    ``fwhm_s`` is each return's measured width (:func:`stages.ranging.width.return_fwhm`,
    the other returns masked); ``max_returns=1`` is the single-return estimate with it.

    With a measured ``response`` (a real instrument's, its tail included) the further
    returns are searched by :func:`stages.ranging.multi_irf.further_returns` instead of
    the Gaussian masks; ``first`` is then the pixels' single-return estimate if the caller
    has one, and ``single`` the function of :class:`Histograms` that made it (its
    estimator and shape, e.g. a measured response's fit), else the ``estimator``'s with
    ``sigma_s``: it times each return of a pixel with several, the others taken out."""
    if isinstance(max_returns, bool) or not (isinstance(max_returns, int | np.integer)
                                             and max_returns >= 1):
        raise ValueError(f"max_returns must be an integer >= 1, found {max_returns!r}")
    flags = check_histograms(h)
    sigma_s = check_sigma(sigma_s)
    p_fa = check_p_fa(p_fa)
    n_pix = h.counts.shape[0]
    if response is not None:
        from stages.ranging.multi_irf import further_returns

        if abs(response.bin_s / h.bin_s - 1) > 0.01:
            raise ValueError(f"response {response.source!r} was measured with "
                             f"{response.bin_s * 1e12:.4g} ps bins, these histograms have "
                             f"{h.bin_s * 1e12:.4g} ps")

        if single is None:
            def single(hh):
                return estimate(hh, sigma_s, estimator, p_fa)
        first = single(h) if first is None else first
        live = np.asarray(first.detected, bool) & (flags == "")
        found = further_returns(h, response, dataclasses.replace(first, detected=live),
                                p_fa, max_returns, single)
        found[0]["detected"] = np.asarray(first.detected, bool)
        found[0]["flag"] = _columns(first, n_pix)["flag"]
        for cols in found[1:]:
            cols["flag"] = np.full(n_pix, "", dtype=object)
        return _assemble(found, first.estimator)
    half = MASK_WIDTHS * sigma_s
    first = estimate(h, sigma_s, estimator, p_fa)
    found = [_columns(first, n_pix)]
    live = found[0]["detected"] & (flags == "")
    cycles = np.maximum(np.asarray(h.cycles, np.float64), 1.0)
    bg_rate = np.nan_to_num(found[0]["background_per_bin"]) / (h.bin_s * cycles)
    while len(found) < max_returns and live.any():
        rows = np.flatnonzero(live)
        sub = _rows(h, rows, _masked(_rows(h, rows), [f["t_s"][rows] for f in found], half))
        cols = _columns(estimate(sub, sigma_s, estimator, p_fa), n_pix, rows)
        cols["detected"][rows] &= _beyond_tails(
            sub, cols["t_s"][rows], [f["t_s"][rows] for f in found],
            [np.nan_to_num(f["signal_counts"][rows]) / cycles[rows] for f in found],
            sigma_s, bg_rate[rows], p_fa)
        cols["t_s"] = np.where(cols["detected"], cols["t_s"], np.nan)
        found.append(cols)
        live = cols["detected"]
    k = len(found)
    if k > 1:  # refit each return with the others masked, where there are others
        for i, cols in enumerate(found):
            others = [f["t_s"] for j, f in enumerate(found) if j != i]
            rows = np.flatnonzero(cols["detected"] & np.any([np.isfinite(t) for t in others],
                                                             axis=0))
            if not rows.size:
                continue
            sub = _rows(h, rows, _masked(_rows(h, rows), [t[rows] for t in others], half))
            e = estimate(sub, sigma_s, estimator, p_fa)
            for name in _NUMERIC:
                cols[name][rows] = np.asarray(getattr(e, name), np.float64)
    _ = h.lam  # (the intensity: computed once, read by each return's masked copy of h)
    for i, cols in enumerate(found):  # each return's measured width, the others masked
        others = [f["t_s"] for j, f in enumerate(found) if j != i]
        hm = _rows(h, slice(None), _masked(h, others, half)) if others else h
        cols["fwhm_s"] = return_fwhm(hm, cols["t_s"], sigma_s)
    return _assemble(found, first.estimator)


def _assemble(found: list[dict], estimator: str) -> Estimate:
    """One row a pixel and detected return of the per-return columns ``found`` (every
    pixel's row 0 kept), ordered by signal counts."""
    # order by signal counts, strongest first (a pixel's undetected row 0 stays row 0)
    det = np.stack([f["detected"] for f in found])                        # (k, n_pix)
    strength = np.stack([np.nan_to_num(f["signal_counts"], nan=0.0) for f in found])
    strength = np.where(det, strength, -np.inf)
    strength[0] = np.where(det[0], strength[0], np.inf)
    order = np.argsort(-strength, axis=0, kind="stable")
    keep = np.take_along_axis(det, order, axis=0)
    keep[0] = True
    pixel, index = np.nonzero(keep.T)                                     # pixel-major

    def col(name, dtype):
        a = np.stack([np.asarray(f[name], dtype) for f in found])
        return np.take_along_axis(a, order, axis=0).T[keep.T]

    return Estimate(**{name: col(name, np.float64) for name in _NUMERIC},
                    detected=col("detected", bool), estimator=estimator,
                    flag=col("flag", object), return_index=index.astype(np.int64),
                    pixel=pixel.astype(np.int64))


def select_rows(est: Estimate, keep) -> Estimate:
    """The rows ``keep`` (a mask or indices) of a per-row estimate."""
    return Estimate(**{f: (v[keep] if isinstance(v := getattr(est, f), np.ndarray) else v)
                       for f in Estimate.__dataclass_fields__})

