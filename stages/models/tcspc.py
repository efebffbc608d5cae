"""The TCSPC process: first-photon histograms with pile-up, and the precision they allow.

Time runs from the window's opening (t = 0) to its close (t = window_s), in arrival order;
the TDC's reversed codes (early photons high) are a relabelling done by the callers. The
detector is sensitive from ``-reset_s``: a photon in ``[-reset_s, 0)`` fires the SPAD during
its reset period and starts the TDC at the window's beginning (the reset peak, thesis
section 2.2.3). Only the first detection of a cycle counts.

With signal detections per cycle ``M`` (PDE included) in a Gaussian of width ``sigma_s``
(eq. 2.18) at ``tof_s``, and background detections at ``bg_rate_hz``, the cumulative
intensity from the start of sensitivity is (eq. 2.17)

    L(t) = M * [Phi((t - tof)/sigma) - Phi((-reset - tof)/sigma)] + bg_rate * (t + reset)

and the first detection falls in ``[a, b)`` with probability ``exp(-L(a)) - exp(-L(b))``
(the exact bin integral of eq. 2.12). Everything is computed in log space with
``log_ndtr`` on the tail that keeps precision, so bins 40 sigma into a tail and cycles where
``exp(-L)`` underflows stay finite and non-negative.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import erf, log_ndtr, ndtr

SQRT2PI = np.sqrt(2 * np.pi)
FWHM_PER_SIGMA = 2 * np.sqrt(2 * np.log(2))


def sigma_from_fwhm(fwhm):
    """Standard deviation of a Gaussian of the given FWHM."""
    return np.asarray(fwhm, np.float64) / FWHM_PER_SIGMA


def combined_sigma(*sigmas):
    """Total jitter of independent Gaussian contributions, eq. 2.18.

    >>> round(float(combined_sigma(sigma_from_fwhm(44.8e-12), 178.2e-12) * 1e12), 1)
    179.2
    """
    return np.sqrt(sum(np.asarray(s, np.float64) ** 2 for s in sigmas))


def log_phi_interval(za, zb):
    """log(Phi(zb) - Phi(za)) for za <= zb, accurate in both tails.

    On the upper side the difference of CDFs near 1 is taken as a difference of survival
    functions, so nothing cancels.

    >>> round(float(log_phi_interval(40.0, 41.0)), 2)  # exp() of it underflows; the log does not
    -804.61
    """
    za, zb = np.broadcast_arrays(np.asarray(za, np.float64), np.asarray(zb, np.float64))
    upper = za > 0
    big = np.where(upper, log_ndtr(-za), log_ndtr(zb))
    small = np.where(upper, log_ndtr(-zb), log_ndtr(za))
    with np.errstate(divide="ignore", invalid="ignore"):
        return big + np.log1p(-np.exp(small - big))


def log_phi_intervals(z):
    """log(Phi(z[k + 1]) - Phi(z[k])) for every k, ``z`` rising along its first axis:
    :func:`log_phi_interval` on consecutive edges, each edge's ``log_ndtr`` computed once
    (not twice for each interval beside it): the same numbers to the bit.

    >>> z = np.array([-1.0, 0.5, 40.0, 41.0])
    >>> bool(np.array_equal(log_phi_intervals(z), log_phi_interval(z[:-1], z[1:])))
    True
    """
    z = np.asarray(z, np.float64)
    lo, hi = log_ndtr(z), log_ndtr(-z)
    upper = z[:-1] > 0
    big = np.where(upper, hi[:-1], lo[1:])
    small = np.where(upper, hi[1:], lo[:-1])
    with np.errstate(divide="ignore", invalid="ignore"):
        return big + np.log1p(-np.exp(small - big))


def _log1mexp(x):
    """log(1 - exp(-x)) for x >= 0 (Maechler's switch between the two forms)."""
    x = np.asarray(x, np.float64)
    with np.errstate(divide="ignore"):
        return np.where(x < np.log(2), np.log(-np.expm1(-x)), np.log1p(-np.exp(-x)))


@dataclass(frozen=True)
class FirstPhotonHistogram:
    """Per-cycle probabilities of where the first detection falls.

    ``log_p`` has shape (..., n_bins) over the window's bins in arrival order;
    ``log_p_reset`` is the reset peak (a detection before the window opened) and
    ``log_p_none`` no detection at all. ``p.sum(-1) + p_reset + p_none == 1``.
    """

    edges_s: np.ndarray
    log_p: np.ndarray
    log_p_reset: np.ndarray
    log_p_none: np.ndarray

    @property
    def p(self) -> np.ndarray:
        return np.exp(self.log_p)

    @property
    def p_reset(self) -> np.ndarray:
        return np.exp(self.log_p_reset)

    @property
    def p_none(self) -> np.ndarray:
        return np.exp(self.log_p_none)

    def counts(self, n_cycles) -> np.ndarray:
        """Expected hits per bin over ``n_cycles`` cycles (eq. 2.15)."""
        return np.asarray(n_cycles, np.float64)[..., None] * self.p


def _log_intervals(m, tof, sigma, bg, a, b):
    """log of the expected detections in [a, b): signal (stable tail) + background."""
    za = (a - tof) / sigma
    zb = (b - tof) / sigma
    with np.errstate(divide="ignore"):
        return np.logaddexp(np.log(m) + log_phi_interval(za, zb), np.log(bg * (b - a)))


def _log_bins(m, tof, sigma, bg, edges):
    """log of the expected detections in each bin of contiguous ``edges`` (..., n_bins).

    Same as ``_log_intervals`` on (edges[:-1], edges[1:]), with each tail of the normal
    CDF evaluated once per edge instead of twice per bin.
    """
    z = (edges - tof) / sigma
    lo_tail = log_ndtr(z)     # log Phi(z)
    hi_tail = log_ndtr(-z)    # log Q(z)
    upper = z[..., :-1] > 0
    big = np.where(upper, hi_tail[..., :-1], lo_tail[..., 1:])
    small = np.where(upper, hi_tail[..., 1:], lo_tail[..., :-1])
    with np.errstate(divide="ignore", invalid="ignore"):
        log_sig = big + np.log1p(-np.exp(small - big))
        return np.logaddexp(np.log(m) + log_sig, np.log(bg * np.diff(edges)))


def _intervals(m, tof, sigma, bg, a, b):
    """Expected detections in [a, b)."""
    return np.exp(_log_intervals(m, tof, sigma, bg, a, b))


def _log1mexp_of_log(log_x):
    """log(1 - exp(-x)) given log(x): stays finite where x itself underflows."""
    x = np.exp(log_x)
    # 1 - e^-x = x (1 - x/2 + ...): below 1e-8 the series is exact to double precision.
    return np.where(x < 1e-8, log_x - x / 2, _log1mexp(np.maximum(x, 1e-8)))


def _intensities(m_signal, tof_s, sigma_s, bg_rate_hz, window_s, bin_s, reset_s):
    """Bin edges, expected detections per bin (..., n_bins) and in the reset period (...)."""
    m, tof, sigma, bg = (np.asarray(v, np.float64)[..., None] for v in
                         (m_signal, tof_s, sigma_s, bg_rate_hz))
    _check(m, sigma, bg, window_s, bin_s, reset_s)
    n_bins = int(round(window_s / bin_s))
    edges = np.arange(n_bins + 1) * float(bin_s)
    log_dl = _log_bins(m, tof, sigma, bg, edges)
    l_reset = _intervals(m, tof, sigma, bg, -float(reset_s), 0.0)[..., 0]
    return edges, log_dl, l_reset


def _before(dl, l_reset):
    """L(a_k): expected detections before each bin's left edge (sums of positives only)."""
    return l_reset[..., None] + np.concatenate(
        [np.zeros_like(dl[..., :1]), np.cumsum(dl, axis=-1)[..., :-1]], axis=-1)


def first_photon_histogram(m_signal, tof_s, sigma_s, bg_rate_hz, window_s, bin_s,
                           reset_s=0.0) -> FirstPhotonHistogram:
    """The expected first-photon histogram with pile-up (eq. 2.12-2.17, exact per bin).

    Parameters
    ----------
    m_signal : array_like
        Expected signal detections per cycle, M (eq. 2.2, PDE included); may be 0.
    tof_s : array_like
        Arrival time of the pulse centre after the window opened (may lie outside it).
    sigma_s : array_like
        Total timing jitter (eq. 2.18), > 0.
    bg_rate_hz : array_like
        Background detection rate (ambient and dark counts, PDE included); may be 0.
    window_s, bin_s : float
        Window length and bin width; the window holds ``round(window_s / bin_s)`` bins.
    reset_s : float
        Length of the reset period before the window in which a detection makes the reset
        peak; 0 for none.

    Examples
    --------
    >>> h = first_photon_histogram(1.0, 40e-9, 0.2e-9, 1e6, 80e-9, 0.2e-9)
    >>> total = h.p.sum() + h.p_reset + h.p_none
    >>> bool(abs(total - 1) < 1e-12), int(np.argmax(h.p))  # the peak bin, early side (eq. 2.6)
    (True, 199)
    """
    return histogram_from_intensities(*_intensities(m_signal, tof_s, sigma_s, bg_rate_hz,
                                                    window_s, bin_s, reset_s))


def layered_histogram(m_signal, tof_s, sigma_s, bg_rate_hz, window_s, bin_s,
                      reset_s=0.0) -> FirstPhotonHistogram:
    """:func:`first_photon_histogram` of several surfaces a pixel (a window before a wall):
    ``m_signal`` and ``tof_s`` (..., K), one column a surface (M = 0 for none; the
    intensities add, pile-up as for one). ``sigma_s`` and ``bg_rate_hz`` as there, (...).

    >>> one = first_photon_histogram(1.0, 40e-9, 0.2e-9, 1e6, 80e-9, 0.2e-9)
    >>> two = layered_histogram([1.0, 0.0], [40e-9, 60e-9], 0.2e-9, 1e6, 80e-9, 0.2e-9)
    >>> bool(np.allclose(one.p, two.p))
    True
    """
    m = np.asarray(m_signal, np.float64)
    tof = np.nan_to_num(np.asarray(tof_s, np.float64), nan=0.0)
    k = m.shape[-1]
    sigma = np.asarray(sigma_s, np.float64)[..., None]
    bg = np.asarray(bg_rate_hz, np.float64)[..., None] / k  # each surface carries 1/K of it
    edges, log_dl, l_reset = _intensities(m, tof, sigma, bg, window_s, bin_s, reset_s)
    return histogram_from_intensities(edges, np.logaddexp.reduce(log_dl, axis=-2),
                                      l_reset.sum(axis=-1))


def histogram_from_intensities(edges, log_dl, l_reset) -> FirstPhotonHistogram:
    """The first-photon histogram from per-bin log-intensities and the reset-period one."""
    dl = np.exp(log_dl)
    with np.errstate(divide="ignore"):
        log_p_reset = _log1mexp(l_reset)
    log_p = -_before(dl, l_reset) + _log1mexp_of_log(log_dl)
    return FirstPhotonHistogram(edges, log_p, log_p_reset, -(l_reset + dl.sum(axis=-1)))


def _check(m, sigma, bg, window_s, bin_s, reset_s):
    bad = []
    if not np.all(np.isfinite(m)) or np.any(m < 0):
        bad.append("m_signal must be finite and >= 0")
    if not np.all(np.isfinite(sigma)) or np.any(sigma <= 0):
        bad.append("sigma_s must be finite and > 0")
    if not np.all(np.isfinite(bg)) or np.any(bg < 0):
        bad.append("bg_rate_hz must be finite and >= 0")
    if not (window_s > 0 and bin_s > 0 and window_s / bin_s >= 1):
        bad.append("window_s and bin_s must be > 0 with window_s >= bin_s")
    if not reset_s >= 0:
        bad.append("reset_s must be >= 0")
    if bad:
        raise ValueError("first_photon_histogram: " + "; ".join(bad))


def niclass_histogram(n_cycles, m_signal, tof_s, sigma_s, bg_rate_hz, window_s, bin_s):
    """Niclass's model without pile-up, eq. 2.7-2.9: s(tau) + b, expected counts per bin.

    eq. 2.8 writes the signal as a difference of erf; here it is the same integral taken
    on the stable tail (``log_phi_interval``).
    """
    m, tof, sigma, bg = (np.asarray(v, np.float64)[..., None] for v in
                         (m_signal, tof_s, sigma_s, bg_rate_hz))
    n_bins = int(round(window_s / bin_s))
    edges = np.arange(n_bins + 1) * float(bin_s)
    return np.asarray(n_cycles, np.float64)[..., None] * _intervals(
        m, tof, sigma, bg, edges[:-1], edges[1:])


def detected_power_shape(t_s, m_signal, tof_s, sigma_s, bg_rate_hz=0.0):
    """The detected-photon density of eq. 2.12 (per second, per cycle), in arrival time.

    ``[M phi((t-tof)/sigma)/sigma + bg] * exp(-[M Phi((t-tof)/sigma) + bg t])``, the
    first-detection density from t = 0; :func:`first_photon_histogram` is its exact bin
    integral.
    """
    t = np.asarray(t_s, np.float64)
    z = (t - tof_s) / sigma_s
    rate = m_signal * np.exp(-0.5 * z * z) / (SQRT2PI * sigma_s) + bg_rate_hz
    return rate * np.exp(-(m_signal * ndtr(z) + bg_rate_hz * t))


def peak_shift(m_signal, sigma_s=1.0):
    """Where the pile-up-distorted pulse peaks: ``t_peak - tof`` (Figure 2.2), <= 0.

    Solves eq. 2.6 numerically. eq. 2.6 as printed, ``x/sigma^2 + M/sqrt(pi) exp(...)``,
    drops a factor ``1/(sqrt(2) sigma)`` from d/dt of ``erf((t-TOF)/(sqrt(2) sigma))``; the
    derivative of eq. 2.4 gives ``x + M/sqrt(2 pi) exp(-x^2/2) = 0`` with
    ``x = (t_peak - TOF)/sigma``, solved here (monotone for x < 0: one root).

    >>> float(peak_shift(0.0)), round(float(peak_shift(1.0)), 4)
    (0.0, -0.3722)
    """
    m = np.asarray(m_signal, np.float64)
    c = m / SQRT2PI
    lo, hi = -np.maximum(c, 1e-300), np.zeros_like(c)
    for _ in range(80):  # bisection: f(lo) <= 0 <= f(hi), f increasing
        mid = 0.5 * (lo + hi)
        f = mid + c * np.exp(-0.5 * mid * mid)
        lo = np.where(f < 0, mid, lo)
        hi = np.where(f < 0, hi, mid)
    return np.where(m > 0, 0.5 * (lo + hi), 0.0) * np.asarray(sigma_s, np.float64)


def centroid_sigma(n_cycles, signal_rate_hz, sbr, t0_s, bin_s, sigma_s, n_hw):
    """Standard deviation of the centroid estimate (eq. 2.10), eq. 2.11, as printed.

    ``n_cycles * t0_s`` is the acquisition time T, ``signal_rate_hz`` is S_R, ``sbr`` is
    S_R / B_R, ``n_hw`` the half-width in bins of the centroid window.
    """
    t_acq = np.asarray(n_cycles, np.float64) * t0_s
    w = (2 * np.asarray(n_hw, np.float64) + 1) * bin_s
    e = erf(w / (np.sqrt(8) * sigma_s))
    num = ((w / bin_s) ** 2 - 1) * w * bin_s ** 2 / (128 * sbr * t0_s) + e * sigma_s ** 2
    den = w / (sbr * t0_s) + e
    return np.sqrt(num / den) / np.sqrt(t_acq * signal_rate_hz)


def crlb_tof(n_cycles, m_signal, tof_s, sigma_s, bg_rate_hz, window_s, bin_s,
             reset_s=0.0, amplitude_known: bool = True):
    """Cramer-Rao lower bound on the standard deviation of the arrival time (seconds).

    The Fisher information of the multinomial first-detection outcome of one cycle (every
    bin, the reset peak and "no detection"), pile-up included, times ``n_cycles``:
    ``I = sum_k (dp_k/dTOF)^2 / p_k``. The background carries no information about the
    arrival time but takes first detections away from the signal. Bins whose probability
    underflows carry no information and are skipped.

    ``amplitude_known=False``: the bound when M is estimated alongside the time (as every
    practical estimator must): the (t, t) element of the inverse of the 2 x 2 Fisher
    information of (TOF, M). Under pile-up the leading edge's shape depends on M, so the
    two are correlated and this bound is the larger; at small M they agree.

    >>> s = crlb_tof(10_000, 0.01, 40e-9, 0.2e-9, 0.0, 80e-9, 1e-12)
    >>> round(float(s / (0.2e-9 / np.sqrt(100))), 2)  # ~ sigma / sqrt(signal counts)
    1.0
    """
    edges, log_dl, l_reset = _intensities(m_signal, tof_s, sigma_s, bg_rate_hz, window_s,
                                          bin_s, reset_s)
    dl = np.exp(log_dl)
    m, tof, sigma = (np.asarray(v, np.float64)[..., None] for v in (m_signal, tof_s, sigma_s))
    zs = (-float(reset_s) - tof) / sigma

    def dldt(t):  # dL(t)/dTOF = -(M / sigma) * (phi(z_t) - phi(z_start))
        zt = (t - tof) / sigma
        return -(m / sigma) * (np.exp(-0.5 * zt * zt) - np.exp(-0.5 * zs * zs)) / SQRT2PI

    def dldm(t):  # dL(t)/dM = Phi(z_t) - Phi(z_start)
        return ndtr((t - tof) / sigma) - ndtr(zs)

    l_a = _before(dl, l_reset)           # (..., n_bins)
    p_r = -np.expm1(-l_reset)
    l_t = l_reset + dl.sum(-1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore", under="ignore"):
        log_p = -l_a + _log1mexp_of_log(log_dl)
        ok = np.isfinite(log_p)

        def grads(dfun):
            d = dfun(edges)                  # (..., n_bins + 1)
            # bin [a, b): p = e^{-L_a}(1 - e^{-dL}),  dp = e^{-L_a}(D_b e^{-dL} - D_a);
            # the e^{-L_a} is kept apart so that products are taken in log space
            g = d[..., 1:] * np.exp(-dl) - d[..., :-1]
            # reset peak: dp = e^{-L(0)} D(0); no detection: dp = -e^{-L(T)} D(T)
            return g, np.exp(-l_reset) * d[..., 0], -np.exp(-l_t) * d[..., -1]

        def fisher(a, b):
            (ga, ra, na), (gb, rb, nb) = a, b
            prod = ga * gb
            info = np.where(ok & (prod != 0), np.sign(prod) * np.exp(
                -2 * l_a + np.log(np.abs(ga)) + np.log(np.abs(gb)) - log_p), 0.0).sum(-1)
            info += np.where(p_r > 0, ra * rb / p_r, 0.0)
            info += na * nb * np.exp(l_t)
            return info

        gt = grads(dldt)
        i_tt = fisher(gt, gt)
        if amplitude_known:
            info = i_tt
        else:
            gm = grads(dldm)
            i_tm, i_mm = fisher(gt, gm), fisher(gm, gm)
            info = (i_tt * i_mm - i_tm * i_tm) / i_mm
        return 1.0 / np.sqrt(np.asarray(n_cycles, np.float64) * info)
