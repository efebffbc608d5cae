"""Second-stage code bounds [Nmin, Nmax] per TDC, and the artifact filter they define.

The artifact of thesis section 3.4 is a word with D2nd > Nmax. Bounds come from a
calibration when one is given; otherwise :func:`estimate_bounds` finds them in the capture
itself: valid second-stage codes fill one contiguous block of D2nd values, and the sparse
codes outside the block that holds nearly all of the mass are the artifact.

That estimate assumes the valid block does hold most of a TDC's non-empty words. In a
dark capture (DCR measurement) the artifact can outnumber real detections (298 artifact
words against 6 real ones in the thesis's Figure 3.5): use a calibration there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.errors import CalibrationError
from schemas.words import N_CODES_2ND


@dataclass(frozen=True)
class ArtifactBounds:
    """Valid D2nd range per TDC: a word with D2nd outside [n_min, n_max] is an artifact."""

    n_min: np.ndarray  #: int16 per TDC
    n_max: np.ndarray  #: int16 per TDC
    source: str = "estimated"  #: "calibration:<path>", "estimated" or "none"

    def __post_init__(self):
        n_min = np.asarray(self.n_min, np.int16)
        n_max = np.asarray(self.n_max, np.int16)
        if n_min.shape != n_max.shape or n_min.ndim != 1:
            raise CalibrationError(f"n_min {n_min.shape} and n_max {n_max.shape} must be "
                                   "1-D of one length (one per TDC)")
        if np.any(n_min > n_max) or np.any(n_min < 0) or np.any(n_max >= N_CODES_2ND):
            bad = np.flatnonzero((n_min > n_max) | (n_min < 0) | (n_max >= N_CODES_2ND))
            raise CalibrationError(f"invalid [n_min, n_max] for TDCs {bad[:8].tolist()}: "
                                   f"need 0 <= n_min <= n_max <= {N_CODES_2ND - 1}")
        n_min.setflags(write=False)
        n_max.setflags(write=False)
        object.__setattr__(self, "n_min", n_min)
        object.__setattr__(self, "n_max", n_max)

    @property
    def n_tdc(self) -> int:
        return int(self.n_min.size)

    @classmethod
    def unbounded(cls, n_tdc: int) -> ArtifactBounds:
        """Bounds that accept every D2nd (no artifact filtering)."""
        return cls(np.zeros(n_tdc, np.int16), np.full(n_tdc, N_CODES_2ND - 1, np.int16),
                   source="none")

    def in_block(self) -> np.ndarray:
        """Boolean table (n_tdc, 256): True where D2nd is inside the TDC's block."""
        d2 = np.arange(N_CODES_2ND)
        return (d2 >= self.n_min[:, None]) & (d2 <= self.n_max[:, None])


def estimate_bounds(d2nd_hist: np.ndarray, min_gain: float = 12.0) -> ArtifactBounds:
    """Estimate [Nmin, Nmax] per TDC from histograms of D2nd over candidate words.

    The artifact lies above Nmax only (thesis section 3.4), so the model is one-sided:
    no valid or artifact code below Nmin (Nmin is the lowest populated code), Poisson
    counts of one density in ``[Nmin, b]`` and of another above ``b``; the ``b`` of
    highest likelihood wins. It is kept only when it beats the one-density model over
    the populated span by ``min_gain`` in log-likelihood (12 is p ~ 1e-5), so a clean TDC
    keeps its whole span and a fluctuation at the edge is not cut away.

    Exactness needs statistics: a code at Nmax with k counts, block density L and
    artifact density l, is kept when k*log(L/l) > L - l. With L = 10 counts per code and
    l = 0.2, a code is misplaced with probability ~0.3 %. A calibration (``--calibration``)
    gives exact bounds; a dark capture, where the artifact outnumbers real counts, needs one.

    Parameters
    ----------
    d2nd_hist : ndarray, shape (n_tdc, 256)
        Counts of D2nd per TDC over words that are neither malformed, invalid nor no_hit.
    min_gain : float
        Log-likelihood margin the two-density model needs.

    Returns
    -------
    ArtifactBounds
        A TDC with no counts gets the full range 0..255: with no data there is nothing to
        filter, and nothing is invented.

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> h = np.zeros((1, 256), int); h[0, 20:150] = rng.poisson(20, 130)
    >>> h[0, 150:256] = rng.poisson(0.5, 106)           # sparse artifact codes above Nmax
    >>> b = estimate_bounds(h); int(b.n_min[0]), int(b.n_max[0])
    (20, 149)
    """
    from scipy.special import xlogy

    h = np.asarray(d2nd_hist)
    if h.ndim != 2 or h.shape[1] != N_CODES_2ND:
        raise ValueError(f"estimate_bounds: d2nd_hist must be (n_tdc, {N_CODES_2ND}), "
                         f"found {h.shape}")
    n_tdc, n = h.shape
    counts = h.astype(np.float64)
    total = counts.sum(axis=1)
    populated = counts > 0
    lo = np.where(total > 0, np.argmax(populated, axis=1), 0)
    hi = np.where(total > 0, n - 1 - np.argmax(populated[:, ::-1], axis=1), n - 1)
    # Every candidate upper edge b of every TDC at once: block [lo, b], artifact (b, hi].
    csum = np.cumsum(counts, axis=1)
    below = np.take_along_axis(csum, lo[:, None], axis=1) - counts[np.arange(n_tdc), lo][:, None]
    b = np.arange(n)[None, :]
    s_in = csum - below
    w_in = (b - lo[:, None] + 1).astype(np.float64)
    s_out = total[:, None] - csum
    w_out = (hi[:, None] - b).astype(np.float64)
    valid = (b >= lo[:, None]) & (b <= hi[:, None])
    with np.errstate(divide="ignore", invalid="ignore"):
        ll = xlogy(s_in, s_in / w_in) + xlogy(s_out, np.where(w_out > 0, s_out / w_out, 0))
    ll = np.where(valid, ll, -np.inf)
    ll_span = xlogy(total, total / (hi - lo + 1))
    best = np.argmax(ll, axis=1)
    gain = ll[np.arange(n_tdc), best] - ll_span
    n_max = np.where((total > 0) & (gain > min_gain), best, hi)
    return ArtifactBounds(lo.astype(np.int16), n_max.astype(np.int16), source="estimated")
