"""The width of a return, measured: the second moment of its pile-up-corrected counts
above the background, in a window that grows with what it measures (a response wider
than the window first assumed is not cut to it). What the ranges' ``fwhm_m`` reports, and
the instrument response taken from the data when none is given."""

from __future__ import annotations

import math

import numpy as np

from stages.models.tcspc import FWHM_PER_SIGMA
from stages.ranging._numba import numba
from stages.ranging.detection import _background
from stages.ranging.histograms import Histograms

#: half-width of the measuring window in the width it measures (a Gaussian's moments within
#: +-4 sigma are its own to 0.3 %)
WINDOW_WIDTHS = 4.0
#: times the window is re-centred and re-sized on what it measured (from 1 bin, a response
#: 4 bins wide is measured within 2 % by the fifth)
ROUNDS = 5
#: a return needs this many counts above the background for its width to enter the
#: instrument response taken from the data
MIN_COUNTS = 100.0


def return_sigma(h: Histograms, t_s, sigma0_s: float, rounds: int = ROUNDS,
                 compiled: bool | None = None):
    """Per pixel: the return's measured sigma (s) around ``t_s`` and its counts above the
    background. The quantisation of the bins (width^2 / 12) is taken out; NaN where no
    count stands above the background or ``t_s`` is not finite (those rows are not
    computed: a pixel's further returns are mostly none)."""
    t_all = np.asarray(t_s, np.float64)
    sig_all, tot_all = np.full(t_all.shape, np.nan), np.zeros(t_all.shape)
    live = np.flatnonzero(np.isfinite(t_all))
    if not live.size:
        return sig_all, tot_all
    compiled = (numba is not None) if compiled is None else compiled
    sig0 = max(float(sigma0_s), h.bin_s)
    if compiled:
        t, sig = t_all[live], np.full(live.size, sig0)
        tot = _sigma_numba(np.ascontiguousarray(h.lam),
                           np.ascontiguousarray(h.at_risk), np.ascontiguousarray(h.widths),
                           np.ascontiguousarray(h.valid, np.bool_),
                           np.ascontiguousarray(np.broadcast_to(  # (one for all rows too)
                               np.asarray(h.cycles, np.float64), h.counts.shape[:1])),
                           np.ascontiguousarray(h.centres), live, t, sig, float(h.bin_s),
                           int(rounds))
        rows = live
    else:
        rows = slice(None) if live.size == t_all.size else live
        counts, at_risk = np.asarray(h.counts)[rows], h.at_risk[rows]
        r = np.maximum(at_risk, 1.0)  # (Histograms.intensity, on these rows)
        lam = -np.log1p(-np.minimum(counts / r, 1 - 1e-12))
        w, valid = h.widths[rows], np.asarray(h.valid, bool)[rows]
        bg = _background(lam, w, valid, at_risk)
        excess = np.where(valid, np.maximum(lam - bg[:, None] * w, 0.0), 0.0) * (
            np.asarray(h.cycles)[rows][:, None])
        t, sig = t_all[rows].copy(), np.full(excess.shape[0], sig0)
        tot = _moments_numpy(excess, h.centres[rows], w ** 2, t, sig, float(h.bin_s),
                             int(rounds))
    bad = ~(tot > 0)
    sig_all[rows] = np.where(bad, np.nan, sig)
    tot_all[rows] = np.where(bad, 0.0, tot)
    return sig_all, tot_all


def _moments_numpy(excess, cen, w2, t, sig, bin_s, rounds):
    """The window's rounds over whole rows (the numpy path): ``t`` and ``sig`` updated in
    place, the counts in the last window returned."""
    tot = np.zeros(t.shape)
    on = np.arange(t.size)  # the rows still moving: a row whose time and sigma a round
    # left as they were has reached what the next rounds give. (Buffers reused: a
    # temporary of a few hundred kB is fresh pages from the system at every operation.)
    buf_all, e_all = np.empty_like(excess), np.empty_like(excess)
    win_all = np.empty(excess.shape, bool)
    for _ in range(rounds):
        t_on, sig_on = t[on], sig[on]
        buf, e, win = buf_all[:on.size], e_all[:on.size], win_all[:on.size]
        half = WINDOW_WIDTHS * np.maximum(sig_on, bin_s)
        with np.errstate(invalid="ignore"):
            np.less_equal(np.abs(np.subtract(cen, t_on[:, None], out=buf), out=buf),
                          half[:, None], out=win)
        e.fill(0.0)
        np.copyto(e, excess, where=win)
        tot_on = e.sum(axis=1)
        ok = tot_on > 0
        d = np.where(ok, tot_on, 1.0)
        mu = np.multiply(e, cen, out=buf).sum(axis=1) / d
        np.subtract(cen, mu[:, None], out=buf)
        var = np.multiply(e, np.multiply(buf, buf, out=buf), out=buf).sum(axis=1) / d
        q = np.multiply(e, w2, out=buf).sum(axis=1) / d / 12.0
        new = np.sqrt(np.maximum(var - q, 0.0))
        sig_new = np.where(ok & (new > 0), new, sig_on)
        t_new = np.where(ok, mu, t_on)
        tot[on], sig[on], t[on] = tot_on, sig_new, t_new
        moved = (sig_new != sig_on) | ~((t_new == t_on) | (np.isnan(t_new) & np.isnan(t_on)))
        on = on[moved]
        if not on.size:
            break
        if on.size < moved.size:
            excess, cen, w2 = excess[moved], cen[moved], w2[moved]
    return tot


if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _window_sums(ex, cen, w, a, b, tp, half, full):
        """One round's sums over bins ``a``..``b - 1`` of a row (``full``: every bin, those
        outside the window adding 0 times their centre and width, as numpy's zeros do)."""
        s0 = s1 = 0.0
        for j in range(a, b):
            if not full or abs(cen[j] - tp) <= half:
                s0 += ex[j]
                s1 += ex[j] * cen[j]
            else:
                s1 += 0.0 * cen[j]
        d = s0 if s0 > 0 else 1.0
        mu = s1 / d
        s2 = s3 = 0.0
        for j in range(a, b):
            e = ex[j] if not full or abs(cen[j] - tp) <= half else 0.0
            c = cen[j] - mu
            s2 += e * (c * c)
            s3 += e * (w[j] * w[j])
        return s0, mu, s2 / d, s3 / d / 12.0

    @numba.njit(cache=True, nogil=True)
    def _sigma_numba(lam_all, at_risk, widths, valid, cycles, centres, rows, t, sig, bin_s,
                     rounds):
        """:func:`return_sigma`'s work on ``rows`` a row at a time (``lam_all``: the
        intensity, :attr:`Histograms.lam`): the row's excess (as
        :func:`stages.ranging.detection._background` and the numpy path make it), then
        the rounds, each summing its window's bins only (found from the centre nearest
        the time: the centres increase along a row; a row whose centres or widths are not
        finite and increasing sums every bin, as numpy does). The same windows, rounds
        and stop as :func:`_moments_numpy`; the sums in another order. ``t``, ``sig`` (one
        a row) updated in place; the counts in the last window returned."""
        n = lam_all.shape[1]
        ex = np.empty(n)
        tot = np.zeros(rows.size)
        for i in range(rows.size):
            p = rows[i]
            cen, w, lam = centres[p], widths[p], lam_all[p]
            sl = sw = 0.0
            for j in range(n):
                if valid[p, j]:
                    sl += lam[j]
                    sw += w[j]
            rate = sl / (sw if sw > 1e-300 else 1e-300)
            sl = sw = 0.0
            for j in range(n):
                r = at_risk[p, j]
                r = r if not r < 1.0 else 1.0
                expect = rate * w[j]
                # (within a count of what is expected it is kept whatever the sqrt adds)
                if valid[p, j] and ((expect >= 0.0 and lam[j] <= expect + 1 / r) or
                                    lam[j] <= expect + (5 * math.sqrt(expect * r) + 1) / r):
                    sl += lam[j]
                    sw += w[j]
            bg = sl / (sw if sw > 1e-300 else 1e-300)
            ordered = True
            for j in range(n):
                v = lam[j] - bg * w[j]
                ex[j] = (v if not v < 0.0 else 0.0) * cycles[p] if valid[p, j] else (
                    0.0 * cycles[p])
                if not (math.isfinite(cen[j]) and math.isfinite(w[j])
                        and (j == 0 or cen[j - 1] <= cen[j])):
                    ordered = False
            for _ in range(rounds):
                tp, sp = t[i], sig[i]
                half = WINDOW_WIDTHS * (sp if sp > bin_s else bin_s)
                if ordered and math.isfinite(tp) and math.isfinite(half):
                    lo, hi = 0, n  # the first centre >= tp; the window around it
                    while lo < hi:
                        mid = (lo + hi) // 2
                        if cen[mid] < tp:
                            lo = mid + 1
                        else:
                            hi = mid
                    a = lo
                    while a > 0 and abs(cen[a - 1] - tp) <= half:
                        a -= 1
                    b = lo
                    while b < n and abs(cen[b] - tp) <= half:
                        b += 1
                    s0, mu, var, q = _window_sums(ex, cen, w, a, b, tp, half, False)
                else:
                    s0, mu, var, q = _window_sums(ex, cen, w, 0, n, tp, half, True)
                v = var - q
                new = math.sqrt(v if not v < 0.0 else 0.0)
                sig_new = new if s0 > 0 and new > 0 else sp
                t_new = mu if s0 > 0 else tp
                tot[i], sig[i], t[i] = s0, sig_new, t_new
                if sig_new == sp and (t_new == tp or (math.isnan(t_new) and math.isnan(tp))):
                    break
        return tot


def return_fwhm(h: Histograms, t_s, sigma_s: float) -> np.ndarray:
    """The measured FWHM (s) of each pixel's return around ``t_s`` (NaN: none)."""
    return FWHM_PER_SIGMA * return_sigma(h, t_s, sigma_s)[0]


def _pooled_sigma(h: Histograms, t0, s0: float, rows, rounds: int = 6,
                  k: float = 3.0) -> float:
    """The response's sigma pooled over the returns of ``rows`` (their times ``t0``, a
    first sigma ``s0``): the second moment of their counts above the background, signed
    (a row's own moments clip the background's negative fluctuations, and the median of
    them was 12 % wide at 100 counts on 1 a bin, 42 % for a response 12 bins wide), each
    row centred on its own mean, in +-k sigma, the truncation and the bins' width^2 / 12
    taken out. NaN where the counts do not allow it."""
    counts, at_risk = np.asarray(h.counts, np.float64)[rows], h.at_risk[rows]
    lam = -np.log1p(-np.minimum(counts / np.maximum(at_risk, 1.0), 1 - 1e-12))
    w, valid = h.widths[rows], np.asarray(h.valid, bool)[rows]
    bg = _background(lam, w, valid, at_risk)
    cyc = np.broadcast_to(np.asarray(h.cycles, np.float64), h.counts.shape[:1])[rows]
    e_all = np.where(valid, lam - bg[:, None] * w, 0.0) * cyc[:, None]
    cen, t, s = h.centres[rows], np.array(t0, np.float64), float(s0)
    trunc = 1.0 - 2.0 * k * math.exp(-k * k / 2) / math.sqrt(2 * math.pi) / math.erf(
        k / math.sqrt(2))
    for _ in range(rounds):
        half = k * max(s, h.bin_s)
        for _ in range(2):  # each row's centre: its own mean in the window
            e = np.where(np.abs(cen - t[:, None]) <= half, e_all, 0.0)
            tot = e.sum(axis=1)
            t = np.where(tot > 0, (e * cen).sum(axis=1) / np.where(tot > 0, tot, 1.0), t)
        e = np.where(np.abs(cen - t[:, None]) <= half, e_all, 0.0)
        total = e.sum()
        if not total > 0:
            return float("nan")
        var = (e * (cen - t[:, None]) ** 2).sum() / total - h.bin_s ** 2 / 12.0
        s = math.sqrt(max(var, 0.0) / trunc)
    return s


def response_from_data(h: Histograms, t_s=None) -> tuple[float, str]:
    """The instrument response's sigma (s) when none is given: the median measured sigma
    of the returns with >= :data:`MIN_COUNTS` counts above the background (at ``t_s``, or
    each histogram's fullest bin), and how it was chosen. One bin when no return is that
    strong. (One bin was the default: a response 4 bins wide then gave sigmas 7-11x too
    small.)"""
    from stages.ranging.validation import _safe, check_histograms

    h = _safe(h, check_histograms(h))  # (what the estimators refuse, refused first)
    counts = np.asarray(h.counts, np.float64)
    if t_s is None:
        score = np.where(np.asarray(h.valid, bool), counts, -1.0)
        j = np.argmax(score, axis=1)
        t_s = h.centres[np.arange(j.size), j]
    sig, tot = return_sigma(h, t_s, h.bin_s)
    strong = np.isfinite(sig) & (tot >= MIN_COUNTS)
    if not strong.any():
        return float(h.bin_s), "one bin (no return of >= 100 counts to measure it on)"
    s = float(np.median(sig[strong]))
    pooled = _pooled_sigma(h, np.asarray(t_s, np.float64)[strong], s, strong)
    if np.isfinite(pooled) and 0.5 * s <= pooled <= 1.5 * s:
        s = pooled
    return max(s, float(h.bin_s) / np.sqrt(12.0)), (
        f"measured on {int(strong.sum())} return(s) of >= {MIN_COUNTS:g} counts")
