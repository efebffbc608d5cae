"""Synthetic word streams with a known class mix, for benchmarks, tests and the demo.

This is not the sensor simulator (no photons, no pile-up, no TDC non-linearity): it draws
each word's class first and then fields consistent with that class, so the exact class
counts and hit histogram it intends are known and returned with the words.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.constants import (
    ARTIFACT,
    HIT,
    INVALID_PHASE,
    MALFORMED,
    N_CLASSES,
    N_CODES,
    N_CODES_2ND,
    NO_HIT,
)
from stages.codec import BUBBLE_CODES, MARKER_BITS, encode_words


@dataclass(frozen=True)
class PatternTruth:
    """What a pattern's words are meant to decode to."""

    hits: np.ndarray          #: (n_tdc, 512) hits per D1st code
    class_counts: np.ndarray  #: (N_CLASSES, n_tdc)
    n_min: np.ndarray         #: valid D2nd block per TDC
    n_max: np.ndarray


def pattern_words(n_cycles: int, n_tdc: int = 128, *, hit_prob: float = 0.05,
                 peak_code: float = 300.0, peak_sigma: float = 3.0,
                 peak_fraction: float = 0.5, artifact_prob: float = 0.001,
                 invalid_prob: float = 1e-4, malformed_prob: float = 1e-4,
                 n_min: int = 24, n_max: int = 150,
                 rng: np.random.Generator | int | None = 0) -> tuple[np.ndarray, PatternTruth]:
    """Words of ``n_cycles`` cycles and the truth they encode.

    Each word is independently a hit with ``hit_prob`` (a fraction ``peak_fraction`` from
    a Gaussian peak at ``peak_code``, the rest uniform over the 512 codes), an artifact, an
    invalid-phase or malformed word with their probabilities, else a no_hit word. Valid
    D2nd is uniform in ``[n_min, n_max]``; artifacts have D2nd above ``n_max``.

    Examples
    --------
    >>> w, truth = pattern_words(10, 4, hit_prob=0.5, rng=1)
    >>> w.size, int(truth.class_counts.sum())
    (40, 40)
    """
    if not 1 <= n_min <= n_max < N_CODES_2ND - 1:
        raise ValueError(f"need 1 <= n_min <= n_max < {N_CODES_2ND - 1}: an artifact needs "
                         "room above n_max, and n_min >= 1 keeps hits apart from no_hit")
    rng = np.random.default_rng(rng)
    n = n_cycles * n_tdc
    pos = np.arange(n, dtype=np.int64) % n_tdc
    u = rng.random(n)
    edges = np.cumsum([hit_prob, artifact_prob, invalid_prob, malformed_prob])
    if edges[-1] > 1:
        raise ValueError("class probabilities add up to more than 1")
    cls = np.full(n, NO_HIT, np.int64)
    for code, lo, hi in ((HIT, 0, edges[0]), (ARTIFACT, edges[0], edges[1]),
                         (INVALID_PHASE, edges[1], edges[2]), (MALFORMED, edges[2], edges[3])):
        cls[(u >= lo) & (u < hi)] = code
    in_peak = rng.random(n) < peak_fraction
    d1 = np.where(in_peak, np.rint(rng.normal(peak_code, peak_sigma, n)),
                  rng.integers(0, N_CODES, n))
    d1 = np.clip(d1, 0, N_CODES - 1).astype(np.int64)
    d2 = rng.integers(n_min, n_max + 1, n)
    d2 = np.where(cls == ARTIFACT, rng.integers(n_max + 1, N_CODES_2ND, n), d2)
    zero = cls == NO_HIT
    d1 = np.where(zero, 0, d1)
    d2 = np.where(zero, 0, d2)
    words = encode_words(d1 // 8, d1 % 8, d2 // 8, d2 % 8, pos)
    # An invalid phase: a bubble code in P1st (or P2nd, half of the time).
    bad_phase = cls == INVALID_PHASE
    bubble = BUBBLE_CODES[rng.integers(0, BUBBLE_CODES.size, n)]
    which = rng.random(n) < 0.5
    w_p1 = (words & ~np.uint32(0xF << 12)) | (bubble << 12)
    w_p2 = (words & ~np.uint32(0xF << 22)) | (bubble << 22)
    words = np.where(bad_phase, np.where(which, w_p1, w_p2), words)
    # Malformed: a broken marker bit (bit 0, 9, 10, 11 or 31) or a wrong address.
    mal = cls == MALFORMED
    bit = MARKER_BITS[rng.integers(0, MARKER_BITS.size, n)]
    wrong_addr = (words & ~np.uint32(0xFF << 1)) | (((pos + 1) % 256).astype(np.uint32) << 1)
    broken = words ^ (np.uint32(1) << bit)
    if n_tdc == 256:
        wrong_addr = broken
    words = np.where(mal, np.where(rng.random(n) < 0.5, broken, wrong_addr), words)
    hits = np.bincount(pos[cls == HIT] * N_CODES + d1[cls == HIT],
                       minlength=n_tdc * N_CODES).reshape(n_tdc, N_CODES)
    cc = np.bincount(cls * n_tdc + pos, minlength=N_CLASSES * n_tdc).reshape(N_CLASSES, n_tdc)
    truth = PatternTruth(hits, cc, np.full(n_tdc, n_min), np.full(n_tdc, n_max))
    return words.astype(np.uint32), truth
