"""What the estimators are given, checked at the door, one check per kind of argument:
the counts, the time axis (edges and bin widths), the cycles, the instrument response,
the false-alarm probability and the delay. An argument that no histogram could satisfy is
a ``ValueError`` naming the parameter, the constraint and the value; a row that is
inconsistent in itself (fewer cycles than counts, no finite time axis) is ranged as the
others but flagged and not detected, so one bad pixel does not stop a file. After the
estimator, :func:`finish` flags what no input should give: a time outside the window, a
non-finite time or uncertainty, an uncertainty below the bound of the return's counts.

Every public estimator runs through :func:`validated`; so do the calibration functions
that take light levels (:func:`check_levels`).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np

from stages.ranging._numba import numba
from stages.ranging.histograms import Estimate, Histograms

#: flags of :attr:`Estimate.flag` ("" when nothing is wrong)
CYCLES_FEWER = "fewer cycles than counts"
NO_AXIS = "no finite time axis"
OUTSIDE = "estimate outside the window"
NOT_FINITE = "no finite time or uncertainty"
EDGE = "at the window's edge (the return may be cut)"


def _fail(name: str, constraint: str, value) -> ValueError:
    return ValueError(f"{name} must be {constraint}, found {value}")


def check_p_fa(p_fa) -> float:
    """The false-alarm probability: a number in (0, 1)."""
    try:
        v = float(p_fa)
    except (TypeError, ValueError):
        raise _fail("p_fa (the false-alarm probability)", "a number in (0, 1)", p_fa) from None
    if not 0.0 < v < 1.0:
        raise _fail("p_fa (the false-alarm probability)", "in (0, 1)", v)
    return v


def check_sigma(sigma_s, span_s: float | None = None, name: str = "sigma_s") -> float:
    """The instrument response's sigma: positive, finite and, when the histogram's span is
    given, no wider than it (a response wider than the window cannot be located in it)."""
    try:
        v = float(sigma_s)
    except (TypeError, ValueError):
        raise _fail(f"{name} (the instrument response)", "a number", sigma_s) from None
    if not (math.isfinite(v) and v > 0):
        raise _fail(f"{name} (the instrument response)", "positive and finite", v)
    if span_s is not None and math.isfinite(span_s) and v > span_s:
        raise _fail(f"{name} (the instrument response)",
                    f"no wider than the histogram's span {span_s:.4g} s", f"{v:.4g} s")
    return v


def check_delay(delay_s, name: str = "delay") -> np.ndarray:
    """A delay (s): finite where given (NaN is "no delay for this pixel", which is not
    ranged); an infinite one is refused."""
    d = np.asarray(delay_s, np.float64)
    if np.isinf(d).any():
        raise _fail(name, "finite", d[np.isinf(d)][0])
    return d


def check_counts(counts) -> tuple[np.ndarray, np.ndarray]:
    """Counts (n_pix, n_bins): at least one bin, finite and non-negative. Returns them as
    float64 and each row's total. (Two reductions when all is well: the checks run on
    every call of the fastest estimator, whose own work is a few ms a 100 000 bins.)"""
    c = np.asarray(counts)
    if c.ndim != 2 or c.shape[1] < 1:
        raise _fail("counts", "(pixels, bins) with at least one bin", f"shape {c.shape}")
    c = c.astype(np.float64, copy=False)
    if numba is not None and c.flags.c_contiguous:
        total, ok = _count_scan(c)
    else:
        total = c.sum(axis=1)
        ok = not c.size or (np.isfinite(total).all() and c.min() >= 0)
    if not ok:
        r, j = np.argwhere(~np.isfinite(c) | (c < 0))[0]
        raise _fail("counts", "finite and >= 0", f"{c[r, j]} (row {r}, bin {j})")
    return c, total


def check_edges(edges_s, n_pix: int, n_bins: int) -> np.ndarray:
    """Bin edges (n_pix, n_bins + 1): never decreasing (a bin may be empty, a dead code),
    and a row's span positive. Rows with a non-finite edge are returned for flagging (a
    TDC without a time axis)."""
    e = np.asarray(edges_s, np.float64)
    if e.shape != (n_pix, n_bins + 1):
        raise _fail("edges_s", f"(pixels, bins + 1) = {(n_pix, n_bins + 1)}",
                    f"shape {e.shape}")
    if numba is not None and e.flags.c_contiguous:
        well = _edges_scan(e)
    else:
        ends = e[:, [0, -1]]
        well = (np.isfinite(ends).all() and (ends[:, 1] > ends[:, 0]).all()
                and (e[:, 1:] >= e[:, :-1]).all())  # (NaN fails a comparison)
    if well:
        return np.zeros(n_pix, bool)
    w = np.diff(e, axis=1)
    neg = np.isfinite(w) & (w < 0)
    if neg.any():
        r, j = np.argwhere(neg)[0]
        raise _fail("bin widths (edges_s)", ">= 0", f"{w[r, j]:.4g} s (row {r}, bin {j})")
    finite = np.isfinite(e).all(axis=1)
    span = np.where(finite, e[:, -1] - e[:, 0], 1.0)
    if (span <= 0).any():
        r = int(np.argmax(span <= 0))
        raise _fail("bin widths (edges_s)", "positive over a row", f"0 s (row {r})")
    return ~finite


def check_cycles(cycles, total: np.ndarray) -> np.ndarray:
    """Cycles (n_pix,): finite and >= 0. Returns the rows with fewer cycles than their
    counts' ``total`` (each cycle holds one first photon at most: inconsistent, flagged)."""
    c = np.asarray(cycles, np.float64)
    if c.shape != total.shape:
        raise _fail("cycles", f"one per pixel ({total.size})", f"shape {c.shape}")
    bad = ~np.isfinite(c) | (c < 0)
    if bad.any():
        r = int(np.argmax(bad))
        raise _fail("cycles", "finite and >= 0", f"{c[r]} (row {r})")
    return c < total


def check_histograms(h: Histograms) -> np.ndarray:
    """Every check of a :class:`Histograms`; returns the flags of its rows ("" or why the
    row cannot be detected)."""
    counts, total = check_counts(h.counts)
    n_pix, n_bins = counts.shape
    no_axis = check_edges(h.edges_s, n_pix, n_bins)
    fewer = check_cycles(h.cycles, total)
    if np.shape(h.valid) != counts.shape:
        raise _fail("valid", f"the counts' shape {counts.shape}", f"shape {np.shape(h.valid)}")
    flags = np.full(n_pix, "", dtype=object)
    flags[fewer] = CYCLES_FEWER
    flags[no_axis] = NO_AXIS
    return flags


def check_levels(n, name: str = "light levels") -> np.ndarray:
    """Light levels for an LSB-against-light fit: finite, and at least 4 distinct (a
    cubic, eq. 5.1: repeated levels give no more of the curve, only fewer unknowns than
    the fit assumes)."""
    from schemas.errors import CalibrationError

    v = np.asarray(n, np.float64)
    if v.ndim != 1 or not np.isfinite(v).all():
        raise CalibrationError(f"{name} must be finite numbers, found {v.tolist()}")
    if np.unique(v).size < 4:
        raise CalibrationError(f"an LSB-against-light fit needs density tests at >= 4 "
                               f"{name} (distinct: a cubic, eq. 5.1); found "
                               f"{np.unique(v).size} distinct in {v.tolist()}")
    return v


def _span(h: Histograms) -> float:
    e = np.asarray(h.edges_s, np.float64)
    s = e[:, -1] - e[:, 0]
    s = s[np.isfinite(s)]
    return float(s.max()) if s.size else math.inf


def _safe(h: Histograms, flags: np.ndarray) -> Histograms:
    """``h`` with its flagged rows replaced by an empty histogram on a 1-bin-per-unit
    axis of the others' typical width: whatever an estimator does with a bad row, it
    cannot crash on it (the row's result is discarded)."""
    bad = flags != ""
    if not bad.any():
        return h
    counts = np.array(h.counts, np.float64)
    edges = np.array(h.edges_s, np.float64)
    cycles = np.array(h.cycles, np.float64)
    good = edges[~bad]
    width = (float(np.median((good[:, -1] - good[:, 0]) / counts.shape[1])) if good.size
             else 1e-10)
    counts[bad] = 0.0
    edges[bad] = np.arange(counts.shape[1] + 1) * width
    cycles[bad] = 1.0
    return Histograms(counts, edges, cycles, np.asarray(h.valid, bool))


def finish(est: Estimate, h: Histograms, sigma_s: float, flags: np.ndarray) -> Estimate:
    """The flags of what no input should give, and the detections they withdraw: a
    non-finite time or sigma, a time outside the histogram's span, an uncertainty below
    ``sigma_s / sqrt(signal counts)`` (the bound of a Gaussian response without binning or
    background: a fit that claims less has failed, e.g. every count in one bin); a return
    within one response of the first or last valid bin is flagged, still detected."""
    flags = np.array(flags, dtype=object)
    t = np.asarray(est.t_s, np.float64)
    sig = np.asarray(est.sigma_s, np.float64)
    n = np.asarray(est.signal_counts, np.float64)
    floor = sigma_s / np.sqrt(np.maximum(np.where(np.isfinite(n), n, 0.0), 1.0))
    sig = np.where(np.isfinite(n) & np.isfinite(sig), np.maximum(sig, floor), sig)
    e = np.asarray(h.edges_s, np.float64)
    ok = flags == ""
    valid = np.asarray(h.valid, bool)
    rows = np.arange(t.size)
    if numba is not None:
        first, last = _valid_span(np.ascontiguousarray(valid))
    else:
        first = valid.argmax(axis=1)                              # the first valid bin
        last = valid.shape[1] - 1 - valid[:, ::-1].argmax(axis=1)  # and the last
    first, last = np.maximum(first, 0), np.maximum(last, 0)
    any_valid = valid[rows, first]  # (a row without a valid bin: no edge to be near)
    with np.errstate(invalid="ignore"):
        not_finite = ~(np.isfinite(t) & np.isfinite(sig) & (sig > 0))
        outside = ~not_finite & ((t < e[:, 0]) | (t > e[:, -1]))
        lo = 0.5 * (e[rows, first] + e[rows, first + 1])
        hi = 0.5 * (e[rows, last] + e[rows, last + 1])
        edge = (~not_finite & ~outside & any_valid
                & ((t - lo < sigma_s) | (hi - t < sigma_s)))
    flags[ok & not_finite] = NOT_FINITE
    flags[ok & outside] = OUTSIDE
    flags[ok & edge] = EDGE
    usable = (flags == "") | (flags == EDGE)
    detected = np.asarray(est.detected, bool) & usable
    return dataclasses.replace(est, t_s=np.where(usable, t, np.nan),
                               sigma_s=np.where(usable, sig, np.nan), detected=detected,
                               flag=flags)


def validated(fn):
    """Wrap a public estimator ``fn(h, sigma_s, p_fa=1e-3, ...)``: check its arguments,
    range its bad rows harmlessly and :func:`finish` its result."""

    @functools.wraps(fn)
    def run(h: Histograms, sigma_s: float, p_fa: float = 1e-3, *args, **kwargs):
        flags = check_histograms(h)
        sigma_s = check_sigma(sigma_s, _span(h))
        p_fa = check_p_fa(p_fa)
        safe = _safe(h, flags)
        if safe.counts.shape[0] == 0:
            z = np.zeros(0)
            return Estimate(z, z, z, z, z, np.zeros(0, bool), fn.__name__,
                            np.zeros(0, dtype=object))
        est = fn(safe, sigma_s, p_fa, *args, **kwargs)
        return finish(est, safe, sigma_s, flags)

    run.unchecked = fn
    return run


if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _count_scan(c):
        """Each row's total, and whether every count is finite and >= 0, in one pass (the
        numpy form: a sum and a minimum)."""
        n_pix, n = c.shape
        total = np.empty(n_pix)
        low = np.inf
        for p in range(n_pix):
            acc = 0.0
            for j in range(n):
                acc += c[p, j]                # NaN and inf carry into the total
                low = min(low, c[p, j])
            total[p] = acc
        return total, low >= 0.0 and np.isfinite(total).all()

    @numba.njit(cache=True, nogil=True)
    def _valid_span(valid):
        """Each row's first and last valid bin (0 and -1 for a row with none)."""
        n_pix, n = valid.shape
        first = np.zeros(n_pix, np.int64)
        last = np.full(n_pix, -1, np.int64)
        for p in range(n_pix):
            for j in range(n):
                if valid[p, j]:
                    first[p] = j
                    break
            for j in range(n - 1, -1, -1):
                if valid[p, j]:
                    last[p] = j
                    break
        return first, last

    @numba.njit(cache=True, nogil=True)
    def _edges_scan(e):
        """Whether every row's edges are finite, never decrease and span > 0, in one pass
        (the numpy form: a comparison of neighbours)."""
        n_pix, n = e.shape
        for p in range(n_pix):
            if not (np.isfinite(e[p, 0]) and np.isfinite(e[p, n - 1])
                    and e[p, n - 1] > e[p, 0]):
                return False
            for j in range(n - 1):
                if not e[p, j + 1] >= e[p, j]:
                    return False
        return True

