"""The centroid estimator (eq. 2.10)."""

from __future__ import annotations

import numpy as np

from stages.models.tcspc import FWHM_PER_SIGMA
from stages.ranging.detection import _detect, _peak_index
from stages.ranging.histograms import Estimate, Histograms
from stages.ranging.validation import validated


@validated
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
                    bg * h.bin_s * h.cycles, _detect(h, peak, bg, p_fa, t, sigma_s), "centroid")


