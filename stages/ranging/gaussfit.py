"""The thesis's baseline: a least-squares Gaussian fit (section 5.2)."""

from __future__ import annotations

import numpy as np

from stages.models.tcspc import FWHM_PER_SIGMA
from stages.ranging.detection import _detect, _peak_index
from stages.ranging.histograms import Estimate, Histograms
from stages.ranging.validation import validated


@validated
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
            width = abs(popt[2])
            sd = np.sqrt(max(pcov[1, 1], 0.0))
            if not (0.25 * h.bin_s <= width <= x[-1] - x[0] + h.bin_s and sd <= width):
                # a peak in one bin has no width to fit: its covariance gave sigmas of
                # metres to kilometres (issue 34.6); NaN fails the test too
                raise ValueError
            out[i] = popt[1], sd, width
        except (RuntimeError, ValueError, TypeError, OptimizeWarning):  # (TypeError: < 4 bins)
            out[i] = h.centres[i, p], sigma_s, sigma_s
    sig_counts = np.full(peak.size, np.nan)
    det = _detect(h, peak, bg, p_fa, sigma_s=sigma_s)
    return Estimate(out[:, 0], out[:, 1], FWHM_PER_SIGMA * out[:, 2], sig_counts,
                    bg * h.bin_s * h.cycles, det, "gaussfit")


