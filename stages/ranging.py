"""Range estimation from first-photon histograms: centroid (eq. 2.10), matched filter,
the thesis's Gaussian fit (the baseline), and a Poisson maximum likelihood with pile-up.

Histograms arrive in code order; with reversed timing the first photon is the highest code,
so everything here works in arrival order (codes reversed) on the time axis the calibration
gives (bin edges from the INL and LSB).

Pile-up without approximation: going through the bins in arrival order, a cycle whose TDC
has not started yet is "at risk"; bin j's hits are Binomial(R_j, 1 - exp(-lambda_j)) given
the R_j cycles at risk, where lambda_j is the undistorted intensity (signal Gaussian plus
flat background). The likelihood of a first-photon histogram factorises into these
binomials exactly, so the ML estimator fits the undistorted model and is unbiased at any
M; the same step (``lambda = -log(1 - h / R)``, Coates) corrects the histogram for the fast
estimators.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.special import gammainc, ndtr

from stages.models.tcspc import FWHM_PER_SIGMA, SQRT2PI

ESTIMATORS = ("fast", "centroid", "matched", "gaussfit", "ml")


@dataclass(frozen=True)
class Histograms:
    """First-photon histograms in arrival order on a calibrated time axis.

    ``counts`` (n_pix, n_bins) hits; ``edges_s`` (n_pix, n_bins + 1) arrival times of the
    bin edges after the window opened (increasing); ``cycles`` (n_pix,); ``valid``
    (n_pix, n_bins) bins that may hold a return (reset peak, window edges and codes outside
    the gate masked). Masked bins still count in the at-risk numbers.
    """

    counts: np.ndarray
    edges_s: np.ndarray
    cycles: np.ndarray
    valid: np.ndarray

    @classmethod
    def from_codes(cls, hits: np.ndarray, tau_edges_s: np.ndarray, cycles, window_s: float,
                   x_t=None, margin: int = 6, gate_codes: tuple[int, int] | None = None):
        """From D1st histograms (code order) and per-code tau edges (n_pix, n_codes + 1).

        Codes from ``x_t - margin`` up (the reset peak and beyond the window), code 0 (the
        window's end, where the TDC jitter piles up) and codes outside ``gate_codes`` are
        masked.
        """
        hits = np.asarray(hits, np.float64)
        n_pix, n_codes = hits.shape
        k = np.arange(n_codes)[None, :]
        valid = np.broadcast_to(k >= 1, hits.shape).copy()
        if x_t is not None:
            valid &= k < np.floor(np.asarray(x_t))[:, None] - margin
        if gate_codes is not None:
            valid &= (k >= gate_codes[0]) & (k <= gate_codes[1])
        edges = window_s - np.asarray(tau_edges_s)[:, ::-1]
        return cls(hits[:, ::-1], edges, np.asarray(cycles, np.float64), valid[:, ::-1])

    @cached_property
    def at_risk(self) -> np.ndarray:
        before = np.cumsum(self.counts, axis=1) - self.counts
        return self.cycles[:, None] - before

    @cached_property
    def widths(self) -> np.ndarray:
        return np.diff(self.edges_s, axis=1)

    @cached_property
    def bin_s(self) -> float:
        """A typical bin width (the median over a sample of bins: the LSB)."""
        w = self.widths[:, :: max(1, self.widths.shape[1] // 16)]
        return float(np.nanmedian(w)) if np.isfinite(w).any() else 1.0

    @cached_property
    def centres(self) -> np.ndarray:
        return 0.5 * (self.edges_s[:, 1:] + self.edges_s[:, :-1])

    def intensity(self) -> np.ndarray:
        """Coates-corrected expected detections per bin per cycle (undistorted)."""
        r = np.maximum(self.at_risk, 1.0)
        return -np.log1p(-np.minimum(self.counts / r, 1 - 1e-12))


@dataclass(frozen=True)
class Estimate:
    """Per-pixel results in arrival time after the window opened."""

    t_s: np.ndarray
    sigma_s: np.ndarray
    fwhm_s: np.ndarray
    signal_counts: np.ndarray
    background_per_bin: np.ndarray
    detected: np.ndarray
    estimator: str


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
    """The bin the detection tests: of the peak's bin and its two neighbours, the valid
    one with the most counts. An estimator's peak is the centre of its box, which can be
    a dead code (zero width, no count) with the return's counts on both sides: tested
    there, a return of 4 000 counts went undetected (chip zoo seed 326). Any bin's count
    against its own background tail at ``p_fa / n_bins`` keeps the false-alarm rate at
    ``p_fa`` whichever bin is chosen (the union bound over the valid bins)."""
    counts, valid, peak = np.asarray(counts), np.asarray(valid, bool), np.asarray(peak)
    rows = np.arange(peak.size)[:, None]
    idx = np.clip(peak[:, None] + np.array([0, -1, 1])[None, :], 0, counts.shape[1] - 1)
    score = np.where(valid[rows, idx], counts[rows, idx].astype(np.float64), -1.0)
    return idx[rows[:, 0], np.argmax(score, axis=1)]  # ties: the peak's own bin first


def _detection(counts, valid, at_risk, widths, peak, bg_rate, p_fa):
    """eq. 2.44-2.48 at false-alarm probability p_fa with the exact Poisson tail: the peak
    bin's count (:func:`tested_bin`) against what background alone (its expected count b
    in that bin, pile-up included) exceeds in any of the valid bins with probability p_fa
    (:func:`detection_threshold`). The compiled fast kernel has its twin inline."""
    rows = np.arange(peak.size)
    q = tested_bin(counts, valid, peak)
    b = np.maximum(at_risk[rows, q], 0.0) * -np.expm1(-bg_rate * widths[rows, q])
    n_bins = np.maximum(np.asarray(valid).sum(axis=1), 1)
    return poisson_tail(counts[rows, q], b) <= p_fa / n_bins


def _detect(h: Histograms, peak, bg_rate, p_fa):
    """:func:`_detection` of a :class:`Histograms`."""
    return _detection(h.counts, h.valid, h.at_risk, h.widths, peak, bg_rate, p_fa)


def centroid(h: Histograms, sigma_s: float, p_fa: float = 1e-3, n_hw: int | None = None):
    """eq. 2.10 on the raw histogram: the background-subtracted centroid around the peak."""
    lam, w = h.intensity(), h.widths
    peak, _, bg = _peak_index(h, lam, sigma_s)
    n_hw = n_hw or max(1, int(round(1.5 * sigma_s / h.bin_s)))
    idx = np.clip(peak[:, None] + np.arange(-n_hw, n_hw + 1)[None, :], 0, w.shape[1] - 1)
    rows = np.arange(peak.size)[:, None]
    r = h.at_risk[rows, idx]
    b = r * -np.expm1(-bg[:, None] * w[rows, idx])
    s = np.clip(h.counts[rows, idx] - b, 0, None)
    tot = s.sum(1)
    t = (s * h.centres[rows, idx]).sum(1) / np.maximum(tot, 1e-300)
    var = (s * (h.centres[rows, idx] - t[:, None]) ** 2).sum(1) / np.maximum(tot, 1e-300)
    sig = np.sqrt(np.maximum(var, sigma_s ** 2 / 4) / np.maximum(tot, 1.0))
    return Estimate(t, sig, np.full(t.size, FWHM_PER_SIGMA * sigma_s), tot,
                    bg * h.bin_s * h.cycles, _detect(h, peak, bg, p_fa), "centroid")


def matched(h: Histograms, sigma_s: float, p_fa: float = 1e-3):
    """Matched filter on the pile-up-corrected density, parabolic sub-bin interpolation."""
    lam, w = h.intensity(), h.widths
    peak, corr, bg = _peak_index(h, lam, sigma_s)
    rows = np.arange(peak.size)
    n = corr.shape[1]
    near = np.clip(peak[:, None] + np.arange(-2, 3)[None, :], 0, n - 1)
    peak = near[rows, np.argmax(corr[rows[:, None], near], axis=1)]
    c0 = corr[rows, peak]
    cm = np.where(peak > 0, corr[rows, np.maximum(peak - 1, 0)], c0)
    cp = np.where(peak < n - 1, corr[rows, np.minimum(peak + 1, n - 1)], c0)
    cm, cp = np.where(np.isfinite(cm), cm, c0), np.where(np.isfinite(cp), cp, c0)
    den = cm - 2 * c0 + cp
    frac = np.where(den < 0, 0.5 * (cm - cp) / np.where(den < 0, den, -1), 0.0)
    frac = np.clip(frac, -0.5, 0.5)
    cen = h.centres
    t = cen[rows, peak] + frac * w[rows, peak]
    win = np.abs(np.arange(n)[None, :] - peak[:, None]) <= max(1, int(3 * sigma_s / h.bin_s))
    sig_counts = np.where(win & h.valid, lam - bg[:, None] * w, 0).sum(1) * h.cycles
    sig = sigma_s / np.sqrt(np.maximum(sig_counts, 1.0))
    return Estimate(t, sig, np.full(t.size, FWHM_PER_SIGMA * sigma_s), sig_counts,
                    bg * h.bin_s * h.cycles, _detect(h, peak, bg, p_fa), "matched")


def gaussfit(h: Histograms, sigma_s: float, p_fa: float = 1e-3):
    """The thesis's baseline (section 5.2): a Gaussian plus constant fitted by least squares
    to the raw histogram around its peak, one pixel at a time (scipy's curve_fit)."""
    import warnings

    from scipy.optimize import OptimizeWarning, curve_fit

    lam, w = h.intensity(), h.widths
    peak, _, bg = _peak_index(h, lam, sigma_s)
    n_hw = max(4, int(round(4 * sigma_s / h.bin_s)))
    out = np.full((peak.size, 3), np.nan)
    for i, p in enumerate(peak):  # the baseline loops per pixel, as the thesis's MATLAB did
        lo, hi = max(p - n_hw, 0), min(p + n_hw + 1, w.shape[1])
        x, y = h.centres[i, lo:hi], h.counts[i, lo:hi]
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", OptimizeWarning)  # a degenerate fit: fall back
                popt, pcov = curve_fit(
                    lambda t, a, mu, s, c: a * np.exp(-0.5 * ((t - mu) / s) ** 2) + c, x, y,
                    p0=(max(y.max() - np.median(y), 1.0), h.centres[i, p], sigma_s,
                        np.median(y)),
                    sigma=np.sqrt(np.maximum(y, 1.0)), maxfev=2000)
            out[i] = popt[1], np.sqrt(max(pcov[1, 1], 0.0)), abs(popt[2])
        except (RuntimeError, ValueError, OptimizeWarning):
            out[i] = h.centres[i, p], sigma_s, sigma_s
    sig_counts = np.full(peak.size, np.nan)
    return Estimate(out[:, 0], out[:, 1], FWHM_PER_SIGMA * out[:, 2], sig_counts,
                    bg * h.bin_s * h.cycles, _detect(h, peak, bg, p_fa), "gaussfit")


def _ml_setup(h: Histograms, sigma_s: float, half_width_sigma: float, compiled: bool):
    """What both ML paths start from: the fast estimator's peak, background and time."""
    fargs, _ = _fast_args(h, sigma_s, 1e-3)
    t_start, peak, _, bg, _, _ = (_fast_numba if compiled else _fast_numpy)(*fargs)
    counts, edges, valid, cycles = fargs[:4]
    args = (counts, np.ascontiguousarray(h.widths), np.ascontiguousarray(h.centres), valid,
            cycles, t_start, peak, bg)
    k = max(3, int(np.ceil(half_width_sigma * sigma_s / h.bin_s)))
    return args, k


def ml(h: Histograms, sigma_s: float, p_fa: float = 1e-3, iterations: int = 30,
       half_width_sigma: float = 8.0, compiled: bool | None = None):
    """Poisson maximum likelihood of signal + background with pile-up (the exact binomial
    factorisation, see the module docstring), by Fisher scoring with step halving.

    The signal (arrival time, detections per cycle) is fitted in a window of
    ``half_width_sigma`` around the fast estimator's peak, starting from its time; the
    flat background is its constant-hazard estimate away from the peak. sigma from the
    expected information. Compiled where numba is installed; the numpy path runs the same
    iterations (tested to agree).
    """
    compiled = (numba is not None) if compiled is None else compiled
    args, k = _ml_setup(h, sigma_s, half_width_sigma, compiled)
    if compiled:
        t0, sig, m, bg, peak = _ml_numba(*args, k, sigma_s, iterations)
    else:
        t0, sig, m, bg, peak = _ml_numpy(*args, k, sigma_s, iterations)
    return Estimate(t0, sig, np.full(t0.size, FWHM_PER_SIGMA * sigma_s), m * h.cycles,
                    bg * h.bin_s * h.cycles, _detect(h, peak, bg, p_fa), "ml")


def _ml_numpy(counts_all, widths, centres, valid_all, cycles, t_start, peak, bg, k, sigma_s,
              iterations):
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
    m = np.maximum(-np.log1p(-hw / r0) - bg * np.where(valid, w, 0).sum(1), 1e-9)
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
        lam_c = np.maximum(lam, 1e-300)
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
            nt, nm = t0 + scale * st, np.maximum(m + scale * sm, 1e-12)
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
        if not active.any():
            break
    i00, i01, i11, _, _ = info_score(m, lam, za, zb, dphi)
    det = i00 * i11 - i01 * i01
    sig = np.sqrt(np.where(det > 0, i11 / np.where(det > 0, det, 1), np.inf))
    return t0, sig, m, bg, peak


# ----------------------------------------------------------------------- the fast one

# The Gaussian's CDF and density for the scoring steps: a table every 1/32 sigma over
# +-9 sigma of the third-order Taylor polynomials in d = z - z0 about each entry z0
# (|d| <= 1/64: error ~2e-9), eight coefficients to an entry (one cache line): two
# Horner evaluations an edge, a tenth of the cost of erfc and exp.
_Z_MAX, _Z_PER = 9.0, 32


def _coefficients() -> np.ndarray:
    z0 = np.arange(-_Z_MAX * _Z_PER, _Z_MAX * _Z_PER + 1) / _Z_PER
    c0, f, q = ndtr(z0), np.exp(-0.5 * z0 ** 2) / SQRT2PI, z0 * z0 - 1.0
    tab = np.stack([c0, f, -0.5 * f * z0, f * q / 6.0,                      # Phi
                    f, -f * z0, 0.5 * f * q, -f * (z0 * q - 2.0 * z0) / 6.0], 1)  # phi
    tab.flags.writeable = False
    return np.ascontiguousarray(tab)


_CDF_PDF_TAB = _coefficients()


def _cdf_pdf_numpy(z):
    """Phi(z) and phi(z) from the table (the compiled ``_cdf_pdf``'s twin)."""
    zc = np.minimum(np.maximum(z, -_Z_MAX), _Z_MAX)
    i = ((zc + _Z_MAX) * _Z_PER + 0.5).astype(np.int64)  # >= 0: truncation is floor
    d = zc - (i / _Z_PER - _Z_MAX)
    a = _CDF_PDF_TAB[i]
    a = np.moveaxis(a, -1, 0)
    return (a[0] + d * (a[1] + d * (a[2] + d * a[3])),
            a[4] + d * (a[5] + d * (a[6] + d * a[7])))
#: Fisher-scoring steps after the centroid, at most; a pixel stops once a step moves its
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
            1.0 / sigma_s, steps, sigma_s), bin_s


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


def _fast_numpy(counts, edges, valid, cycles, kb, kc, p_fa, kw, inv_s, steps, step_cap):
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
    det = _detection(counts, valid, r, widths, peak, bg, p_fa)
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
    m = np.maximum((-np.log1p(-hits / r0) - bg * w_in) / np.maximum(share, 0.5), 1e-9)
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
        m = np.where(active, np.minimum(np.maximum(np.maximum(m + sm, 0.5 * m), 1e-9), 2.0 * m),
                     m)
        ast = np.abs(st)
        settled = (ast < _CONVERGED * sig) | (ast * (ast + sig) * inv_s < _RESIDUAL * sig)
        active &= ~(settled & (np.abs(sm) < _CONVERGED * m))
        if not active.any():
            break
    return t, m, sig


try:
    import numba
except ImportError:  # pragma: no cover
    numba = None

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

    @numba.njit(cache=True, nogil=True, inline="always")
    def _cdf_pdf(z):
        zc = min(max(z, -_Z_MAX), _Z_MAX)
        i = int((zc + _Z_MAX) * _Z_PER + 0.5)
        d = zc - (i / _Z_PER - _Z_MAX)
        a = _CDF_PDF_TAB
        return (a[i, 0] + d * (a[i, 1] + d * (a[i, 2] + d * a[i, 3])),
                a[i, 4] + d * (a[i, 5] + d * (a[i, 6] + d * a[i, 7])))

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
    def _fast_numba(counts, edges, valid, cycles, kb, kc, p_fa, kw, inv_s, steps, step_cap):
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
            m = max((-math.log1p(-hits / r0) - bg * w_in) / max(share, 0.5), 1e-9)
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
                m = min(max(m + sm, 0.5 * m, 1e-9), 2.0 * m)  # at most a factor 2 a step
                ast = abs(st)
                settled = (ast < _CONVERGED * sig
                           or ast * (ast + sig) * inv_s < _RESIDUAL * sig)
                if settled and abs(sm) < _CONVERGED * m:
                    break
            t_out[p] = t
            sig_out[p] = sig
            q = peak  # tested_bin: the valid bin of most counts of peak - 1 .. peak + 1
            for j in (peak - 1, peak + 1):
                if 0 <= j < n and valid[p, j] and (not valid[p, q]
                                                   or counts[p, j] > counts[p, q]):
                    q = j
            b = max(r[q], 0.0) * -np.expm1(-bg * (edges[p, q + 1] - edges[p, q]))
            det_out[p] = _poisson_tail(counts[p, q], b) <= p_fa / max(nv, 1)
            tot_out[p] = m
            bg_out[p] = bg
            peak_out[p] = peak
        return t_out, peak_out, tot_out, bg_out, det_out, sig_out


if numba is not None:
    @numba.njit(cache=True, nogil=True)
    def _ml_numba(counts_all, widths, centres, valid_all, cycles, t_start, peak, bg, k,
                  sigma_s, iterations):
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
        for p in range(n_pix):
            acc = 0.0
            # at-risk of the window's bins
            cum = np.empty(n)
            for j in range(n):
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
            m = max(-math.log1p(-hw / r0) - bg[p] * wsum, 1e-9)
            t0 = t_start[p]
            ll = _ml_ll(t0, m, bg[p], lo_e, hi_e, cnt, rr, ok, sigma_s)
            active = True
            for _ in range(iterations):
                if not active:
                    break
                i00, i01, i11, s0, s1 = _ml_info(t0, m, bg[p], lo_e, hi_e, cnt, rr, ok,
                                                 sigma_s)
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
                    nm = max(m + scale * sm, 1e-12)
                    nll = _ml_ll(nt, nm, bg[p], lo_e, hi_e, cnt, rr, ok, sigma_s)
                    if nll >= ll - 1e-12:
                        better = True
                        break
                    scale *= 0.5
                if better:
                    t0, m, ll = nt, nm, nll
                if abs(scale * st) <= 1e-16:
                    active = False
            i00, i01, i11, _, _ = _ml_info(t0, m, bg[p], lo_e, hi_e, cnt, rr, ok, sigma_s)
            det = i00 * i11 - i01 * i01
            out_t[p] = t0
            out_m[p] = m
            out_s[p] = math.sqrt(i11 / det) if det > 0 else np.inf
        return out_t, out_s, out_m, bg, peak

    @numba.njit(cache=True, nogil=True)
    def _ndtr(z):
        return 0.5 * math.erfc(-z / math.sqrt(2.0))

    @numba.njit(cache=True, nogil=True)
    def _ml_ll(t0, m, bg, lo_e, hi_e, cnt, rr, ok, sigma_s):
        ll = 0.0
        for i in range(lo_e.size):
            if not ok[i]:
                continue
            dphi = _ndtr((hi_e[i] - t0) / sigma_s) - _ndtr((lo_e[i] - t0) / sigma_s)
            lam = max(m * dphi + bg * (hi_e[i] - lo_e[i]), 1e-300)
            ll += cnt[i] * math.log(-math.expm1(-lam)) - (rr[i] - cnt[i]) * lam
        return ll

    @numba.njit(cache=True, nogil=True)
    def _ml_info(t0, m, bg, lo_e, hi_e, cnt, rr, ok, sigma_s):
        i00 = i01 = i11 = s0 = s1 = 0.0
        for i in range(lo_e.size):
            if not ok[i]:
                continue
            za = (lo_e[i] - t0) / sigma_s
            zb = (hi_e[i] - t0) / sigma_s
            dphi = _ndtr(zb) - _ndtr(za)
            lam = max(m * dphi + bg * (hi_e[i] - lo_e[i]), 1e-300)
            em1 = math.expm1(lam)
            sl = cnt[i] / em1 - (rr[i] - cnt[i])
            il = rr[i] / em1
            pdf = (math.exp(-0.5 * zb * zb) - math.exp(-0.5 * za * za)) / (SQRT2PI * sigma_s)
            jt = -m * pdf
            jm = dphi
            i00 += il * jt * jt
            i01 += il * jt * jm
            i11 += il * jm * jm
            s0 += sl * jt
            s1 += sl * jm
        return i00, i01, i11, s0, s1


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
    t, _, m, bg, det, sig = (_fast_numba if compiled else _fast_numpy)(*args)
    return Estimate(t, sig, np.full(t.size, FWHM_PER_SIGMA * sigma_s), m * h.cycles,
                    bg * bin_s * h.cycles, det, "fast")


ESTIMATOR_FUNCS = {"centroid": centroid, "matched": matched, "gaussfit": gaussfit, "ml": ml,
                   "fast": fast}


def estimate(h: Histograms, sigma_s: float, estimator: str = "ml", p_fa: float = 1e-3):
    """Run one estimator by name (see :data:`ESTIMATORS`)."""
    if estimator not in ESTIMATOR_FUNCS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, found {estimator!r}")
    return ESTIMATOR_FUNCS[estimator](h, sigma_s, p_fa)
