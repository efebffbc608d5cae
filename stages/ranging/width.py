"""The width of a return, measured: the second moment of its pile-up-corrected counts
above the background, in a window that grows with what it measures (a response wider
than the window first assumed is not cut to it). What the ranges' ``fwhm_m`` reports, and
the instrument response taken from the data when none is given."""

from __future__ import annotations

import numpy as np

from stages.models.tcspc import FWHM_PER_SIGMA
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


def return_sigma(h: Histograms, t_s, sigma0_s: float, rounds: int = ROUNDS):
    """Per pixel: the return's measured sigma (s) around ``t_s`` and its counts above the
    background. The quantisation of the bins (width^2 / 12) is taken out; NaN where no
    count stands above the background or ``t_s`` is not finite (those rows are not
    computed: a pixel's further returns are mostly none)."""
    t_all = np.asarray(t_s, np.float64)
    sig_all, tot_all = np.full(t_all.shape, np.nan), np.zeros(t_all.shape)
    live = np.flatnonzero(np.isfinite(t_all))
    if not live.size:
        return sig_all, tot_all
    rows = slice(None) if live.size == t_all.size else live
    counts, at_risk = np.asarray(h.counts)[rows], h.at_risk[rows]
    r = np.maximum(at_risk, 1.0)  # (Histograms.intensity, on these rows)
    lam = -np.log1p(-np.minimum(counts / r, 1 - 1e-12))
    w, valid = h.widths[rows], np.asarray(h.valid, bool)[rows]
    bg = _background(lam, w, valid, at_risk)
    excess = np.where(valid, np.maximum(lam - bg[:, None] * w, 0.0), 0.0) * (
        np.asarray(h.cycles)[rows][:, None])
    cen, w2 = h.centres[rows], w ** 2
    t = t_all[rows].copy()
    sig = np.full(t.shape, max(float(sigma0_s), h.bin_s))
    tot = np.zeros(t.shape)
    on = np.arange(t.size)  # the rows still moving: a row whose time and sigma a round
    # left as they were has reached what the next rounds give. (Buffers reused: a
    # temporary of a few hundred kB is fresh pages from the system at every operation.)
    buf_all, e_all = np.empty_like(excess), np.empty_like(excess)
    win_all = np.empty(excess.shape, bool)
    for _ in range(rounds):
        t_on, sig_on = t[on], sig[on]
        buf, e, win = buf_all[:on.size], e_all[:on.size], win_all[:on.size]
        half = WINDOW_WIDTHS * np.maximum(sig_on, h.bin_s)
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
    bad = ~(tot > 0)
    sig_all[rows] = np.where(bad, np.nan, sig)
    tot_all[rows] = np.where(bad, 0.0, tot)
    return sig_all, tot_all


def return_fwhm(h: Histograms, t_s, sigma_s: float) -> np.ndarray:
    """The measured FWHM (s) of each pixel's return around ``t_s`` (NaN: none)."""
    return FWHM_PER_SIGMA * return_sigma(h, t_s, sigma_s)[0]


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
    return max(s, float(h.bin_s) / np.sqrt(12.0)), (
        f"measured on {int(strong.sum())} return(s) of >= {MIN_COUNTS:g} counts")
