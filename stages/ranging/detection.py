"""Background, the strongest return's bin and its detection: the exact Poisson tail, the
threshold at false-alarm probability p_fa (the union bound over the valid bins) and the
bin the detection tests; the compiled tail beside its numpy form."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import betainc, gammainc

from stages.ranging._numba import numba
from stages.ranging.histograms import Histograms


def _background(lam, w, valid, at_risk):
    """Background intensity per second over the valid bins: a mean, then the mean again
    without the bins above it by 5 Poisson sigmas and a count (the returns). A median is biased on
    small counts and needs a sort per histogram."""
    vw = np.where(valid, w, 0.0)
    rate = np.where(valid, lam, 0.0).sum(1) / np.maximum(vw.sum(1), 1e-300)
    expect = rate[:, None] * w
    r = np.maximum(at_risk, 1.0)  # lambda ~ counts / at-risk
    # 5 Poisson sigmas and a count: at 0.001 counts a bin every bin that holds one is
    # 30 sigmas up, and leaving them all out set the background to 0 (every count a return)
    keep = valid & (lam <= expect + (5 * np.sqrt(expect * r) + 1) / r)
    return np.where(keep, lam, 0).sum(1) / np.maximum(np.where(keep, w, 0).sum(1), 1e-300)


def _peak_index(h: Histograms, lam, sigma_s):
    """The strongest return, and the matched-filter correlation of the corrected density.

    The peak is found on the excess counts over what background alone would put in each
    bin given the cycles still at risk: bins late in a heavily piled-up window (few cycles
    at risk) have a noisy corrected density but few counts, and must not win. Returns
    (peak index, density correlation, background rate).
    """
    from scipy.ndimage import correlate1d

    w, valid = h.widths, h.valid
    bg = _background(lam, w, valid, h.at_risk)
    width = max(1, int(round(3 * sigma_s / h.bin_s)))
    taps = np.arange(-width, width + 1)
    kern = np.exp(-0.5 * (taps * h.bin_s / sigma_s) ** 2)
    excess = np.where(valid, h.counts - h.at_risk * -np.expm1(-bg[:, None] * w), 0.0)
    score = np.where(valid, correlate1d(excess, kern, axis=1, mode="constant"), -np.inf)
    peak = np.argmax(score, axis=1)
    # (a dead code has zero width: no intensity density, not 0/0)
    dens = np.divide(lam, w, out=np.zeros_like(lam), where=w > 0)
    d = np.where(valid & (w > 0), dens - bg[:, None], 0.0)
    corr = np.where(valid, correlate1d(d, kern, axis=1, mode="constant"), -np.inf)
    return peak, corr, bg


#: where the union bound over the window positions is below this, the scan's p-value is
#: the union bound (the compiled form's shortcut; an upper bound all the same)
_SCAN_SURE = 1e-12

#: Above this many expected background counts the compiled Poisson tail is
#: Wilson-Hilferty's cube-root normal approximation (relative error ~1e-3 at 5 sigma from
#: 1e4 on, falling as 1/b); below it the exact series or continued fraction.
TAIL_EXACT_MAX = 1e4


def poisson_tail(c, b) -> np.ndarray:
    """P(X >= c) for X ~ Poisson(b), vectorised and stable for tiny values: the regularised
    lower incomplete gamma P(c, b) (``scipy.special.gammainc``); 1 for c <= 0, 0 for c >= 1
    at b = 0.

    >>> round(float(poisson_tail(4, 0.34)), 7)  # a bin of a background-only gate
    0.0004249
    """
    c = np.floor(np.asarray(c, np.float64))
    b = np.maximum(np.asarray(b, np.float64), 0.0)
    return np.where(c <= 0, 1.0, gammainc(np.maximum(c, 1.0), b))


def rise_p(cc, cp, bc, bp, lc, lp) -> np.ndarray:
    """The p-value of counts ``cc`` in a window of length ``lc`` after ``cp`` in one of
    length ``lp`` (bins or seconds), their backgrounds ``bc`` and ``bp``, under the null
    that the later window's signal a unit of time is no larger than the earlier's (a
    tail that decays): P(X >= cc), X binomial over cc + cp at the later window's largest
    share under the null (its length's or its background's share). Conditional on the
    sum, so the tail's unknown size does not enter. With no count after, 1."""
    cc, cp = np.asarray(cc, np.float64), np.maximum(np.asarray(cp, np.float64), 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        p0 = np.fmax(np.where(bc + bp > 0, bc / (bc + bp), 0.0),
                     np.where(lc + lp > 0, lc / (lc + lp), 1.0))
    return np.where(cc > 0, betainc(np.maximum(cc, 1e-300), cp + 1.0, p0), 1.0)


def detection_threshold(b, p_fa: float, n_bins) -> np.ndarray:
    """The count a bin must exceed to be a detection: the exact Poisson quantile, the
    smallest k with P(X > k) <= p_fa / n_bins for background alone (X ~ Poisson(b)), so
    that background alone crosses it in any of ``n_bins`` bins with probability <= p_fa
    (the union bound). Replaces eq. 2.46's Gaussian ``b + alpha_b sqrt(b) + 0.5``, which
    below ~1 count a bin lets through far more false alarms than p_fa (0.34 counts a bin,
    3000 bins, p_fa 1e-3: threshold 3.8, P(X >= 4) = 4.2e-4 a bin, 1.3 false alarms a
    histogram; here the threshold is 6). For reports; the estimators compare
    :func:`poisson_tail` of the count with p_fa / n_bins (the same decision).

    >>> detection_threshold([0.0, 0.34, 100.0], 1e-3, 3000).tolist()
    [0.0, 6.0, 153.0]
    """
    from scipy.stats import poisson

    q = p_fa / np.maximum(np.asarray(n_bins, np.float64), 1.0)
    b = np.maximum(np.asarray(b, np.float64), 0.0)
    return np.where(b > 0, poisson.isf(q, np.where(b > 0, b, 1.0)), 0.0)


def tested_bin(counts, valid, peak) -> np.ndarray:
    """The bin the detection tests: of the ``peak`` bin (the bin holding the estimate,
    :func:`bin_of`) and its two neighbours, the valid one with the most counts. The
    estimate can sit on a dead code (zero width, no count) with the return's counts on
    both sides: tested there alone, a return of 4 000 counts went undetected (chip zoo
    seed 326); the peak search's box centre can be bins away from a return in one bin
    (5 000 counts in one bin went undetected by fast and ml). Any bin's count against its
    own background tail at ``p_fa / n_bins`` keeps the false-alarm rate at ``p_fa``
    whichever bin is chosen (the union bound over the valid bins)."""
    counts, valid, peak = np.asarray(counts), np.asarray(valid, bool), np.asarray(peak)
    rows = np.arange(peak.size)[:, None]
    idx = np.clip(peak[:, None] + np.array([0, -1, 1])[None, :], 0, counts.shape[1] - 1)
    score = np.where(valid[rows, idx], counts[rows, idx].astype(np.float64), -1.0)
    return idx[rows[:, 0], np.argmax(score, axis=1)]  # ties: the peak's own bin first


def bin_of(edges_s, t_s, peak) -> np.ndarray:
    """The bin holding each time ``t_s`` (the last bin whose lower edge is <= t, clipped
    to the histogram), ``peak`` where t is not finite (the compiled fast kernel's
    ``_window_at`` finds the same bin)."""
    e = np.asarray(edges_s, np.float64)
    t = np.asarray(t_s, np.float64)
    n = e.shape[1] - 1
    if numba is not None and e.ndim == 2 and t.shape == e.shape[:1] and n >= 1:
        return _bin_count(np.ascontiguousarray(e), t,
                          np.broadcast_to(np.asarray(peak, np.int64), t.shape))
    with np.errstate(invalid="ignore"):
        cb = np.minimum((e[:, 1:n] <= t[:, None]).sum(axis=1), n - 1)
    return np.where(np.isfinite(t), cb, np.asarray(peak))


def _detection(counts, valid, at_risk, widths, peak, bg_rate, p_fa, exposure=None, scan=1):
    """eq. 2.44-2.48 at false-alarm probability p_fa with exact Poisson tails. With
    ``scan`` = k > 1 bins (the estimators' detection, :func:`scan_bins`): the most counts
    in a window of k bins holding the ``peak`` bin (the estimate's) or a neighbour, against
    the probability that background alone puts as many in any window of the gate
    (:func:`scan_pvalue`, the scan statistic's null). With k = 1: the tested bin's count
    (:func:`tested_bin`) against its background's tail at p_fa over the valid bins (the
    union bound; the further-return searches). The background is taken no lower than one
    count over the valid bins' ``exposure`` (cycle-seconds at risk): a histogram of one
    count has no other to estimate it from, and a rate of 0 called that count a return (6
    in 400 histograms of 0.001 counts a bin, at p_fa 0.05 when the tested bin was the
    estimate's)."""
    rows = np.arange(peak.size)
    if exposure is None and numba is not None and np.shape(valid) == np.shape(at_risk) == (
            np.shape(widths)) and np.ndim(widths) == 2 and np.shape(widths)[1]:
        exposure = _exposure(np.ascontiguousarray(at_risk, np.float64),
                             np.ascontiguousarray(widths, np.float64),
                             np.ascontiguousarray(valid, np.bool_))
    elif exposure is None:
        exposure = np.cumsum(np.where(valid, np.maximum(at_risk, 0.0) * widths, 0.0),
                             axis=1)[:, -1]
    rate = np.maximum(bg_rate, 1.0 / np.maximum(exposure, 1e-300))
    if scan > 1:
        return scan_pvalue(*_scan_stat(counts, valid, at_risk, widths, peak, rate,
                                       scan)) <= p_fa
    q = tested_bin(counts, valid, peak)
    b = np.maximum(at_risk[rows, q], 0.0) * -np.expm1(-rate * widths[rows, q])
    n_bins = np.maximum(np.asarray(valid).sum(axis=1), 1)
    return poisson_tail(counts[rows, q], b) <= p_fa / n_bins


def scan_bins(sigma_s: float, bin_s: float) -> int:
    """The detection window in bins: 3 sigma of the response (the width that maximises
    a Gaussian return's share over the square root of the background it holds is ~2.8
    sigma; 3 did best of 2-3.8 on the issue-34 grid, where the sub-bin phase spreads the
    peak), at least one bin."""
    return max(1, int(round(3.0 * sigma_s / bin_s))) if bin_s > 0 else 1


def _scan_stat(counts, valid, at_risk, widths, q, rate, k):
    """The statistic and its null's parameters, row by row: the most counts (of valid
    bins) in a window of ``k`` bins among the windows holding bin ``q`` or a neighbour
    (the first of equals); that window's background mean (its valid bins' cycles at risk
    times the probability of a background count: under pile-up the background late in
    the window is the at-risk cycles' share, and a window is tested against its own);
    the number of window positions."""
    counts = np.asarray(counts, np.float64)
    n_pix, n = counts.shape
    valid = np.asarray(valid, bool)
    k = min(k, n)
    zero = np.zeros((n_pix, 1))
    C = np.concatenate([zero, np.cumsum(np.where(valid, counts, 0.0), axis=1)], axis=1)
    rows = np.arange(n_pix)[:, None]
    s = np.clip(np.asarray(q)[:, None] + np.arange(-k, 2)[None, :], 0, n - k)
    sums = C[rows, s + k] - C[rows, s]
    best = s[rows[:, 0], np.argmax(sums, axis=1)]
    t = sums.max(axis=1)
    j = best[:, None] + np.arange(k)[None, :]
    b = np.maximum(at_risk[rows, j], 0.0) * -np.expm1(-rate[:, None] * widths[rows, j])
    mu = np.where(valid[rows, j], b, 0.0).sum(axis=1)
    n_valid = valid.sum(axis=1)
    m = np.maximum(np.minimum(n_valid + k - 1, n - k + 1), 1)
    return t, mu, k, m


def scan_threshold(mu: float, k: int, m: int, p_fa: float) -> int:
    """The least window count that :func:`scan_pvalue` calls a detection at ``p_fa`` (for
    reports and tests; the estimators compare the p-value itself).

    >>> scan_threshold(7 * 2 / 1024, 7, 1024, 1e-3)  # 2 background counts over 1 024 bins
    3
    """
    grid = np.arange(0, int(mu + 20 * math.sqrt(mu) + 60))
    p = scan_pvalue(grid, np.full(grid.size, mu), k, np.full(grid.size, m))
    return int(grid[np.argmax(p <= p_fa)])


def scan_pvalue(t, mu, k: int, m) -> np.ndarray:
    """An upper bound, tight when small, on the probability that background alone puts
    ``t`` or more counts in some window of ``k`` consecutive bins among ``m`` window
    positions, each bin Poisson(mu / k): the maximum reaches t only if the first window
    does or some window does while the one before it did not (an upcrossing), so
    P(max >= t) <= P(S >= t) + (m - 1) P(S_prev < t <= S), with S = A + X_in and
    S_prev = A + X_out, A ~ Poisson((k - 1) b) the bins they share, X ~ Poisson(b):
    P(S_prev < t <= S) = sum_a P(A = a) P(X <= t - 1 - a) P(X >= t - a). For k = 1 it is
    the union bound over the bins. The window's exact null distribution (no Gaussian or
    asymptotic form): at p_fa 1e-3 on 1 024 bins it is within a few per cent of the
    simulated rate (``tests/stages/test_ranging_scan.py``)."""
    from scipy.stats import poisson

    t = np.floor(np.asarray(t, np.float64))
    mu = np.maximum(np.asarray(mu, np.float64), 0.0)
    m = np.asarray(m, np.float64)
    b = mu / k
    first = poisson_tail(t, mu)
    # the terms a = t - 1 - d, d = 0 .. D: X's count up to d; beyond b + 12 sqrt(b) + 12
    # P(X >= d + 1) is below 1e-30 of the sum
    dmax = np.minimum(t - 1, np.ceil(b + 12 * np.sqrt(b) + 12))
    D = int(np.max(dmax, initial=0)) if t.size else 0
    d = np.arange(D + 1)[None, :]
    a = t[:, None] - 1 - d
    use = (d <= dmax[:, None]) & (a >= 0)
    pa = np.where(use, poisson.pmf(np.maximum(a, 0), (k - 1) * b[:, None]), 0.0)
    if k == 1:
        pa = np.where(use & (a == 0), 1.0, 0.0)
    up = (pa * poisson.cdf(d, b[:, None]) * poisson_tail(d + 1, b[:, None])).sum(axis=1)
    p = np.where(m * first <= _SCAN_SURE, m * first, first + np.maximum(m - 1, 0) * up)
    return np.where(t <= 0, 1.0, np.where(m <= 1, first, np.minimum(p, 1.0)))


#: the per-pixel estimators' background time profile (:func:`time_profile`): blocks of
#: this many bins, the z above the line through the blocks two away that makes a block a
#: return's, and the chi-square's p below which a batch's background is not flat (the
#: spatial estimator's block and p)
PROFILE_BLOCK = 32
PROFILE_Z = 3.1
PROFILE_P = 1e-4


def _block_sums(counts, edges_s, valid, edges):
    """Per row and block (``edges``: the blocks' first bins and the end): the valid
    counts, all counts and the valid bins' widths; None where the rows' bin edges are not
    all the same."""
    e = np.asarray(edges_s, np.float64)
    if not (e.strides[0] == 0 or (e == e[:1]).all()):
        return None
    valid = np.asarray(valid, bool)
    w = np.diff(e[0])
    whole = np.add.reduceat(counts, edges[:-1], axis=1)
    if valid.all():  # (generic histograms: one pass)
        return whole, whole, np.broadcast_to(np.add.reduceat(w, edges[:-1]), whole.shape)
    blk = np.add.reduceat(np.where(valid, counts, 0.0), edges[:-1], axis=1)
    wb = np.add.reduceat(np.where(valid, w[None, :], 0.0), edges[:-1], axis=1)
    return blk, whole, wb


def time_profile(h: Histograms, block: int = PROFILE_BLOCK, z: float = PROFILE_Z,
                 p: float = PROFILE_P) -> np.ndarray | None:
    """The background's time profile over a batch of rows that share one bin axis, a
    factor a bin (mean 1), or None where the batch's background is flat within its noise
    (or the rows' edges differ, or there are fewer than 6 blocks): the background expected
    in bin j is then the row's rate times width_j times s_j, not rate times width_j (a
    background that falls in time, pile-up of ambient light not corrected or an
    afterpulsing tail, made the early bins look like returns).

    Each row's valid counts in blocks of ``block`` bins against the block's exposure (its
    valid bins' widths times the cycles at risk at its middle); a block whose rate stands more than
    ``z`` sds above the line through the blocks two away on either side (at the ends,
    through the next two inside) is a return's and is left out of that row with the blocks
    beside it: a return is narrow, a background's profile is not (the rows have no
    neighbours here: the row's own blocks decide, where the spatial estimator's
    :func:`stages.ranging.spatial.background_profile` sums a 7 x 7 neighbourhood). The
    profile is each block's kept counts over those each row's rate would put there (three
    passes), interpolated linearly in time between the blocks' centres. A test of a trend
    decides: the kept counts' excess over each row's flat rate, weighted by the blocks'
    times, over its sd (normal; two-sided): flat at p >= ``p``. Not a chi-square over the
    blocks: faint returns at times spread over the batch, each too faint for its row's
    block test, raise the middle of the window, and at 2 signal and 2 background photons
    a row the chi-square called 3 000 such rows not flat (p ~ 1e-75) and their detection
    lost a third; a trend is what pile-up and afterpulsing make."""
    from scipy.special import ndtr

    counts = np.asarray(h.counts, np.float64)
    n_pix, n = counts.shape
    nb = n // block
    if n_pix == 0 or nb < 6:
        return None
    edges = np.arange(nb + 1) * block
    edges[-1] = n                                    # the last block takes the rest
    sums = _block_sums(counts, h.edges_s, h.valid, edges)
    if sums is None:
        return None
    blk, whole, wb = sums
    e = np.asarray(h.edges_s, np.float64)
    # the exposure: the valid bins' width times the cycles at risk at the block's start
    # less half its counts (the at-risk numbers bin by bin cost a (rows, bins) running
    # sum: 4x the fast estimator's time)
    before = np.cumsum(whole, axis=1) - 0.5 * whole
    expo = wb * np.maximum(np.asarray(h.cycles, np.float64)[:, None] - before, 0.0)
    keep = profile_keep(blk, expo, z)
    kept = np.where(keep, blk, 0.0)
    ke = np.where(keep, expo, 0.0)
    prof = profile_passes(kept, ke)
    rate0 = kept.sum(1) / np.maximum(ke.sum(1), 1e-300)
    expect = (ke * rate0[:, None]).sum(0)
    obs = kept.sum(0)
    ok = expect > 0
    if ok.sum() < 4:
        return None
    mid = 0.5 * (e[0, edges[:-1]] + e[0, edges[1:]])
    x = mid - (expect * mid).sum() / expect.sum()
    zt = float((obs - expect)[ok] @ x[ok]) / math.sqrt(float(expect[ok] @ x[ok] ** 2))
    if 2 * ndtr(-abs(zt)) >= p:
        return None
    return profile_per_bin(prof, mid, 0.5 * (e[0, :-1] + e[0, 1:]))


PROFILE_MIN_SHARE = 0.1  # a block kept where at least this share of the median's exposure


def profile_keep(blk, expo, z):
    """Blocks (..., blocks) of counts ``blk`` over exposures ``expo``: False where a block
    is a return's, or beside one. A return's block stands more than ``z`` sds above the line
    through the blocks two away on either side (at the ends, through the next two inside):
    a return is narrow, a background's profile is not (a linear one cancels; e^-3t's
    curvature over 4 blocks is a tenth of a block's count). Blocks without exposure are
    False too. For :func:`time_profile` (a row's own blocks) and the spatial estimator's
    :func:`stages.ranging.spatial.background_profile` (a 7 x 7 neighbourhood's)."""
    use = expo > 0
    E = np.where(use, expo, 1.0)
    rb, vb = np.where(use, blk / E, 0.0), np.where(use, blk / E ** 2, 0.0)
    line, var = np.empty_like(rb), np.empty_like(rb)
    line[..., 2:-2] = (rb[..., :-4] + rb[..., 4:]) / 2
    var[..., 2:-2] = (vb[..., :-4] + vb[..., 4:]) / 4
    for k in (0, 1):
        line[..., k] = 2 * rb[..., k + 2] - rb[..., k + 4]
        var[..., k] = 4 * vb[..., k + 2] + vb[..., k + 4]
        line[..., -1 - k] = 2 * rb[..., -3 - k] - rb[..., -5 - k]
        var[..., -1 - k] = 4 * vb[..., -3 - k] + vb[..., -5 - k]
    expect = np.maximum(line, 0.0) * E
    hit = use & ((blk - expect) / np.sqrt(np.maximum(expect, 1.0) + var * E ** 2) > z)
    pad = [(0, 0)] * (hit.ndim - 1)
    return use & ~(hit | np.pad(hit[..., 1:], pad + [(0, 1)])
                   | np.pad(hit[..., :-1], pad + [(1, 0)]))


def profile_passes(kept, ke, passes: int = 3):
    """The profile a block (mean about 1) from every row's (pixel's) kept counts ``kept``
    and kept exposures ``ke`` (..., blocks): each block's kept counts over those that each
    row's own rate would put there, the rates and the profile estimated in turn; NaN
    where the block's kept exposure is under ``PROFILE_MIN_SHARE`` of the median
    block's."""
    nb = kept.shape[-1]
    kept2, ke2 = kept.reshape(-1, nb), ke.reshape(-1, nb)
    prof = np.ones(nb)
    for _ in range(passes):
        rate = kept2.sum(1) / np.maximum((ke2 * prof).sum(1), 1e-300)
        unit = (ke2 * rate[:, None]).sum(0)
        prof = np.where(unit > 0, kept2.sum(0) / np.maximum(unit, 1e-300), prof)
    # a block that (nearly) every row left out, a return at one time in all of them,
    # says nothing: NaN, and the blocks either side of it give its profile
    # (profile_per_bin). From the few rows that kept it, a wall at one depth in every
    # pixel of a frame (an outside probe's fence under e^-3t) gave 2x the truth there
    # and 0.07x beside it, and surfaces 26-48 cm behind the wall
    expo = ke2.sum(0)
    return np.where(expo >= PROFILE_MIN_SHARE * np.median(expo), prof, np.nan)


def profile_per_bin(prof, mid, centres):
    """A profile a block, at the blocks' middles ``mid``, a bin (at ``centres``): linear
    in between (over a NaN block, from the blocks either side), at least 1e-3 of its
    largest, mean 1."""
    ok = np.isfinite(prof)
    if ok.sum() < 2:
        return np.ones(len(centres))
    sj = np.interp(centres, np.asarray(mid)[ok], np.maximum(prof[ok], 0.0))
    sj = np.maximum(sj, 1e-3 * sj.max()) if sj.max() > 0 else np.ones(len(centres))
    return sj / sj.mean()


def _detect(h: Histograms, peak, bg_rate, p_fa, t_s=None, sigma_s=None, compiled=None,
            profile="auto"):
    """:func:`_detection` of a :class:`Histograms` at the bin holding the estimate ``t_s``
    (the ``peak`` where it is not finite, or not given: the least-squares fit's time can
    be pulled sigmas off by an empty code, its box's peak is not); over windows of
    :func:`scan_bins` bins when ``sigma_s`` is given (compiled where numba is: one pass a
    row, no (pixels, bins) arrays). Where the batch's background is not flat in time
    (:func:`time_profile`, computed when ``profile`` is "auto"; None: flat), the
    background expected in bin j is the row's rate times width_j times s_j, the rate
    estimated (:func:`_background`) on those weighted widths, not ``bg_rate``."""
    at = peak if t_s is None else bin_of(h.edges_s, t_s, peak)
    k = 1 if sigma_s is None else scan_bins(sigma_s, h.bin_s)
    if isinstance(profile, str):
        profile = time_profile(h)
    if profile is not None:
        ws = h.widths * profile[None, :]
        bg = _background(h.lam, ws, h.valid, h.at_risk)
        return _detection(h.counts, h.valid, h.at_risk, ws, at, bg, p_fa, scan=k)
    compiled = (numba is not None) if compiled is None else compiled
    if k > 1 and compiled:
        det = _scan_detect(np.ascontiguousarray(h.counts, np.float64),
                           np.ascontiguousarray(h.edges_s, np.float64),
                           np.ascontiguousarray(h.valid, np.bool_),
                           np.ascontiguousarray(h.cycles, np.float64),
                           np.asarray(at, np.int64), np.asarray(bg_rate, np.float64),
                           k, float(p_fa))
    else:
        det = _detection(h.counts, h.valid, h.at_risk, h.widths, at, bg_rate, p_fa, scan=k)
    # (an estimate on masked bins is tested on the valid bins of its windows only: the
    # single-bin test took a masked bin's counts, the reset peak's or a found return's,
    # and a further return searched beside a masked one was "detected" in 22 % of rows)
    return det


if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _poisson_tail(c, b):
        """:func:`poisson_tail` compiled: P(a, b) by its series where b < a + 1, else
        1 - Q(a, b) by Lentz's continued fraction (Numerical Recipes' gser and gcf; both
        converge in ~3 sqrt(b) terms or fewer), Wilson-Hilferty beyond TAIL_EXACT_MAX."""
        a = math.floor(c)
        if a <= 0.0:
            return 1.0
        if b <= 0.0:
            return 0.0
        if b > TAIL_EXACT_MAX:
            # P(X >= a) = P(chi2_{2a} <= 2b): the cube-root normal approximation
            z = (math.pow(b / a, 1.0 / 3.0) - 1.0 + 1.0 / (9.0 * a)) * 3.0 * math.sqrt(a)
            return 0.5 * math.erfc(-z / math.sqrt(2.0))
        front = math.exp(-b + a * math.log(b) - math.lgamma(a))
        if b < a + 1.0:
            ap = a
            term = 1.0 / a
            total = term
            for _ in range(100_000):
                ap += 1.0
                term *= b / ap
                total += term
                if term < total * 1e-16:
                    break
            return min(total * front, 1.0)
        tiny = 1e-300
        bb = b + 1.0 - a
        cc = 1.0 / tiny
        d = 1.0 / bb
        h = d
        for i in range(1, 100_000):
            an = -i * (i - a)
            bb += 2.0
            d = an * d + bb
            if abs(d) < tiny:
                d = tiny
            cc = bb + an / cc
            if abs(cc) < tiny:
                cc = tiny
            d = 1.0 / d
            delta = d * cc
            h *= delta
            if abs(delta - 1.0) < 1e-16:
                break
        return max(1.0 - front * h, 0.0)

    @numba.njit(cache=True, nogil=True)
    def _bin_count(e, t, peak):
        """:func:`bin_of` a row at a time: the count of inner edges at or below t (the
        same count, without the (n_pix, n_bins) comparison array)."""
        n = e.shape[1] - 1
        out = np.empty(t.size, np.int64)
        for p in range(t.size):
            if not math.isfinite(t[p]):
                out[p] = peak[p]
                continue
            c = 0
            for j in range(1, n):
                if e[p, j] <= t[p]:
                    c += 1
            out[p] = min(c, n - 1)
        return out

    @numba.njit(cache=True, nogil=True)
    def _exposure(at_risk, widths, valid):
        """The valid bins' cycle-seconds at risk, a row at a time: numpy's running sum's
        last element (the same additions in the same order)."""
        n_pix, n = at_risk.shape
        out = np.empty(n_pix)
        for p in range(n_pix):
            acc = 0.0
            for j in range(n):
                r = at_risk[p, j]
                x = ((r if not r < 0.0 else 0.0) * widths[p, j]) if valid[p, j] else 0.0
                acc = x if j == 0 else acc + x
            out[p] = acc
        return out

    @numba.njit(cache=True, nogil=True)
    def _scan_p(t, mu, k, m):
        """:func:`scan_pvalue` of one row (its twin, tested equal)."""
        t = math.floor(t)
        if t <= 0.0:
            return 1.0
        b = mu / k
        first = _poisson_tail(t, mu)
        if m <= 1.0 or first >= 1.0:
            return min(first, 1.0)
        if m * first <= _SCAN_SURE:
            # (the upcrossings' term is at most (m - 1) P(S >= t): far below, the union
            # bound decides, and a strong return costs no sum)
            return m * first
        dmax = int(min(t - 1.0, math.ceil(b + 12.0 * math.sqrt(b) + 12.0)))
        mua = (k - 1) * b
        px = np.empty(dmax + 2)        # P(X = j), j = 0 .. dmax + 1
        for j in range(dmax + 2):
            px[j] = (math.exp(-b + j * math.log(b) - math.lgamma(j + 1.0)) if b > 0.0
                     else (1.0 if j == 0 else 0.0))
        sf = _poisson_tail(dmax + 1.0, b)  # P(X >= dmax + 1), then down by the pmf
        terms = np.empty(dmax + 1)
        for d in range(dmax, -1, -1):
            terms[d] = sf                  # P(X >= d + 1)
            sf += px[d]
        up = 0.0
        cdf = 0.0
        for d in range(dmax + 1):
            cdf += px[d]
            a = t - 1.0 - d
            if mua > 0.0:
                pa = math.exp(-mua + a * math.log(mua) - math.lgamma(a + 1.0))
            else:
                pa = 1.0 if a == 0.0 else 0.0
            up += pa * min(cdf, 1.0) * terms[d]
        return min(first + (m - 1.0) * up, 1.0)

    @numba.njit(cache=True, nogil=True)
    def _scan_detect(counts, edges, valid, cycles, q, bg_rate, k, p_fa):
        """:func:`_detection` with ``scan`` = k, a row at a time (one pass for the valid
        counts' running sum, the cycles at risk and the exposure; tested equal)."""
        n_pix, n = counts.shape
        k = min(k, n)
        out = np.empty(n_pix, np.bool_)
        C = np.empty(n + 1)
        r = np.empty(n)
        for p in range(n_pix):
            acc = 0.0
            expo = 0.0
            cs = 0.0
            nv = 0
            C[0] = 0.0
            for j in range(n):
                rj = cycles[p] - acc
                r[j] = rj
                c = counts[p, j]
                acc += c
                if valid[p, j]:
                    expo += max(rj, 0.0) * (edges[p, j + 1] - edges[p, j])
                    nv += 1
                    cs += c
                C[j + 1] = cs
            rate = max(bg_rate[p], 1.0 / max(expo, 1e-300))
            qp = q[p]
            t = -1.0
            best = 0
            for s in range(max(qp - k, 0), min(qp + 1, n - k) + 1):
                if C[s + k] - C[s] > t:
                    t = C[s + k] - C[s]
                    best = s
            mu = 0.0
            for j in range(best, best + k):
                if valid[p, j]:
                    mu += max(r[j], 0.0) * -math.expm1(-rate * (edges[p, j + 1] - edges[p, j]))
            m = max(min(nv + k - 1, n - k + 1), 1)
            out[p] = _scan_p(t, mu, k, float(m)) <= p_fa
        return out
