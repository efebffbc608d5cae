"""The Poisson maximum-likelihood estimator with pile-up (the exact binomial
factorisation, see the package docstring); compiled and numpy paths."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import ndtr

from stages.models.tcspc import FWHM_PER_SIGMA, SQRT2PI
from stages.ranging._numba import numba
from stages.ranging.detection import _detect
from stages.ranging.fast import _M_FLOOR, _fast_args, _fast_numpy
from stages.ranging.histograms import Estimate, Histograms
from stages.ranging.validation import validated

if numba is not None:
    from stages.ranging.fast import _fast_numba

#: the fit stops when a step moves its time and its signal by less than this part of their
#: own sigmas (from the information): the last steps of a slow approach were moving the
#: time by 1e-7 of its sigma, each as costly as the first
STEP_TOL = 1e-3


def _ml_setup(h: Histograms, sigma_s: float, half_width_sigma: float, compiled: bool):
    """What both ML paths start from: the fast estimator's peak, background and time."""
    fargs, _ = _fast_args(h, sigma_s, 1e-3)
    t_start, peak, _, bg, _, _ = (_fast_numba if compiled else _fast_numpy)(*fargs)
    counts, edges, valid, cycles = fargs[:4]
    args = (counts, np.ascontiguousarray(h.widths), np.ascontiguousarray(h.centres), valid,
            cycles, t_start, peak, bg)
    # (no wider than the histogram: a response far wider than the window made it unbounded)
    k = min(max(3, int(np.ceil(half_width_sigma * sigma_s / h.bin_s))), h.counts.shape[1])
    return args, k


@validated
def ml(h: Histograms, sigma_s: float, p_fa: float = 1e-3, iterations: int = 30,
       half_width_sigma: float = 8.0, compiled: bool | None = None,
       step_tol: float | None = None):
    """Poisson maximum likelihood of signal + background with pile-up (the exact binomial
    factorisation, see the module docstring), by Fisher scoring with step halving.

    The signal (arrival time, detections per cycle) is fitted in a window of
    ``half_width_sigma`` around the fast estimator's peak, starting from its time; the
    flat background is its constant-hazard estimate away from the peak. sigma from the
    expected information. The fit stops at a fixed point, after ``iterations``, or when a
    step moves both the time and the signal by less than ``step_tol`` (default
    :data:`STEP_TOL`) of their own sigmas (0: only at a fixed point or the limit).
    Compiled where numba is installed; the numpy path runs the same iterations (tested to
    agree).
    """
    compiled = (numba is not None) if compiled is None else compiled
    step_tol = STEP_TOL if step_tol is None else float(step_tol)
    args, k = _ml_setup(h, sigma_s, half_width_sigma, compiled)
    if compiled:
        t0, sig, m, bg, peak = _ml_numba(*args, k, sigma_s, iterations, step_tol)
    else:
        t0, sig, m, bg, peak = _ml_numpy(*args, k, sigma_s, iterations, step_tol)
    return Estimate(t0, sig, np.full(t0.size, FWHM_PER_SIGMA * sigma_s), m * h.cycles,
                    bg * h.bin_s * h.cycles, _detect(h, peak, bg, p_fa, t0, sigma_s), "ml")


def _ml_numpy(counts_all, widths, centres, valid_all, cycles, t_start, peak, bg, k, sigma_s,
              iterations, step_tol=STEP_TOL):
    n_pix, n = counts_all.shape
    idx = np.clip(peak[:, None] + np.arange(-k, k + 1)[None, :], 0, n - 1)
    rows = np.arange(n_pix)[:, None]
    edges_lo = centres[rows, idx] - 0.5 * widths[rows, idx]
    edges_hi = centres[rows, idx] + 0.5 * widths[rows, idx]
    at_risk = cycles[:, None] - (np.cumsum(counts_all, axis=1) - counts_all)
    counts, r = counts_all[rows, idx], np.maximum(at_risk[rows, idx], 0.0)
    first = np.concatenate([np.ones((n_pix, 1), bool), np.diff(idx, axis=1) > 0], 1)
    valid = valid_all[rows, idx] & first
    w = edges_hi - edges_lo
    bgw = bg[:, None] * w
    hw = np.where(valid, counts, 0).sum(1)
    r0 = np.maximum(r[:, 0], hw + 1)
    floor = _M_FLOOR / np.maximum(cycles, 1.0)
    m = np.maximum(-np.log1p(-hw / r0) - bg * np.where(valid, w, 0).sum(1), floor)
    t0 = t_start.copy()

    def model(t0, m):
        za = (edges_lo - t0[:, None]) / sigma_s
        zb = (edges_hi - t0[:, None]) / sigma_s
        dphi = ndtr(zb) - ndtr(za)
        return m[:, None] * dphi + bgw, za, zb, dphi

    def loglik(lam):
        lam = np.maximum(lam, 1e-300)
        return np.where(valid, counts * np.log(-np.expm1(-lam)) - (r - counts) * lam,
                        0.0).sum(1)

    def info_score(m, lam, za, zb, dphi):
        # (a bin of no intensity, no background: cycles / expm1(1e-300) overflowed to inf
        # where the file gives no cycles, and inf x 0 made sigma NaN; 1e-200 keeps it finite)
        lam_c = np.maximum(lam, 1e-200)
        em1 = np.expm1(lam_c)
        sl = np.where(valid, counts / em1 - (r - counts), 0.0)
        il = np.where(valid, r / em1, 0.0)
        pdf = (np.exp(-0.5 * zb * zb) - np.exp(-0.5 * za * za)) / (SQRT2PI * sigma_s)
        jt, jm = -m[:, None] * pdf, dphi
        i00, i01, i11 = (il * jt * jt).sum(1), (il * jt * jm).sum(1), (il * jm * jm).sum(1)
        return i00, i01, i11, (sl * jt).sum(1), (sl * jm).sum(1)

    lam, za, zb, dphi = model(t0, m)
    ll = loglik(lam)
    active = np.ones(n_pix, bool)
    for _ in range(iterations):
        i00, i01, i11, s0, s1 = info_score(m, lam, za, zb, dphi)
        det = i00 * i11 - i01 * i01
        ok = active & (det > 0)
        st = np.where(ok, (i11 * s0 - i01 * s1) / np.where(det > 0, det, 1), 0.0)
        sm = np.where(ok, (i00 * s1 - i01 * s0) / np.where(det > 0, det, 1), 0.0)
        scale = np.ones(n_pix)
        for _ in range(8):  # halve the step where the likelihood does not improve
            nt, nm = t0 + scale * st, np.maximum(m + scale * sm, 1e-3 * floor)
            nlam, nza, nzb, ndp = model(nt, nm)
            nll = loglik(nlam)
            better = nll >= ll - 1e-12
            if better.all():
                break
            scale = np.where(better, scale, 0.5 * scale)
        t0, m = np.where(better, nt, t0), np.where(better, nm, m)
        lam, za, zb, dphi = model(t0, m)
        ll = loglik(lam)
        active &= np.abs(scale * st) > 1e-16
        with np.errstate(invalid="ignore", divide="ignore"):
            sd_t, sd_m = np.sqrt(i11 / det), np.sqrt(i00 / det)
        active &= ~(ok & (np.abs(scale * st) <= step_tol * sd_t)
                    & (np.abs(scale * sm) <= step_tol * sd_m))
        if not active.any():
            break
    i00, i01, i11, _, _ = info_score(m, lam, za, zb, dphi)
    det = i00 * i11 - i01 * i01
    sig = np.sqrt(np.where(det > 0, i11 / np.where(det > 0, det, 1), np.inf))
    return t0, sig, m, bg, peak


if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _ml_numba(counts_all, widths, centres, valid_all, cycles, t_start, peak, bg, k,
                  sigma_s, iterations, step_tol):
        n_pix, n = counts_all.shape
        nw = 2 * k + 1
        out_t = np.empty(n_pix)
        out_s = np.empty(n_pix)
        out_m = np.empty(n_pix)
        lo_e = np.empty(nw)
        hi_e = np.empty(nw)
        cnt = np.empty(nw)
        rr = np.empty(nw)
        ok = np.empty(nw, np.bool_)
        cum = np.empty(n)
        # the normal CDF at the window's edges, at the fit's time and at a trial's: what
        # the likelihood computed, the information at the same time reads again
        pa, pb, qa, qb = np.empty(nw), np.empty(nw), np.empty(nw), np.empty(nw)
        for p in range(n_pix):
            acc = 0.0
            # at-risk of the window's bins (up to its last: the sum runs in order)
            for j in range(min(max(peak[p] + k, 0), n - 1) + 1):
                cum[j] = cycles[p] - acc
                acc += counts_all[p, j]
            last = -1
            hw = 0.0
            wsum = 0.0
            for i in range(nw):
                j = min(max(peak[p] - k + i, 0), n - 1)
                lo_e[i] = centres[p, j] - 0.5 * widths[p, j]
                hi_e[i] = centres[p, j] + 0.5 * widths[p, j]
                cnt[i] = counts_all[p, j]
                rr[i] = max(cum[j], 0.0)
                ok[i] = valid_all[p, j] and j != last
                last = j
                if ok[i]:
                    hw += cnt[i]
                    wsum += hi_e[i] - lo_e[i]
            r0 = max(rr[0], hw + 1)
            floor = _M_FLOOR / max(cycles[p], 1.0)
            m = max(-math.log1p(-hw / r0) - bg[p] * wsum, floor)
            t0 = t_start[p]
            ll = _ml_ll(t0, m, bg[p], lo_e, hi_e, cnt, rr, ok, sigma_s, pa, pb)
            active = True
            for _ in range(iterations):
                if not active:
                    break
                i00, i01, i11, s0, s1 = _ml_info(t0, m, bg[p], lo_e, hi_e, cnt, rr, ok,
                                                 sigma_s, pa, pb)
                det = i00 * i11 - i01 * i01
                if det <= 0:
                    break
                st = (i11 * s0 - i01 * s1) / det
                sm = (i00 * s1 - i01 * s0) / det
                scale = 1.0
                better = False
                nt, nm, nll = t0, m, ll
                for _h in range(8):
                    nt = t0 + scale * st
                    nm = max(m + scale * sm, 1e-3 * floor)
                    nll = _ml_ll(nt, nm, bg[p], lo_e, hi_e, cnt, rr, ok, sigma_s, qa, qb)
                    if nll >= ll - 1e-12:
                        better = True
                        break
                    scale *= 0.5
                # where no step improves, or the step leaves the fit where it was, every
                # further iteration starts from the same point and does the same: stop
                if not better or (nt == t0 and nm == m):
                    break
                t0, m, ll = nt, nm, nll
                pa, qa, pb, qb = qa, pa, qb, pb
                if abs(scale * st) <= 1e-16:
                    active = False
                # a step within a small part of the fit's own sigmas (time and signal):
                # converged, what further steps add is far below the estimate's noise
                elif (abs(scale * st) <= step_tol * math.sqrt(i11 / det)
                      and abs(scale * sm) <= step_tol * math.sqrt(i00 / det)):
                    active = False
            i00, i01, i11, _, _ = _ml_info(t0, m, bg[p], lo_e, hi_e, cnt, rr, ok, sigma_s,
                                           pa, pb)
            det = i00 * i11 - i01 * i01
            out_t[p] = t0
            out_m[p] = m
            out_s[p] = math.sqrt(i11 / det) if det > 0 else np.inf
        return out_t, out_s, out_m, bg, peak

    @numba.njit(cache=True, nogil=True)
    def _ndtr(z):
        return 0.5 * math.erfc(-z / math.sqrt(2.0))

    @numba.njit(cache=True, nogil=True)
    def _ml_ll(t0, m, bg, lo_e, hi_e, cnt, rr, ok, sigma_s, pa, pb):
        """The log-likelihood at ``t0``, ``m``; the normal CDF at the bins' edges kept in
        ``pa``, ``pb`` (for :func:`_ml_info` at the same ``t0``)."""
        ll = 0.0
        shared = False  # bin i - 1 is fitted and ends where bin i starts: its upper CDF
        for i in range(lo_e.size):  # is bin i's lower one (the same number, not again)
            if not ok[i]:
                shared = False
                continue
            if shared and lo_e[i] == hi_e[i - 1]:
                pa[i] = pb[i - 1]
            else:
                pa[i] = _ndtr((lo_e[i] - t0) / sigma_s)
            pb[i] = _ndtr((hi_e[i] - t0) / sigma_s)
            shared = True
            dphi = pb[i] - pa[i]
            lam = max(m * dphi + bg * (hi_e[i] - lo_e[i]), 1e-300)
            ll += cnt[i] * math.log(-math.expm1(-lam)) - (rr[i] - cnt[i]) * lam
        return ll

    @numba.njit(cache=True, nogil=True)
    def _ml_info(t0, m, bg, lo_e, hi_e, cnt, rr, ok, sigma_s, pa, pb):
        """Information and score at ``t0``, ``m``, with ``pa``, ``pb`` from
        :func:`_ml_ll` at this ``t0``."""
        i00 = i01 = i11 = s0 = s1 = 0.0
        shared = False  # (as in _ml_ll: the density at a shared edge is computed once)
        eb = 0.0
        for i in range(lo_e.size):
            if not ok[i]:
                shared = False
                continue
            za = (lo_e[i] - t0) / sigma_s
            zb = (hi_e[i] - t0) / sigma_s
            dphi = pb[i] - pa[i]
            lam = max(m * dphi + bg * (hi_e[i] - lo_e[i]), 1e-200)
            em1 = math.expm1(lam)
            sl = cnt[i] / em1 - (rr[i] - cnt[i])
            il = rr[i] / em1
            ea = eb if shared and lo_e[i] == hi_e[i - 1] else math.exp(-0.5 * za * za)
            eb = math.exp(-0.5 * zb * zb)
            shared = True
            pdf = (eb - ea) / (SQRT2PI * sigma_s)
            jt = -m * pdf
            jm = dphi
            i00 += il * jt * jt
            i01 += il * jt * jm
            i11 += il * jm * jm
            s0 += sl * jt
            s1 += sl * jm
        return i00, i01, i11, s0, s1


