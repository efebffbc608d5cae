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

from dataclasses import dataclass
from functools import cached_property

import numpy as np
from scipy.special import ndtr

from stages.models.performance import alpha_b

SQRT2PI = np.sqrt(2 * np.pi)
FWHM_PER_SIGMA = 2 * np.sqrt(2 * np.log(2))
ESTIMATORS = ("centroid", "matched", "gaussfit", "ml")


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
        return float(np.median(self.widths[:, :: max(1, self.widths.shape[1] // 16)]))

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
    without the bins above it by 5 Poisson sigmas (the returns). A median is biased on
    small counts and needs a sort per histogram."""
    vw = np.where(valid, w, 0.0)
    rate = np.where(valid, lam, 0.0).sum(1) / np.maximum(vw.sum(1), 1e-300)
    expect = rate[:, None] * w
    noise = np.sqrt(expect / np.maximum(at_risk, 1.0))  # lambda ~ counts / at-risk
    keep = valid & (lam <= expect + 5 * noise)
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
    d = np.where(valid, lam / w - bg[:, None], 0.0)
    corr = np.where(valid, correlate1d(d, kern, axis=1, mode="constant"), -np.inf)
    return peak, corr, bg


def _detect(h: Histograms, peak, bg_rate, p_fa):
    """eq. 2.44-2.48 at false-alarm probability p_fa: the peak bin's count against the
    largest count background alone would give over the valid bins."""
    rows = np.arange(peak.size)
    r = h.at_risk[rows, peak]
    b = r * -np.expm1(-bg_rate * h.widths[rows, peak])
    n_bins = np.maximum(h.valid.sum(axis=1), 2)
    a_b = alpha_b(1 - p_fa, n_bins)
    return h.counts[rows, peak] > b + a_b * np.sqrt(np.maximum(b, 1e-12)) + 0.5


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
    t = np.interp(frac, [-1, 0, 1], [0, 0, 0]) + cen[rows, peak] + frac * w[rows, peak]
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


def ml(h: Histograms, sigma_s: float, p_fa: float = 1e-3, iterations: int = 30,
       half_width_sigma: float = 8.0):
    """Poisson maximum likelihood of signal + background with pile-up (the exact binomial
    factorisation, see the module docstring), by Fisher scoring with step halving.

    The signal (arrival time, detections per cycle) is fitted in a window of
    ``half_width_sigma`` around the matched filter's peak; the flat background comes from
    the whole histogram (the robust median of the Coates-corrected density), which is where
    its information is. sigma from the expected information.
    """
    start = matched(h, sigma_s, p_fa)
    w_all = h.widths
    n = w_all.shape[1]
    width = max(3, int(np.ceil(half_width_sigma * sigma_s / h.bin_s)))
    peak = np.argmin(np.abs(h.centres - start.t_s[:, None]), axis=1)
    idx = np.clip(peak[:, None] + np.arange(-width, width + 1)[None, :], 0, n - 1)
    rows = np.arange(peak.size)[:, None]
    # the background: the mean corrected density outside the window (a median of small
    # Poisson counts is biased), over bins with enough cycles at risk to be measured
    outside = h.valid & (np.abs(np.arange(n)[None, :] - peak[:, None]) > width) & (
        h.at_risk > 20)
    lam0 = h.intensity()
    bg = np.where(outside, lam0, 0).sum(1) / np.maximum(np.where(outside, w_all, 0).sum(1),
                                                         1e-300)
    lo_e, hi_e = h.edges_s[rows, idx], h.edges_s[rows, idx + 1]
    w = hi_e - lo_e
    counts, r = h.counts[rows, idx], np.maximum(h.at_risk[rows, idx], 0.0)
    # the window's bins, each once: clipped indices at the histogram's ends repeat a bin
    first = np.concatenate([np.ones((idx.shape[0], 1), bool), np.diff(idx, axis=1) > 0], 1)
    valid = h.valid[rows, idx] & first
    t0 = start.t_s.copy()
    # start from the window's detection probability: robust at any pile-up
    hw = np.where(valid, counts, 0).sum(1)
    r0 = np.maximum(r[:, 0], hw + 1)
    m = np.maximum(-np.log1p(-hw / r0) - bg * w.sum(1), 1e-9)
    bgw = bg[:, None] * w

    def model(t0, m):
        za = (lo_e - t0[:, None]) / sigma_s
        zb = (hi_e - t0[:, None]) / sigma_s
        dphi = ndtr(zb) - ndtr(za)
        return m[:, None] * dphi + bgw, za, zb, dphi

    def loglik(lam):
        lam = np.maximum(lam, 1e-300)
        return np.where(valid, counts * np.log(-np.expm1(-lam)) - (r - counts) * lam,
                        0.0).sum(1)

    def jacobian(m, za, zb, dphi):
        pdf = (np.exp(-0.5 * zb * zb) - np.exp(-0.5 * za * za)) / (SQRT2PI * sigma_s)
        return np.stack([-m[:, None] * pdf, dphi], axis=-1)        # (n, bins, 2)

    lam, za, zb, dphi = model(t0, m)
    ll = loglik(lam)
    active = np.ones(t0.size, bool)
    for _ in range(iterations):
        lam_c = np.maximum(lam, 1e-300)
        score_l = counts / np.expm1(lam_c) - (r - counts)
        info_l = np.where(valid, r / np.expm1(lam_c), 0.0)
        jac = jacobian(m, za, zb, dphi)
        score = np.where(valid[..., None], score_l[..., None] * jac, 0).sum(1)
        info = np.einsum("nb,nbi,nbj->nij", info_l, jac, jac) + np.eye(2)[None] * 1e-30
        step = np.linalg.solve(info, score[..., None])[..., 0]
        step[~active] = 0.0
        scale = np.ones(t0.size)
        for _ in range(8):  # halve the step where the likelihood does not improve
            nt, nm = t0 + scale * step[:, 0], np.maximum(m + scale * step[:, 1], 1e-12)
            nlam, nza, nzb, ndp = model(nt, nm)
            nll = loglik(nlam)
            better = nll >= ll - 1e-12
            if better.all():
                break
            scale = np.where(better, scale, scale / 2)
        t0, m = np.where(better, nt, t0), np.where(better, nm, m)
        lam, za, zb, dphi = model(t0, m)
        ll = loglik(lam)
        active &= np.abs(scale * step[:, 0]) > 1e-16
        if not active.any():
            break
    info_l = np.where(valid, r / np.expm1(np.maximum(lam, 1e-300)), 0.0)
    info = np.einsum("nb,nbi,nbj->nij", info_l, *(2 * [jacobian(m, za, zb, dphi)]))
    with np.errstate(invalid="ignore"):
        sig = np.sqrt(np.maximum(np.linalg.pinv(info)[:, 0, 0], 0.0))
    return Estimate(t0, sig, np.full(t0.size, FWHM_PER_SIGMA * sigma_s), m * h.cycles,
                    bg * h.bin_s * h.cycles, start.detected, "ml")


ESTIMATOR_FUNCS = {"centroid": centroid, "matched": matched, "gaussfit": gaussfit, "ml": ml}


def estimate(h: Histograms, sigma_s: float, estimator: str = "ml", p_fa: float = 1e-3):
    """Run one estimator by name (see :data:`ESTIMATORS`)."""
    if estimator not in ESTIMATOR_FUNCS:
        raise ValueError(f"estimator must be one of {ESTIMATORS}, found {estimator!r}")
    return ESTIMATOR_FUNCS[estimator](h, sigma_s, p_fa)
