"""The 32-bit TDC word (docs/design.md "Raw word", thesis Table 5.1): encode, decode, classify.

As a big-endian uint32, bit 31 first::

    31     30-26  25-22  21-16  15-12  11-10  9   8-1   0
    0      C2nd   P2nd   C1st   P1st   0 0    1   A     0

Phase codes are 4-bit Johnson codes of a 4-stage ring, decoded by :data:`PHASE_DECODE`.
This module is the readable reference: :func:`classify_words` is the specification of the
word classes, and the fused fast paths in :mod:`stages.datapath` are tested against it.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from schemas.constants import ARTIFACT, HIT, INVALID_PHASE, MALFORMED, N_CLASSES, NO_HIT

#: Johnson (circular thermometer) codes in decode order: JOHNSON[k] decodes to k.
JOHNSON = (0b0000, 0b0001, 0b0011, 0b0111, 0b1111, 0b1110, 0b1100, 0b1000)
#: 4-bit phase code -> 0..7, or -1 for the eight bubble codes.
PHASE_DECODE = np.full(16, -1, np.int8)
PHASE_DECODE[list(JOHNSON)] = np.arange(8, dtype=np.int8)
#: 0..7 -> 4-bit Johnson code.
PHASE_ENCODE = np.array(JOHNSON, np.uint32)

SHIFT_C2ND, WIDTH_C2ND = 26, 5
SHIFT_P2ND = 22
SHIFT_C1ST, WIDTH_C1ST = 16, 6
SHIFT_P1ST = 12
SHIFT_ADDR = 1
#: Bits that must hold fixed values: 31, 11, 10 (zero), 9 (one), 0 (zero).
MARKER_MASK = np.uint32((1 << 31) | (1 << 11) | (1 << 10) | (1 << 9) | 1)
MARKER_VALUE = np.uint32(1 << 9)
#: The eight 4-bit codes that are no Johnson code (bubbles): an invalid phase.
BUBBLE_CODES = np.array(sorted(set(range(16)) - set(JOHNSON)), np.uint32)
#: Bits whose values are fixed (31, 11, 10, 9, 0): flipping one makes a word malformed.
MARKER_BITS = np.array([0, 9, 10, 11, 31], np.uint32)
#: Largest TDC count the 8-bit address field can express.
MAX_TDC = 256


class DecodedFields(NamedTuple):
    """Bit fields of a word array (every array has the words' shape)."""

    c1st: np.ndarray      #: uint8, 0..63
    p1st_raw: np.ndarray  #: uint8, the 4-bit phase code as read
    c2nd: np.ndarray      #: uint8, 0..31
    p2nd_raw: np.ndarray  #: uint8
    address: np.ndarray   #: uint16, 0..255
    markers_ok: np.ndarray  #: bool

    @property
    def p1st(self) -> np.ndarray:
        """Decoded first-stage phase, int8, -1 where the code is a bubble."""
        return PHASE_DECODE[self.p1st_raw]

    @property
    def p2nd(self) -> np.ndarray:
        return PHASE_DECODE[self.p2nd_raw]

    @property
    def d1st(self) -> np.ndarray:
        """D1st = 8*C1st + P1st (eq. 3.2), int16, -1 where P1st is invalid."""
        p = self.p1st.astype(np.int16)
        return np.where(p < 0, np.int16(-1), self.c1st.astype(np.int16) * 8 + p)

    @property
    def d2nd(self) -> np.ndarray:
        """D2nd = 8*C2nd + P2nd (eq. 3.3), int16, -1 where P2nd is invalid."""
        p = self.p2nd.astype(np.int16)
        return np.where(p < 0, np.int16(-1), self.c2nd.astype(np.int16) * 8 + p)


def _check_range(name: str, values: np.ndarray, hi: int) -> None:
    if values.size and (values.min() < 0 or values.max() > hi):
        bad = values[(values < 0) | (values > hi)]
        raise ValueError(f"encode_words: {name} must be in 0..{hi}, found {bad[:5].tolist()}")


def encode_words(c1st, p1st, c2nd, p2nd, tdc, *, raw_phase: bool = False) -> np.ndarray:
    """Encode fields into native-order uint32 words (vectorised, broadcasting).

    Parameters
    ----------
    c1st, c2nd : array_like of int
        VCO counters, 0..63 and 0..31.
    p1st, p2nd : array_like of int
        Phases 0..7 (Johnson-encoded here), or raw 4-bit codes 0..15 when ``raw_phase``.
    tdc : array_like of int
        TDC address 0..255.

    Examples
    --------
    >>> hex(int(encode_words(1, 1, 0, 0, 3)))
    '0x11206'
    >>> decode_fields(encode_words(63, 7, 31, 4, 127)).d1st.tolist()
    511
    """
    arrays = [np.asarray(v, dtype=np.int64) for v in (c1st, p1st, c2nd, p2nd, tdc)]
    c1, p1, c2, p2, a = np.broadcast_arrays(*arrays)
    phase_hi = 15 if raw_phase else 7
    for name, v, hi in (("c1st", c1, 63), ("p1st", p1, phase_hi), ("c2nd", c2, 31),
                        ("p2nd", p2, phase_hi), ("tdc", a, 255)):
        _check_range(name, v, hi)
    if not raw_phase:
        p1, p2 = PHASE_ENCODE[p1], PHASE_ENCODE[p2]
    word = ((c2.astype(np.uint32) << SHIFT_C2ND) | (p2.astype(np.uint32) << SHIFT_P2ND)
            | (c1.astype(np.uint32) << SHIFT_C1ST) | (p1.astype(np.uint32) << SHIFT_P1ST)
            | MARKER_VALUE | (a.astype(np.uint32) << SHIFT_ADDR))
    return word.astype(np.uint32)


def decode_fields(words) -> DecodedFields:
    """Split native uint32 words into their bit fields (no classification)."""
    w = np.asarray(words, dtype=np.uint32)
    return DecodedFields(
        c1st=((w >> SHIFT_C1ST) & 0x3F).astype(np.uint8),
        p1st_raw=((w >> SHIFT_P1ST) & 0xF).astype(np.uint8),
        c2nd=((w >> SHIFT_C2ND) & 0x1F).astype(np.uint8),
        p2nd_raw=((w >> SHIFT_P2ND) & 0xF).astype(np.uint8),
        address=((w >> SHIFT_ADDR) & 0xFF).astype(np.uint16),
        markers_ok=(w & MARKER_MASK) == MARKER_VALUE,
    )


def positions(n_words: int, n_tdc: int, first_word: int = 0) -> np.ndarray:
    """TDC position of each word: word i of a capture belongs to TDC i % n_tdc."""
    return ((np.arange(n_words, dtype=np.int64) + first_word) % n_tdc).astype(np.uint16)


def classify_words(words, n_tdc: int, first_word: int = 0, n_min=None, n_max=None,
                   fields: DecodedFields | None = None) -> np.ndarray:
    """Class code of every word (the reference definition of the word classes).

    A word gets the first class that fits: malformed (marker bits wrong, or address not
    the TDC of its position ``(first_word + i) % n_tdc``), invalid_phase (a bubble in
    P1st or P2nd), no_hit (C1st, P1st, C2nd, P2nd all zero), artifact (D2nd outside
    ``[n_min[tdc], n_max[tdc]]``; skipped when the bounds are None), hit.

    Returns
    -------
    numpy.ndarray of uint8
        Codes indexing :data:`schemas.WORD_CLASSES`.

    Examples
    --------
    >>> w = encode_words([0, 1, 1], [0, 2, 2], [0, 3, 31], [0, 1, 1], [0, 1, 2])
    >>> classify_words(w, 4, n_min=[0] * 4, n_max=[200] * 4).tolist()  # no_hit, hit, artifact
    [1, 0, 2]
    """
    w = np.atleast_1d(np.asarray(words, dtype=np.uint32))
    f = fields if fields is not None else decode_fields(w)
    pos = positions(w.size, n_tdc, first_word)
    cls = np.full(w.shape, HIT, np.uint8)
    if n_min is not None:
        n_min = np.asarray(n_min)
        n_max = np.asarray(n_max)
        d2 = f.d2nd
        cls[(d2 < n_min[pos]) | (d2 > n_max[pos])] = ARTIFACT
    cls[(f.c1st == 0) & (f.p1st_raw == 0) & (f.c2nd == 0) & (f.p2nd_raw == 0)] = NO_HIT
    cls[(PHASE_DECODE[f.p1st_raw] < 0) | (PHASE_DECODE[f.p2nd_raw] < 0)] = INVALID_PHASE
    cls[~f.markers_ok | (f.address != pos)] = MALFORMED
    return cls


def class_counts(cls: np.ndarray) -> np.ndarray:
    """Counts of each class code, int64 of length :data:`schemas.N_CLASSES`."""
    return np.bincount(np.asarray(cls, dtype=np.intp).ravel(), minlength=N_CLASSES)
