"""Second-stage code bounds [Nmin, Nmax] per TDC, and the artifact filter they define.

The artifact of thesis section 3.4 is a word with D2nd > Nmax. Bounds come from a
calibration when one is given; otherwise :func:`estimate_bounds` finds them in the capture
itself: valid second-stage codes fill one contiguous block of D2nd values, and the sparse
codes outside the block that holds nearly all of the mass are the artifact.

That estimate needs the valid block to hold most of a TDC's non-empty words at a density
well above the artifact's. In a dark capture (DCR measurement) the artifact can outnumber
real detections (298 artifact words against 6 real ones in the thesis's Figure 3.5): such
a TDC is flagged ``uncertain`` with the reason, and the commands say so; use a calibration
there.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from schemas.constants import N_CODES_2ND
from schemas.errors import CalibrationError


@dataclass(frozen=True)
class ArtifactBounds:
    """Valid D2nd range per TDC: a word with D2nd outside [n_min, n_max] is an artifact."""

    n_min: np.ndarray  #: int16 per TDC
    n_max: np.ndarray  #: int16 per TDC
    source: str = "estimated"  #: "calibration:<path>", "estimated" or "none"
    #: per TDC, True where an estimate cannot be vouched for by the data (None: none is)
    uncertain: np.ndarray | None = None
    reasons: tuple = ()  #: per TDC, why it is uncertain ("" where it is not)

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
        unc = np.zeros(n_min.size, bool) if self.uncertain is None else \
            np.asarray(self.uncertain, bool)
        if unc.shape != n_min.shape:
            raise CalibrationError(f"uncertain {unc.shape} must match n_min {n_min.shape}")
        reasons = tuple(self.reasons) or ("",) * n_min.size
        if len(reasons) != n_min.size:
            raise CalibrationError(f"{len(reasons)} reasons for {n_min.size} TDCs")
        for a in (n_min, n_max, unc):
            a.setflags(write=False)
        object.__setattr__(self, "n_min", n_min)
        object.__setattr__(self, "n_max", n_max)
        object.__setattr__(self, "uncertain", unc)
        object.__setattr__(self, "reasons", reasons)

    @property
    def n_tdc(self) -> int:
        return int(self.n_min.size)

    @classmethod
    def unbounded(cls, n_tdc: int) -> ArtifactBounds:
        """Bounds that accept every D2nd (no artifact filtering)."""
        return cls(np.zeros(n_tdc, np.int16), np.full(n_tdc, N_CODES_2ND - 1, np.int16),
                   source="none")

    def rows(self, start: int, stop: int) -> ArtifactBounds:
        """The bounds of TDCs ``start..stop-1`` (a worker's TDC range)."""
        return ArtifactBounds(self.n_min[start:stop], self.n_max[start:stop], self.source,
                              self.uncertain[start:stop], self.reasons[start:stop])

    def describe(self) -> str:
        """The source, and how many TDCs are uncertain and why (for a command's summary)."""
        if not self.uncertain.any():
            return self.source
        why: dict[str, list[int]] = {}
        for t in np.flatnonzero(self.uncertain):
            why.setdefault(self.reasons[t], []).append(int(t))
        parts = [f"{len(v)} TDC(s) {v[:6]}{'...' if len(v) > 6 else ''}: {r}"
                 for r, v in why.items()]
        return f"{self.source}; UNCERTAIN on " + "; ".join(parts)

    def in_block(self) -> np.ndarray:
        """Boolean table (n_tdc, 256): True where D2nd is inside the TDC's block."""
        d2 = np.arange(N_CODES_2ND)
        return (d2 >= self.n_min[:, None]) & (d2 <= self.n_max[:, None])


BLOCK_FLOOR = 0.5       #: lowest density a valid code is expected at, x the block's level
MIN_CONTRAST = 8.0      #: block level over artifact density below which a TDC is ambiguous
MAX_OUTSIDE = 0.1       #: share of the counts outside the block above which a TDC is ambiguous
OUTSIDE_CAP = 16.0      #: the fitted artifact density is at most the block's level over this
MIN_BLOCK_DENSITY = 2.0  #: counts per block code below which the edges are uncertain
LEVEL_SPAN = 0.25       #: codes above this x the level are the block's, for its median


def estimate_bounds(d2nd_hist: np.ndarray) -> ArtifactBounds:
    """Estimate [Nmin, Nmax] per TDC from histograms of D2nd over candidate words.

    The physics (thesis sections 3.2 and 3.4): valid D2nd fill [Nmin, Nmax] contiguously;
    the block's codes differ in density by the second stage's own DNL (tens of percent, so
    no single density describes them); the artifact sits outside the block at a density
    far below the block's. The model follows it: each code inside the block has its own
    Poisson rate, anything from ``BLOCK_FLOOR`` times the block's level up (the level: the
    median count of the codes that hold the top half of the mass, block codes whatever the
    DNL, and at most twice the block's median: a reset peak's spike can hold half the
    mass); each side outside has one rate of its own, fitted, at most the level over
    ``OUTSIDE_CAP``. The block is the [a, b] of
    highest profile likelihood, found exactly for all TDCs at once (the likelihood
    separates into a term of a and a term of b, so a running maximum finds the best pair).
    A code rich enough for the block gains ~ its count x log(contrast) inside, an artifact
    code loses ~ the floor's rate there: both grow with the statistics, so more data makes
    the estimate more right, never less (a likelihood-ratio cut between two flat densities
    found a "boundary" inside a DNL-shaped block once the statistics were large). An empty
    code inside the block at low statistics costs only the floor's rate, and is spanned.

    Parameters
    ----------
    d2nd_hist : ndarray, shape (n_tdc, 256)
        Counts of D2nd per TDC over words that are neither malformed, invalid nor no_hit.

    Returns
    -------
    ArtifactBounds
        A TDC with no counts gets the full range 0..255: with no data there is nothing to
        filter, and nothing is invented. ``uncertain`` flags TDCs whose estimate the data
        cannot vouch for, with the reason in ``reasons``: the artifact within
        ``MIN_CONTRAST`` of the block's level or over ``MAX_OUTSIDE`` of the counts (a
        dark capture, where the artifact may even look like the block: use a
        calibration), or fewer than ``MIN_BLOCK_DENSITY`` counts per block code (the
        edges may be off by a code).

    Examples
    --------
    >>> rng = np.random.default_rng(0)
    >>> h = np.zeros((1, 256), int)
    >>> h[0, 20:150] = rng.poisson(20 * rng.uniform(0.5, 1.5, 130))  # a DNL-shaped block
    >>> h[0, 150:256] = rng.poisson(0.5, 106)           # sparse artifact codes above Nmax
    >>> b = estimate_bounds(h); int(b.n_min[0]), int(b.n_max[0])
    (20, 149)
    >>> b = estimate_bounds(h * 1000); int(b.n_min[0]), int(b.n_max[0])  # more data
    (20, 149)
    """
    h = np.asarray(d2nd_hist)
    if h.ndim != 2 or h.shape[1] != N_CODES_2ND:
        raise ValueError(f"estimate_bounds: d2nd_hist must be (n_tdc, {N_CODES_2ND}), "
                         f"found {h.shape}")
    k = h.astype(np.float64)
    if k.size and (not np.all(np.isfinite(k)) or k.min() < 0):
        raise ValueError("estimate_bounds: counts must be finite and >= 0")
    n_tdc, n = k.shape
    total = k.sum(axis=1)
    codes = np.arange(n)

    # the block's level: the median count of the codes holding the top half of the mass
    order = np.argsort(-k, axis=1, kind="stable")
    ranked = np.take_along_axis(k, order, axis=1)
    top = np.cumsum(ranked, axis=1) - ranked < 0.5 * total[:, None]
    in_top = np.zeros_like(top)
    np.put_along_axis(in_top, order, top, axis=1)
    level = _masked_median(k, in_top)
    # ... at most twice the block's median (that of the codes above LEVEL_SPAN of the level,
    # taken three times: sparse artifact codes stay below): the top half of the mass can
    # sit on a few codes far above the rest. A bright density test's reset peak (its
    # STARTs all at tau = T) puts a third of the hits on the eighth of the block its
    # jitter reaches, 4-6x the other codes: the floor rose above them and the block was
    # cut (Nmax 228 -> 166 on a chip of the zoo with a 35 ns reset period at 0.75
    # detections a cycle, issue 15).
    median = level
    for _ in range(3):
        median = _masked_median(k, k >= (LEVEL_SPAN * median)[:, None])
    level = np.minimum(level, 2.0 * median)
    floor = (BLOCK_FLOOR * level)[:, None]

    # a side of m codes holding s counts, at its fitted rate, which the physics caps far
    # below the block's (else one edge code left outside would fit as well as inside)
    cap = (level / OUTSIDE_CAP)[:, None]

    def outside(s, m):
        rate = np.minimum(s / np.maximum(m, 1), cap)
        return _xlogy(s, rate) - m * rate

    # profile log-likelihood of [a, b] = inside(a..b) + below(a) + above(b)
    rate_in = np.maximum(k, floor)
    p_in = np.concatenate([np.zeros((n_tdc, 1)), np.cumsum(_xlogy(k, rate_in) - rate_in,
                                                         axis=1)], axis=1)
    p_k = np.concatenate([np.zeros((n_tdc, 1)), np.cumsum(k, axis=1)], axis=1)
    term_a = outside(p_k[:, :-1], codes[None, :]) - p_in[:, :-1]            # a = 0..n-1
    term_b = p_in[:, 1:] + outside(total[:, None] - p_k[:, 1:], n - 1 - codes[None, :])
    best_a = np.maximum.accumulate(term_a, axis=1)
    hi = np.argmax(term_b + best_a, axis=1)
    lo = np.argmax(np.where(codes[None, :] <= hi[:, None], term_a, -np.inf), axis=1)
    empty = total == 0
    lo = np.where(empty, 0, lo)
    hi = np.where(empty, n - 1, hi)

    block = (codes >= lo[:, None]) & (codes <= hi[:, None])
    mass_in = (k * block).sum(axis=1)
    below, above = codes < lo[:, None], codes > hi[:, None]
    l_out = np.maximum((k * below).sum(axis=1) / np.maximum(below.sum(axis=1), 1),
                       (k * above).sum(axis=1) / np.maximum(above.sum(axis=1), 1))
    reasons = np.full(n_tdc, "", dtype=object)
    sparse = ~empty & (mass_in / (hi - lo + 1) < MIN_BLOCK_DENSITY)
    reasons[sparse] = f"under {MIN_BLOCK_DENSITY:g} counts per block code: edges may be off"
    low_contrast = ~empty & (l_out * MIN_CONTRAST > level)
    reasons[low_contrast] = (f"artifact density within {MIN_CONTRAST:g}x of the block's "
                             "(use a calibration)")
    dark = ~empty & (mass_in < (1 - MAX_OUTSIDE) * total)
    reasons[dark] = (f"over {MAX_OUTSIDE:.0%} of the counts outside the block (a dark "
                     "capture? use a calibration)")
    return ArtifactBounds(lo.astype(np.int16), hi.astype(np.int16), source="estimated",
                          uncertain=reasons != "", reasons=tuple(reasons.tolist()))


def _xlogy(x, y) -> np.ndarray:
    """``x * log(y)``, 0 where ``x == 0`` (and y is not NaN): scipy.special.xlogy bit for bit
    (the C library's log, as scipy's loop calls it; numpy's own log may differ in the last
    bit), without importing scipy.special (0.3-0.6 s) on the command line's path."""
    x, y = np.broadcast_arrays(np.asarray(x, np.float64), np.asarray(y, np.float64))
    out = np.zeros(x.shape)
    m = (x != 0) | np.isnan(y)
    ym = y[m]
    log = np.full(ym.shape, np.nan)  # log of a negative number or NaN
    pos = ym > 0
    yp = ym[pos]
    log[pos] = np.fromiter(map(math.log, yp.tolist()), np.float64, yp.size)
    log[ym == 0] = -np.inf
    with np.errstate(invalid="ignore"):  # 0 * nan, inf * 0: nan, as scipy's
        out[m] = x[m] * log
    return out


def _masked_median(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Row-wise median of ``values`` where ``mask``; 0 for a row with no such value.

    What ``np.nanmedian`` gives on the masked values (the mean of the two middle ones),
    without it: it imports numpy.ma (20-45 ms) on the command line's path."""
    n = mask.sum(axis=1)
    ranked = np.sort(np.where(mask, values, np.inf), axis=1)
    lo = np.take_along_axis(ranked, np.maximum(n - 1, 0)[:, None] // 2, axis=1)[:, 0]
    hi = np.take_along_axis(ranked, (n // 2)[:, None], axis=1)[:, 0]
    with np.errstate(invalid="ignore"):  # inf - inf in rows without a value
        med = (lo + hi) / 2
    return np.where(n > 0, med, 0.0)
