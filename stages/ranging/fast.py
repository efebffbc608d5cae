"""The fast estimator: two passes per histogram, a centroid, then a few Fisher-scoring
steps of the exact likelihood; the compiled kernel beside its numpy twin."""

from __future__ import annotations

import math

import numpy as np

from stages.models.tcspc import FWHM_PER_SIGMA
from stages.ranging._numba import numba
from stages.ranging.detection import _detect, _detection, bin_of, scan_bins, time_profile
from stages.ranging.gauss_table import _cdf_pdf_numpy
from stages.ranging.histograms import Estimate, Histograms
from stages.ranging.validation import validated

if numba is not None:
    from stages.ranging.detection import _poisson_tail, _scan_p
    from stages.ranging.gauss_table import _cdf_pdf


#: strength by less than _CONVERGED of itself and its time either by less than _CONVERGED
#: of its sigma or by so little against the pulse that what it leaves is below _RESIDUAL
#: of its sigma: a step st from a start off by about st leaves ~st^2 / sigma_pulse (the
#: model's curvature) plus ~st sigma / sigma_pulse (scoring's expected information is
#: not the observed one, off by ~1 / sqrt(counts) ~ sigma / sigma_pulse). With many
#: counts sigma is a picosecond, the centroid's start several, and the second step that
#: the first rule asked for moved the estimate by a small fraction of sigma.
#: In photon-starving light one step does; at M = 5 the centroid of the piled-up peak is
#: a poor start and 2-4 are needed.
SCORING_STEPS = 6
#: the least signal a fit keeps, in counts over the cycles (a thousandth of a count: a
#: floor of 1e-9 a cycle was 1 000x the row's counts where a file gives no cycles and
#: its stand-in is 1e12 x the row's total, issue 34.3)
_M_FLOOR = 1e-3
_CONVERGED = 0.5
_RESIDUAL = 0.2


def _fast_params(bin_s: float, sigma_s: float) -> tuple[int, int, int]:
    """Half-widths in bins: the peak search's box (1.5 sigma), the centroid's (2 sigma)
    and the scoring steps' window (3 sigma)."""
    return (max(1, int(round(1.5 * sigma_s / bin_s))),
            max(1, int(round(2.0 * sigma_s / bin_s))),
            max(2, int(math.ceil(3.0 * sigma_s / bin_s))))


def _fast_args(h: Histograms, sigma_s: float, p_fa: float, steps: int = SCORING_STEPS):
    """The fast kernel's arguments (shared by ``fast`` and the ML's start)."""
    if not (np.isfinite(sigma_s) and sigma_s > 0):
        raise ValueError(f"sigma_s (the instrument response) must be positive and finite, "
                         f"found {sigma_s}")
    counts = np.ascontiguousarray(h.counts, np.float64)
    edges = np.ascontiguousarray(h.edges_s, np.float64)
    n = counts.shape[1]
    sample = edges[:: max(1, edges.shape[0] // 15)]
    # a typical bin (the LSB): the middle of <= 16 rows' spans; a dead TDC's NaN axis is
    # not one (np.nanmedian costs as much as the kernel's work on 10 histograms). Sorted
    # in Python: numpy sorts with AVX-512, and on this VM's Xeon the core then ran the
    # kernel that follows ~8 % slower (the wider units' clock penalty; measured).
    spans = sorted(x for x in (sample[:, -1] - sample[:, 0]).tolist() if math.isfinite(x))
    k = len(spans)
    bin_s = 0.5 * (spans[(k - 1) // 2] + spans[k // 2]) / n if k else 1.0  # the median
    kb, kc, kw = _fast_params(bin_s, sigma_s)
    return (counts, edges, np.ascontiguousarray(h.valid),
            np.ascontiguousarray(h.cycles, np.float64), kb, kc, float(p_fa), kw,
            1.0 / sigma_s, steps, sigma_s, scan_bins(sigma_s, bin_s)), bin_s


def _coarse_to_fine_numpy(S):
    """The compiled ``_coarse_to_fine``'s twin, on rows: the first largest of every second
    box, then the better of its two neighbours if one beats it (the lower on a tie)."""
    rows = np.arange(S.shape[0])
    n = S.shape[1]
    m = 2 * np.argmax(S[:, ::2], axis=1)
    best, bv = m.copy(), S[rows, m]
    left = np.where(m > 0, S[rows, np.maximum(m - 1, 0)], -np.inf)
    take = (m > 0) & (left >= bv)
    best, bv = np.where(take, m - 1, best), np.where(take, left, bv)
    right = np.where(m + 1 < n, S[rows, np.minimum(m + 1, n - 1)], -np.inf)
    return np.where((m + 1 < n) & (right > bv), m + 1, best)


def _fast_numpy(counts, edges, valid, cycles, kb, kc, p_fa, kw, inv_s, steps, step_cap,
                scan=1):
    """The fast estimator on whole arrays (the compiled kernel's twin, tested equal)."""
    n_pix, n = counts.shape
    rows = np.arange(n_pix)
    widths = np.diff(edges, axis=1)
    before = np.cumsum(counts, axis=1) - counts
    r = cycles[:, None] - before                       # cycles still at risk at each bin
    v = valid.astype(np.float64)
    zero = np.zeros((n_pix, 1))
    C = np.concatenate([zero, np.cumsum(counts * v, axis=1)], axis=1)
    RW = np.concatenate([zero, np.cumsum(np.maximum(r, 0.0) * widths * v, axis=1)], axis=1)
    bg0 = C[:, -1] / np.maximum(RW[:, -1], 1e-300)
    j = np.arange(n)
    lo, hi = np.clip(j - kb, 0, n), np.clip(j + kb + 1, 0, n)
    box = np.where(valid, (C[:, hi] - C[:, lo]) - bg0[:, None] * (RW[:, hi] - RW[:, lo]),
                   -np.inf)
    peak = _coarse_to_fine_numpy(box)
    flo, fhi = np.clip(peak - 4 * kc, 0, n), np.clip(peak + 4 * kc + 1, 0, n)
    num = C[:, -1] - (C[rows, fhi] - C[rows, flo])
    den = RW[:, -1] - (RW[rows, fhi] - RW[rows, flo])
    bg = num / np.maximum(den, 1e-300)
    win = np.clip(peak[:, None] + np.arange(-kc, kc + 1)[None, :], 0, n - 1)
    first = np.concatenate([np.ones((n_pix, 1), bool), np.diff(win, axis=1) > 0], axis=1)
    R = rows[:, None]
    ok = valid[R, win] & first
    rr = np.maximum(r[R, win], 1.0)
    lam = -np.log1p(-np.minimum(counts[R, win] / rr, 1 - 1e-12))
    e = np.where(ok, np.maximum(lam - bg[:, None] * widths[R, win], 0.0), 0.0)
    centres = 0.5 * (edges[R, win] + edges[R, win + 1])
    tot = e.sum(1)
    t = np.where(tot > 0, (e * centres).sum(1) / np.maximum(tot, 1e-300),
                 0.5 * (edges[rows, peak] + edges[rows, peak + 1]))
    t, m, sig = _score_steps_numpy(counts, edges, valid, r, C, peak, bg, t, kw, inv_s, steps,
                                   step_cap)
    det = _detection(counts, valid, r, widths, bin_of(edges, t, peak), bg, p_fa, RW[:, -1],
                     scan)
    return t, peak, m, bg, det, sig


def _score_steps_numpy(counts, edges, valid, r, C, peak, bg, t, kw, inv_s, steps, step_cap):
    """The compiled kernel's Fisher-scoring steps on whole arrays (its twin, tested equal):
    (t, m) of the exact likelihood in +-kw bins around the bin holding t, a pixel stopping
    once its step has settled (:data:`SCORING_STEPS`) or its information is singular; sigma
    from the information at the last step's start."""
    n_pix, n = counts.shape
    R = np.arange(n_pix)[:, None]
    rows = R[:, 0]
    taps = np.arange(-kw, kw + 1)[None, :]

    def window(t):
        cb = np.minimum((edges[:, 1:n] <= t[:, None]).sum(1), n - 1)
        win = np.clip(cb[:, None] + taps, 0, n - 1)
        first = np.concatenate([np.ones((n_pix, 1), bool), np.diff(win, axis=1) > 0], 1)
        return cb, win, valid[R, win] & first

    def ndtr_(z):
        return _cdf_pdf_numpy(z)[0]

    cb, win, ok = window(t)
    lo, hi = np.maximum(cb - kw, 0), np.minimum(cb + kw + 1, n)
    hits = C[rows, hi] - C[rows, lo]
    w_in = np.where(ok, edges[R, win + 1] - edges[R, win], 0.0).sum(1)
    r0 = np.maximum(r[rows, lo], hits + 1.0)
    share = ndtr_((edges[rows, hi] - t) * inv_s) - ndtr_((edges[rows, lo] - t) * inv_s)
    floor = _M_FLOOR / np.maximum(r[:, 0], 1.0)  # (the cycles)
    m = np.maximum((-np.log1p(-hits / r0) - bg * w_in) / np.maximum(share, 0.5), floor)
    sig = np.full(n_pix, np.inf)
    active = np.ones(n_pix, bool)
    for step in range(steps):
        if step > 0:
            cb, win, ok = window(t)
        e_lo, e_hi = edges[R, win], edges[R, win + 1]
        cnt, rr = counts[R, win], np.maximum(r[R, win], 0.0)
        (ca, ga), (cb_, gb) = (_cdf_pdf_numpy((e_lo - t[:, None]) * inv_s),
                               _cdf_pdf_numpy((e_hi - t[:, None]) * inv_s))
        dphi = cb_ - ca
        lam = np.maximum(m[:, None] * dphi + bg[:, None] * (e_hi - e_lo), 1e-300)
        inv = 1.0 / np.expm1(lam)
        sl = np.where(ok, cnt * inv - (rr - cnt), 0.0)
        il = np.where(ok, rr * inv, 0.0)
        jt = -m[:, None] * (gb - ga) * inv_s
        i00, i01, i11 = (il * jt * jt).sum(1), (il * jt * dphi).sum(1), (il * dphi * dphi).sum(1)
        s0, s1 = (sl * jt).sum(1), (sl * dphi).sum(1)
        det = i00 * i11 - i01 * i01
        active &= det > 0
        d = np.where(active, det, 1.0)
        sig = np.where(active, np.sqrt(np.abs(i11 / d)), sig)
        st = np.clip((i11 * s0 - i01 * s1) / d, -step_cap, step_cap)
        sm = (i00 * s1 - i01 * s0) / d
        t = np.where(active, t + st, t)
        m = np.where(active, np.minimum(np.maximum(np.maximum(m + sm, 0.5 * m), floor), 2.0 * m),
                     m)
        ast = np.abs(st)
        settled = (ast < _CONVERGED * sig) | (ast * (ast + sig) * inv_s < _RESIDUAL * sig)
        active &= ~(settled & (np.abs(sm) < _CONVERGED * m))
        if not active.any():
            break
    return t, m, sig


if numba is not None:
    @numba.njit(cache=True, nogil=True, inline="always")
    def _window_at(edges_row, cb, t, kw):
        """The bin holding ``t`` (walking from ``cb``) and the +-kw window around it."""
        n = edges_row.size - 1
        while cb > 0 and edges_row[cb] > t:
            cb -= 1
        while cb < n - 1 and edges_row[cb + 1] <= t:
            cb += 1
        return cb, max(cb - kw, 0), min(cb + kw + 1, n)

    @numba.njit(cache=True, nogil=True, inline="always")
    def _first_max(S):
        """The first index of the largest S (0 when all are -inf or NaN): the maximum over
        eight independent lanes (one running maximum waits on each compare; numba does not
        vectorise it), then the first block of eight that holds it, then its place there
        (np.argmax's rule on ties)."""
        n = S.size
        b0 = b1 = b2 = b3 = b4 = b5 = b6 = b7 = -np.inf
        n8 = n - n % 8
        for j in range(0, n8, 8):
            b0 = max(b0, S[j])
            b1 = max(b1, S[j + 1])
            b2 = max(b2, S[j + 2])
            b3 = max(b3, S[j + 3])
            b4 = max(b4, S[j + 4])
            b5 = max(b5, S[j + 5])
            b6 = max(b6, S[j + 6])
            b7 = max(b7, S[j + 7])
        for j in range(n8, n):
            b0 = max(b0, S[j])
        b = max(max(max(b0, b1), max(b2, b3)), max(max(b4, b5), max(b6, b7)))
        if not b > -np.inf:
            return 0
        j0 = n8
        for j in range(0, n8, 8):
            if ((S[j] == b) | (S[j + 1] == b) | (S[j + 2] == b) | (S[j + 3] == b)
                    | (S[j + 4] == b) | (S[j + 5] == b) | (S[j + 6] == b) | (S[j + 7] == b)):
                j0 = j
                break
        for j in range(j0, n):
            if S[j] == b:
                return j
        return 0

    @numba.njit(cache=True, nogil=True, inline="always")
    def _coarse_to_fine(S):
        """Coarse to fine: the first largest of every second box (a box is 3 sigma wide:
        neighbours share 4 of its 5 bins and differ little), then the better of its two
        neighbours if one beats it (the lower on a tie). Half the maximum's work; the
        peak only seeds the centroid and the window, which then follow the estimate."""
        n = S.size
        m = 2 * _first_max(S[::2])
        best, bv = m, S[m]
        if m > 0 and S[m - 1] >= bv:
            best, bv = m - 1, S[m - 1]
        if m + 1 < n and S[m + 1] > bv:
            best = m + 1
        return best

    @numba.njit(cache=True, nogil=True)
    def _fast_numba(counts, edges, valid, cycles, kb, kc, p_fa, kw, inv_s, steps, step_cap,
                    scan=1):
        """Two passes per histogram: prefix sums (at-risk cycles, valid counts and
        cycle-seconds at risk), then the boxed excess's maximum; everything else comes from
        the prefix sums or the window around the peak (the centroid in +-2 sigma, then
        ``steps`` Fisher-scoring steps of the exact likelihood in +-``kw`` bins, the
        Gaussian's CDF and density computed once per bin edge)."""
        n_pix, n = counts.shape
        t_out = np.empty(n_pix)
        sig_out = np.empty(n_pix)
        tot_out = np.empty(n_pix)
        bg_out = np.empty(n_pix)
        det_out = np.empty(n_pix, np.bool_)
        peak_out = np.empty(n_pix, np.int64)
        C = np.empty(n + 1)
        RW = np.empty(n + 1)
        r = np.empty(n)
        S = np.empty(n)
        # the box [j - kb, j + kb] away from the histogram's ends, as slices indexed from 0
        # (numba checks a computed index like C[j + w] for wrap-around, which stops the
        # loop from vectorising)
        w = 2 * kb + 1
        nb = max(n - w + 1, 0)
        C_hi, C_lo, RW_hi, RW_lo, S_in = C[w:w + nb], C[:nb], RW[w:w + nb], RW[:nb], S[kb:kb + nb]
        C1, RW1 = C[1:], RW[1:]
        for p in range(n_pix):
            crow, erow, vrow = counts[p], edges[p], valid[p]
            erow1 = erow[1:]
            v_in = vrow[kb:kb + nb]
            nv = 0
            acc = 0.0
            cs = 0.0
            rws = 0.0
            C[0] = 0.0
            RW[0] = 0.0
            cyc = cycles[p]
            for j in range(n):  # running sums in registers (not re-read from the arrays)
                c = crow[j]
                rj = cyc - acc
                r[j] = rj
                acc += c
                nv += vrow[j]
                if vrow[j]:  # masks change in a few places: a predicted branch
                    cs += c
                    rws += max(rj, 0.0) * (erow1[j] - erow[j])
                C1[j] = cs
                RW1[j] = rws
            bg0 = cs / max(rws, 1e-300)
            # the boxed excess over the constant-hazard background, vectorised
            for j in range(nb):  # an invalid centre is no candidate
                S_in[j] = ((C_hi[j] - C_lo[j]) - bg0 * (RW_hi[j] - RW_lo[j])
                           if v_in[j] else -np.inf)
            for j in range(min(kb, n)):  # the box clamped at either end
                hi = min(j + kb + 1, n)
                S[j] = C[hi] - bg0 * RW[hi] if vrow[j] else -np.inf
                jj = n - 1 - j
                lo = max(jj - kb, 0)
                S[jj] = (C[n] - C[lo]) - bg0 * (RW[n] - RW[lo]) if vrow[jj] else -np.inf
            peak = _coarse_to_fine(S)
            flo = max(peak - 4 * kc, 0)
            fhi = min(peak + 4 * kc + 1, n)
            bg = (C[n] - (C[fhi] - C[flo])) / max(RW[n] - (RW[fhi] - RW[flo]), 1e-300)
            tot = 0.0
            mom = 0.0
            last = -1
            for i in range(-kc, kc + 1):
                j = min(max(peak + i, 0), n - 1)
                if j == last or not valid[p, j]:
                    last = j
                    continue
                last = j
                c = counts[p, j]
                # an empty bin's intensity is 0 (no log1p: most bins when photons are few)
                lam = -math.log1p(-min(c / max(r[j], 1.0), 1 - 1e-12)) if c > 0 else 0.0
                e = max(lam - bg * (edges[p, j + 1] - edges[p, j]), 0.0)
                tot += e
                mom += e * 0.5 * (edges[p, j] + edges[p, j + 1])
            if tot > 0:
                t = mom / tot
            else:
                t = 0.5 * (edges[p, peak] + edges[p, peak + 1])
            sig = np.inf
            # the window follows the estimate (under pile-up the counts peak early)
            cb, lo, hi = _window_at(edges[p], peak, t, kw)
            # strength: the share of the cycles at risk at the window's start that fire
            # in it, less the background's, over the window's share of the pulse (robust
            # under pile-up, unlike the Coates sum)
            hits = C[hi] - C[lo]
            w_in = 0.0
            for j in range(lo, hi):
                if valid[p, j]:
                    w_in += edges[p, j + 1] - edges[p, j]
            r0 = max(r[lo], hits + 1.0)
            share = (_cdf_pdf((edges[p, hi] - t) * inv_s)[0]
                     - _cdf_pdf((edges[p, lo] - t) * inv_s)[0])
            floor = _M_FLOOR / max(cyc, 1.0)
            m = max((-math.log1p(-hits / r0) - bg * w_in) / max(share, 0.5), floor)
            for _s in range(steps):
                if _s > 0:  # re-centre on the new estimate
                    cb, lo, hi = _window_at(edges[p], cb, t, kw)
                i00 = i01 = i11 = s0 = s1 = 0.0
                cp, gp = _cdf_pdf((edges[p, lo] - t) * inv_s)
                for j in range(lo, hi):
                    c, g = _cdf_pdf((edges[p, j + 1] - t) * inv_s)
                    if valid[p, j]:
                        dphi = c - cp
                        lam = max(m * dphi + bg * (edges[p, j + 1] - edges[p, j]), 1e-300)
                        inv = 1.0 / math.expm1(lam)
                        rj = max(r[j], 0.0)
                        sl = counts[p, j] * inv - (rj - counts[p, j])
                        il = rj * inv
                        jt = -m * (g - gp) * inv_s
                        i00 += il * jt * jt
                        i01 += il * jt * dphi
                        i11 += il * dphi * dphi
                        s0 += sl * jt
                        s1 += sl * dphi
                    cp = c
                    gp = g
                det = i00 * i11 - i01 * i01
                if not det > 0:
                    break
                sig = math.sqrt(i11 / det)
                st = min(max((i11 * s0 - i01 * s1) / det, -step_cap), step_cap)
                sm = (i00 * s1 - i01 * s0) / det
                t += st
                m = min(max(m + sm, 0.5 * m, floor), 2.0 * m)  # at most a factor 2 a step
                ast = abs(st)
                settled = (ast < _CONVERGED * sig
                           or ast * (ast + sig) * inv_s < _RESIDUAL * sig)
                if settled and abs(sm) < _CONVERGED * m:
                    break
            t_out[p] = t
            sig_out[p] = sig
            q = _window_at(edges[p], cb, t, kw)[0] if math.isfinite(t) else peak
            bgd = max(bg, 1.0 / max(RW[n], 1e-300))  # _detection's floor: one count
            if scan > 1:  # _scan_detect's test, from this kernel's running sums
                k = min(scan, n)
                best = 0
                top = -1.0
                for s in range(max(q - k, 0), min(q + 1, n - k) + 1):
                    if C[s + k] - C[s] > top:
                        top = C[s + k] - C[s]
                        best = s
                mu = 0.0
                for j in range(best, best + k):
                    if valid[p, j]:
                        mu += max(r[j], 0.0) * -math.expm1(-bgd * (edges[p, j + 1]
                                                                 - edges[p, j]))
                mpos = max(min(nv + k - 1, n - k + 1), 1)
                det_out[p] = _scan_p(top, mu, k, float(mpos)) <= p_fa
            else:  # tested_bin: the valid bin of most counts of the estimate's bin and
                # its neighbours
                for j in (q - 1, q + 1):
                    if 0 <= j < n and valid[p, j] and (not valid[p, q]
                                                       or counts[p, j] > counts[p, q]):
                        q = j
                b = max(r[q], 0.0) * -np.expm1(-bgd * (edges[p, q + 1] - edges[p, q]))
                det_out[p] = _poisson_tail(counts[p, q], b) <= p_fa / max(nv, 1)
            tot_out[p] = m
            bg_out[p] = bg
            peak_out[p] = peak
        return t_out, peak_out, tot_out, bg_out, det_out, sig_out



@validated
def fast(h: Histograms, sigma_s: float, p_fa: float = 1e-3, compiled: bool | None = None):
    """The fastest estimator: two passes per histogram, then work only in the peak window.

    Background as a constant hazard (hits over cycle-seconds at risk, re-estimated away
    from the peak); the peak where the excess counts over it, boxed over +-1.5 sigma, are
    largest; a start at the centroid of the pile-up-corrected excess within +-2 sigma; then
    :data:`SCORING_STEPS` Fisher-scoring steps of the exact first-photon likelihood (the
    module docstring) for time and strength in +-3 sigma, the one-step-estimator idea: from
    a consistent start, Newton steps reach the ML's efficiency without iterating to
    convergence. sigma from the Fisher information. Detection by eq. 2.44-2.48 as for the
    others. Compiled where numba is installed; the numpy path computes the same thing
    (tested). Touches nothing per bin but the counts, the edges and the mask (no derived
    arrays), which is what makes it fast.
    """
    compiled = (numba is not None) if compiled is None else compiled
    args, bin_s = _fast_args(h, sigma_s, p_fa)
    t, peak, m, bg, det, sig = (_fast_numba if compiled else _fast_numpy)(*args)
    profile = time_profile(h)
    if profile is not None:  # a background not flat in time: the test on its profile
        det = _detect(h, peak, bg, p_fa, t, sigma_s, profile=profile)
    return Estimate(t, sig, np.full(t.size, FWHM_PER_SIGMA * sigma_s), m * h.cycles,
                    bg * bin_s * h.cycles, det, "fast")


