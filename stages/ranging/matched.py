"""The matched-filter estimator."""

from __future__ import annotations

import numpy as np

from stages.models.tcspc import FWHM_PER_SIGMA
from stages.ranging.detection import _detect, _peak_index
from stages.ranging.histograms import Estimate, Histograms
from stages.ranging.validation import validated


@validated
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
                    bg * h.bin_s * h.cycles, _detect(h, peak, bg, p_fa, t, sigma_s), "matched")


