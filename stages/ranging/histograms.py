"""The ranging stage's input and output: first-photon histograms on a calibrated time
axis (:class:`Histograms`) and per-pixel results (:class:`Estimate`)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np


def coates(counts, cycles, at_risk=None) -> np.ndarray:
    """Coates's pile-up correction of first-photon histograms: the expected detections
    per bin per cycle, ``-log(1 - counts / at_risk)``, with ``at_risk`` the cycles not yet
    stopped before the bin (at least 1) and the ratio kept below 1. ``counts`` (..., bins),
    ``cycles`` broadcast against ``counts[..., 0]``. (Times ``cycles``: the photon counts
    a histogram without pile-up would hold.) ``at_risk``: those numbers where known."""
    c = np.asarray(counts, np.float64)
    if at_risk is None:
        at_risk = np.asarray(cycles, np.float64)[..., None] - (np.cumsum(c, axis=-1) - c)
    r = np.maximum(at_risk, 1.0)
    return -np.log1p(-np.minimum(c / r, 1 - 1e-12))


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

    @cached_property
    def lam(self) -> np.ndarray:
        """:meth:`intensity`, kept (read, never written: each return's width reads it)."""
        return self.intensity()

    def intensity(self) -> np.ndarray:
        """Coates-corrected expected detections per bin per cycle (undistorted)."""
        return coates(self.counts, self.cycles, self.at_risk)


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
    #: per pixel, "" or why the result is flagged (:mod:`stages.ranging.validation`): an
    #: input it could not use, an estimate outside the window, no uncertainty; a flagged
    #: pixel is not detected unless the flag says it may be cut by the window's edge
    flag: np.ndarray | None = None
    #: per row, the index of the return (0 the strongest) and the pixel it belongs to, where
    #: a pixel may have several rows (:func:`stages.ranging.multi.estimate_returns`)
    return_index: np.ndarray | None = None
    pixel: np.ndarray | None = None
