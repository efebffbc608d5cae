"""The fused hot path: decode + classify + histogram of raw words in one pass.

Two engines compute the same thing and are tested to agree with each other and with the
reference :func:`stages.codec.classify_words`:

``numpy``
    Table-driven. Each native uint32 word is viewed as two uint16 halves. The low half,
    XORed with the expected marker/address pattern of its position, indexes a 64 Ki table
    ``lut_lo``; ``high_half * n_tdc + position`` indexes a per-TDC table ``lut_hi`` (the
    artifact bounds are folded into it). Their sum holds ``D1st * n_tdc + position`` in its
    low part and, above it, ``(lo_state + 4 * hi_state) * n_tdc * 512``: each half's
    table adds its own state (ok, zero, invalid, malformed; the high half also artifact),
    so the sum is the final key, one ``bincount`` per block counts every word, and the 24
    state pairs are folded into the five classes once per block. No boolean-mask
    copies. Sub-chunks are sized to stay in L2 and every temporary is preallocated.
    Keys and tables are code-major (``code * n_tdc + position``): position-major strides
    of 4 KiB put the no-hit words of a cycle into one cache set and ran five times slower.
``numba``
    One compiled loop over the words with the same semantics (a plain Python function
    here, compiled by numba). A process runs it as a C kernel that loads without numba
    (:mod:`stages.nativecode`, 1-2 ms against numba's 0.5-0.9 s of import and first call)
    or, where that cannot be had, through numba's dispatcher. Either releases the GIL, so
    threads may fill separate states at once.

State is two arrays: ``hits`` (n_tdc, n_bins) of uint64 and ``class_counts``
(N_CLASSES, n_tdc) of uint64. The per-TDC cycle count is the column sum of
``class_counts``: every word at a TDC's position is one cycle of that TDC. Optionally a
third, ``artifacts`` (n_tdc, n_bins): the artifact words by their code. An artifact is a
START too: the cycle is not at risk after it, which a density test's pile-up correction
must know (at 1e-4 artifacts a cycle, ~0.015 LSB of INL).
"""

from __future__ import annotations

import ctypes
import functools
import importlib.util
import sys
import threading
from dataclasses import dataclass
from functools import cached_property

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
from stages.artifact import ArtifactBounds
from stages.codec import MARKER_MASK, MARKER_VALUE, MAX_TDC, PHASE_DECODE

# numba is a dependency, but the numpy path must work (and is tested) without it. It is
# imported only when a kernel is compiled or the dispatcher is needed: a process whose
# kernels load from stages.nativecode never imports it (0.5-0.9 s saved at start-up).
HAVE_NUMBA = importlib.util.find_spec("numba") is not None

ENGINES = ("numba", "numpy")
#: Words per numpy sub-chunk: ~6 int32 temporaries of this length stay within L2.
CHUNK_WORDS = 1 << 15
#: Words per bincount: large enough that the (N_CLASSES * n_tdc * 512) output is cheap.
BLOCK_WORDS = 1 << 22

# States of each half; a word's key is low + (lo_state + N_LO * hi_state) * n_low, so the
# two table lookups add up to the final bincount key with no third lookup.
_LO_OK, _LO_ZERO, _LO_INV, _LO_MAL = range(4)
_HI_OK, _HI_ART, _HI_ZERO, _HI_ZERO_ART, _HI_INV, _HI_MAL = range(6)
_N_LO, _N_HI = 4, 6


def default_engine() -> str:
    """numba where it is installed, else numpy."""
    return "numba" if HAVE_NUMBA else "numpy"


def _state_classes() -> np.ndarray:
    """Class code of each (hi_state, lo_state) pair, with docs/design.md's precedence."""
    cls = np.full((_N_HI, _N_LO), HIT, np.int64)
    for hs in range(_N_HI):
        for ls in range(_N_LO):
            if hs == _HI_MAL or ls == _LO_MAL:
                cls[hs, ls] = MALFORMED
            elif hs == _HI_INV or ls == _LO_INV:
                cls[hs, ls] = INVALID_PHASE
            elif hs in (_HI_ZERO, _HI_ZERO_ART) and ls == _LO_ZERO:
                cls[hs, ls] = NO_HIT
            elif hs in (_HI_ART, _HI_ZERO_ART):
                cls[hs, ls] = ARTIFACT
    return cls


STATE_CLASSES = _state_classes()


@dataclass(frozen=True)
class WordTables:
    """Lookup tables of the numpy engine for one TDC count, bounds and histogram mode.

    ``mode="d1st"`` histograms D1st over hits (512 bins per TDC); ``mode="d2nd"``
    histograms D2nd over hit candidates (256 bins per TDC), which is what
    :func:`stages.artifact.estimate_bounds` needs.
    """

    n_tdc: int
    bounds: ArtifactBounds
    mode: str = "d1st"
    #: address of the first TDC of the stream: a worker of a fan-out by TDC range sees the
    #: words of TDCs ``tdc_offset .. tdc_offset + n_tdc - 1`` (address = offset + position)
    tdc_offset: int = 0

    def __post_init__(self):
        if not 1 <= self.n_tdc <= MAX_TDC:
            raise ValueError(f"n_tdc must be in 1..{MAX_TDC}, found {self.n_tdc}")
        if not 0 <= self.tdc_offset <= MAX_TDC - self.n_tdc:
            raise ValueError(f"TDCs {self.tdc_offset}..{self.tdc_offset + self.n_tdc - 1} "
                             f"exceed the address range 0..{MAX_TDC - 1}")
        if self.bounds.n_tdc != self.n_tdc:
            raise ValueError(f"bounds are for {self.bounds.n_tdc} TDCs, data has {self.n_tdc}")
        if self.mode not in ("d1st", "d2nd"):
            raise ValueError(f"mode must be 'd1st' or 'd2nd', found {self.mode!r}")

    @cached_property
    def in_block(self) -> np.ndarray:
        return self.bounds.in_block()

    @cached_property
    def in_block_u8(self) -> np.ndarray:
        """``in_block`` as bytes, for the C kernel."""
        return np.ascontiguousarray(self.in_block, np.uint8)

    @cached_property
    def _numpy_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(lut_lo, lut_hi, pattern_lo, pattern_pos), built on first use by the numpy engine."""
        n_bins = self.n_bins
        n_low = self.n_tdc * n_bins
        x = np.arange(1 << 16, dtype=np.int64)
        # Low half after XOR with the expected pattern: bits 0..11 must be zero.
        p1_raw = x >> 12
        p1 = PHASE_DECODE[p1_raw].astype(np.int64)
        lo_state = np.where(p1_raw == 0, _LO_ZERO, _LO_OK)
        lo_state = np.where(p1 < 0, _LO_INV, lo_state)
        lo_state = np.where((x & 0xFFF) != 0, _LO_MAL, lo_state)
        lo_low = np.where((lo_state == _LO_OK) & (self.mode == "d1st"), p1 * self.n_tdc, 0)
        lo = lo_low + lo_state * n_low
        # High half: bit 15 is word bit 31; C2nd 14..10, P2nd 9..6, C1st 5..0.
        c1 = x & 0x3F
        p2 = PHASE_DECODE[(x >> 6) & 0xF].astype(np.int64)
        d2 = np.clip(((x >> 10) & 0x1F) * 8 + p2, 0, N_CODES_2ND - 1)
        low = c1 * 8 if self.mode == "d1st" else d2
        art = ~self.in_block[:, d2].T  # (65536, n_tdc)
        zero = ((x & 0x7FFF) == 0)[:, None]
        hi_state = np.where(zero, np.where(art, _HI_ZERO_ART, _HI_ZERO),
                            np.where(art, _HI_ART, _HI_OK))
        hi_state = np.where((p2 < 0)[:, None], _HI_INV, hi_state)
        hi_state = np.where(((x & 0x8000) != 0)[:, None], _HI_MAL, hi_state)
        # Row-major over (high half, position): entry hi * n_tdc + pos.
        hi = (np.arange(self.n_tdc)[None, :] + low[:, None] * self.n_tdc
              + hi_state * (_N_LO * n_low))
        # Position patterns, long enough for any chunk start: expected low half per position
        # (marker bit 9 and the address), and the position itself.
        pos = np.arange(CHUNK_WORDS + self.n_tdc) % self.n_tdc
        return (lo.astype(np.intp), hi.astype(np.intp).ravel(),
                ((1 << 9) | ((pos + self.tdc_offset) << 1)).astype(np.uint16),
                pos.astype(np.int32))

    @property
    def n_bins(self) -> int:
        return N_CODES if self.mode == "d1st" else N_CODES_2ND


_LO, _HI = (0, 1) if sys.byteorder == "little" else (1, 0)


class _NumpyBuffers:
    """Preallocated temporaries of the numpy engine (fresh allocations page-fault)."""

    def __init__(self):
        self.x = np.empty(CHUNK_WORDS, np.intp)
        self.a = np.empty(CHUNK_WORDS, np.intp)
        self.b = np.empty(CHUNK_WORDS, np.intp)
        self.keys = np.empty(BLOCK_WORDS, np.intp)


_BUFFERS: dict[int, _NumpyBuffers] = {}


def _accumulate_numpy(words: np.ndarray, first_word: int, tables: WordTables,
                      hits: np.ndarray, class_counts: np.ndarray, artifacts=None) -> None:
    n_tdc, n_bins = tables.n_tdc, tables.n_bins
    halves = words.view(np.uint16).reshape(-1, 2)
    n_keys = _N_HI * _N_LO * n_tdc * n_bins
    lut_lo, lut_hi, pattern_lo, pattern_pos = tables._numpy_tables
    # Temporaries are per thread: stages may run in threads of one process.
    buf = _BUFFERS.setdefault(threading.get_ident(), _NumpyBuffers())
    total = np.zeros(n_keys, np.int64)
    for block in range(0, words.size, BLOCK_WORDS):
        block_end = min(block + BLOCK_WORDS, words.size)
        for start in range(block, block_end, CHUNK_WORDS):
            n = min(start + CHUNK_WORDS, block_end) - start
            p0 = (first_word + start) % n_tdc
            x, a, b = buf.x[:n], buf.a[:n], buf.b[:n]
            key = buf.keys[start - block:start - block + n]
            np.bitwise_xor(halves[start:start + n, _LO], pattern_lo[p0:p0 + n], out=x,
                           dtype=np.intp)
            # mode='clip' skips the bounds-error path (indices are in range by construction)
            np.take(lut_lo, x, out=key, mode="clip")
            np.multiply(halves[start:start + n, _HI], n_tdc, out=a, dtype=np.intp)
            a += pattern_pos[p0:p0 + n]
            np.take(lut_hi, a, out=b, mode="clip")
            key += b
        total += np.bincount(buf.keys[:block_end - block], minlength=n_keys)
    per = total.reshape(_N_HI * _N_LO, n_bins, n_tdc)
    states = STATE_CLASSES.ravel()
    hits += per[states == HIT].sum(axis=0).T.astype(np.uint64)
    if artifacts is not None:  # an artifact's key holds its code as a hit's does
        artifacts += per[states == ARTIFACT].sum(axis=0).T.astype(np.uint64)
    per_tdc = per.sum(axis=1)  # (states, n_tdc)
    for cls in range(N_CLASSES):
        class_counts[cls] += per_tdc[states == cls].sum(axis=0).astype(np.uint64)


# --- the numba engine's loops ------------------------------------------------------------
#
# Both loops run in two passes over blocks of ``SIFT`` words. The first pass only finds the
# words that are not their position's plain no_hit word (the marker and address with an
# empty payload: ~80 % of a capture), without a branch (:func:`_sift`); the second
# classifies and counts those (:func:`_classify`). A single pass branched on every word
# for an outcome that light makes random, and paid a mispredicted branch on most hits:
# at 5-30 % hits the two passes run 1.5-3x as fast; at 50 % as fast; at 90 % (a density
# test brighter than the thesis's) 0.8x (docs/performance.md: a block-by-block switch to
# one pass won back ~10 % there, within the noise, and was not kept). The loops count the
# words of the other classes only; each TDC's no_hit words are its words less those, at
# the end of a call (:func:`_count_no_hits`). The helpers are plain Python here;
# ``_numba_loop`` inlines their compiled twins.

#: words per block of the two passes (their index buffer, 64 KiB, stays in L2)
SIFT = 4096


def _others(class_counts, k):
    """Words of TDC ``k`` counted in a class other than no_hit."""
    total = np.uint64(0)
    for c in range(N_CLASSES):
        if c != NO_HIT:
            total += class_counts[c, k]
    return total


def _mark_others(class_counts, n_tdc, scratch):
    """Keep each TDC's :func:`_others` in ``scratch[2]`` (at the start of a call)."""
    for k in range(n_tdc):
        scratch[2, k] = np.int64(_others(class_counts, k))


def _count_no_hits(class_counts, pos0, n, n_tdc, scratch):
    """At the end of a call over ``n`` words from position ``pos0``: the no_hit words of
    each TDC are its words less those the call counted in another class (the loops count
    only those: a plain no_hit word is four fifths of a capture)."""
    full, rem = n // n_tdc, n % n_tdc
    for k in range(n_tdc):
        mine = full + (1 if (k - pos0) % n_tdc < rem else 0)
        class_counts[NO_HIT, k] += np.uint64(mine) - (_others(class_counts, k)
                                                      - np.uint64(scratch[2, k]))


def _sift(words, b0, b1, pos, n_tdc, offset, scratch):
    """Indices (``scratch[0]``) and positions (``scratch[1]``) of the words of
    ``words[b0:b1]`` (the first at position ``pos``) that are not a plain no_hit word
    with their position's address (``offset +`` position); returns how many."""
    m = 0
    marker = np.uint32(MARKER_VALUE)
    for i in range(b0, b1):
        scratch[0, m] = i
        scratch[1, m] = pos
        m += words[i] != marker | np.uint32((pos + offset) << 1)
        pos += 1
        if pos == n_tdc:
            pos = 0
    return m


def _classify(w, addr, phase):
    """(class, phase 1, phase 2) of a word expected at address ``addr`` (docs/design.md's
    precedence; a hit's phases index its codes, others' are 0)."""
    if (w & np.uint32(MARKER_MASK)) != np.uint32(MARKER_VALUE) or ((w >> 1) & 0xFF) != addr:
        return MALFORMED, 0, 0
    p1 = np.int64(phase[(w >> 12) & 0xF])
    p2 = np.int64(phase[(w >> 22) & 0xF])
    if p1 < 0 or p2 < 0:
        return INVALID_PHASE, 0, 0
    if (w & 0x7FFFF000) == 0:
        return NO_HIT, 0, 0
    return HIT, p1, p2


def _kernel_loop(words, pos0, n_tdc, phase, inblock, hits, class_counts, d2mode, offset,
                 arts, count_arts, scratch):
    _mark_others(class_counts, n_tdc, scratch)
    for b0 in range(0, words.size, SIFT):
        m = _sift(words, b0, min(words.size, b0 + SIFT), (pos0 + b0) % n_tdc, n_tdc, offset,
                  scratch)
        for j in range(m):
            w, pos = words[scratch[0, j]], scratch[1, j]
            cls, p1, p2 = _classify(w, pos + offset, phase)
            if cls == HIT:
                d2 = ((w >> 26) & 0x1F) * 8 + p2
                code = d2 if d2mode else ((w >> 16) & 0x3F) * 8 + p1
                if inblock[pos, d2]:
                    hits[pos, code] += np.uint64(1)
                else:
                    cls = ARTIFACT
                    if count_arts:
                        arts[pos, code] += np.uint64(1)
            if cls != NO_HIT:
                class_counts[cls, pos] += np.uint64(1)
    _count_no_hits(class_counts, pos0, words.size, n_tdc, scratch)


def _accumulate_numba(words, first_word, tables, hits, class_counts, artifacts=None):
    count = artifacts is not None
    arts = artifacts if count else np.zeros((1, 1), np.uint64)
    scratch = _scratch()
    fn = _native("kernel")
    if fn is not None and all(_plain(a, np.uint64) for a in (hits, class_counts, arts)):
        fn(words.ctypes.data, words.size, first_word % tables.n_tdc, tables.n_tdc,
           PHASE_DECODE.ctypes.data, tables.in_block_u8.ctypes.data, hits.ctypes.data,
           hits.shape[1], class_counts.ctypes.data, tables.mode == "d2nd",
           tables.tdc_offset, arts.ctypes.data, arts.shape[0], arts.shape[1], count,
           scratch.ctypes.data)
        return
    _jitted("kernel")(words, first_word % tables.n_tdc, tables.n_tdc, PHASE_DECODE,
                      tables.in_block, hits, class_counts, tables.mode == "d2nd",
                      tables.tdc_offset, arts, count, scratch)


def accumulate(words: np.ndarray, first_word: int, tables: WordTables, hits: np.ndarray,
               class_counts: np.ndarray, engine: str | None = None,
               artifacts: np.ndarray | None = None) -> None:
    """Fold native uint32 ``words`` into ``hits`` and ``class_counts`` in place. The
    arrays are one caller's: two calls at once on the same ``class_counts`` are not
    allowed (the numba engine derives a call's no_hit words from how much the other
    classes grew during it; threads each fill their own state and merge them).

    Parameters
    ----------
    words : ndarray of uint32
        Contiguous native-order words; word ``i`` is at stream position
        ``first_word + i`` and belongs to TDC ``(first_word + i) % n_tdc``.
    first_word : int
        Stream index of ``words[0]``.
    tables : WordTables
    hits : ndarray of uint64, shape (n_tdc, tables.n_bins)
    class_counts : ndarray of uint64, shape (N_CLASSES, n_tdc)
    engine : {"numba", "numpy"}, optional
        Defaults to numba where it is installed.
    artifacts : ndarray of uint64, shape (n_tdc, tables.n_bins), optional
        Where to count the artifact words by their code (not counted when None).
    """
    words = np.ascontiguousarray(words, dtype=np.uint32)
    engine = engine or default_engine()
    if engine == "numba":
        if not HAVE_NUMBA:
            raise RuntimeError("engine='numba' requested but numba is not installed")
        _accumulate_numba(words, first_word, tables, hits, class_counts, artifacts)
    elif engine == "numpy":
        _accumulate_numpy(words, first_word, tables, hits, class_counts, artifacts)
    else:
        raise ValueError(f"engine must be one of {ENGINES}, found {engine!r}")


# --- one pass without bounds: candidates by code, D2nd marginal, and the edge words ------
#
# Without a calibration the artifact bounds come from the capture's own D2nd histogram, so
# a word's class is known only at the end. Counting (TDC, D1st, D2nd) jointly answers any
# bounds, but its 16.7 M cells are touched at random by every word (141 M words/s at 5 %
# hits, 59 at 30 %, one core: cache misses). Instead: every candidate (a word that is
# neither malformed, invalid nor no_hit) is counted by D1st and by D2nd, both small tables,
# and only candidates whose D2nd lies outside a provisional core of each TDC's block (from
# the capture's first chunk, shrunk by a margin) are also kept: the edge words. The final
# bounds come from the whole D2nd marginal; when each contains its TDC's core, the hits
# are the candidates less the edge words outside the bounds, exactly.
#
# The edge words (the artifact and the core's margins: ~1 % of the words) are kept as keys
# ``(tdc * 256 + D2nd) * 512 + D1st`` in a buffer, not counted in a dense (tdc, D2nd, D1st)
# table: that table's 134 MB are touched sparsely, and each touch faulted in a zeroed page
# (a 2 MiB one where numpy asks for huge pages): 30-250 ms per table, per thread, on a
# capture whose edge words were 7 500. The dense table takes only the keys that do not
# fit in the buffer (a dark capture, where every candidate is an edge word).

#: edge-word keys a buffer holds before the dense table takes the rest (32 MiB)
EDGE_KEYS = 1 << 23


def edge_key(tdc, d2nd, d1st):
    """The key of an edge word (see the comment above)."""
    return (tdc * N_CODES_2ND + d2nd) * N_CODES + d1st


def accumulate_self_bounded(words: np.ndarray, first_word: int, n_tdc: int,
                            core_lo: np.ndarray, core_hi: np.ndarray, cand: np.ndarray,
                            d2nd: np.ndarray, keys: np.ndarray, fill: np.ndarray,
                            edge: np.ndarray, class_counts: np.ndarray,
                            engine: str | None = None) -> None:
    """Fold ``words`` into the one-pass state in place (see the comment above); the state
    is one caller's (see :func:`accumulate`).

    Parameters
    ----------
    words : ndarray of uint32
        Native-order words; word ``i`` is at stream position ``first_word + i``.
    core_lo, core_hi : ndarray of int64, shape (n_tdc,)
        Each TDC's provisional core [core_lo, core_hi] of D2nd (empty when lo > hi: every
        candidate of that TDC is then an edge word).
    cand : uint64 (n_tdc, 512)
        Candidates by D1st.
    d2nd : uint64 (n_tdc, 256)
        Candidates by D2nd.
    keys : uint32 (capacity,), fill : int64 (1,)
        Edge words by :func:`edge_key`, ``keys[:fill[0]]`` used.
    edge : uint64 (n_tdc, 256, 512)
        Edge words that found the buffer full, by (D2nd, D1st); any array when ``fill[0] +
        words.size <= keys.size`` (then none can).
    class_counts : uint64 (N_CLASSES, n_tdc)
        Malformed, invalid_phase and no_hit as usual; every candidate under ``HIT``.
    """
    words = np.ascontiguousarray(words, dtype=np.uint32)
    core_lo = np.ascontiguousarray(core_lo, np.int64)
    core_hi = np.ascontiguousarray(core_hi, np.int64)
    if fill[0] + words.size > keys.size and edge.shape != (n_tdc, N_CODES_2ND, N_CODES):
        raise ValueError("the key buffer may fill up: edge must be (n_tdc, 256, 512)")
    engine = engine or default_engine()
    if engine == "numba":
        if not HAVE_NUMBA:
            raise RuntimeError("engine='numba' requested but numba is not installed")
        scratch = _scratch()
        fn = _native("self_bounded")
        if fn is not None and all(_plain(a, np.uint64) for a in (cand, d2nd, edge,
                                                                  class_counts)) \
                and _plain(keys, np.uint32) and _plain(fill, np.int64):
            fn(words.ctypes.data, words.size, first_word % n_tdc, n_tdc,
               PHASE_DECODE.ctypes.data, core_lo.ctypes.data, core_hi.ctypes.data,
               cand.ctypes.data, d2nd.ctypes.data, keys.ctypes.data, keys.size,
               fill.ctypes.data, edge.ctypes.data, edge.shape[0], edge.shape[1],
               edge.shape[2], class_counts.ctypes.data, scratch.ctypes.data)
        else:
            _jitted("self_bounded")(words, first_word % n_tdc, n_tdc, PHASE_DECODE, core_lo,
                                    core_hi, cand, d2nd, keys, fill, edge, class_counts,
                                    scratch)
    elif engine == "numpy":
        _self_bounded_numpy(words, first_word, n_tdc, core_lo, core_hi, cand, d2nd, keys,
                            fill, edge, class_counts)
    else:
        raise ValueError(f"engine must be one of {ENGINES}, found {engine!r}")


def _self_bounded_numpy(words, first_word, n_tdc, core_lo, core_hi, cand, d2nd, keys, fill,
                        edge, class_counts):
    from stages.codec import classify_words, decode_fields

    f = decode_fields(words)
    # unbounded: every candidate is a HIT here; the reference classifier knows the rest
    cls = classify_words(words, n_tdc, first_word, fields=f)
    pos = ((np.arange(words.size, dtype=np.int64) + first_word) % n_tdc)
    class_counts += np.bincount(cls.astype(np.int64) * n_tdc + pos,
                                minlength=N_CLASSES * n_tdc).reshape(N_CLASSES, n_tdc) \
        .astype(np.uint64)
    c = cls == HIT
    p, d1, d2 = pos[c], f.d1st[c].astype(np.int64), f.d2nd[c].astype(np.int64)
    cand += np.bincount(p * N_CODES + d1, minlength=cand.size).reshape(cand.shape) \
        .astype(np.uint64)
    d2nd += np.bincount(p * N_CODES_2ND + d2, minlength=d2nd.size).reshape(d2nd.shape) \
        .astype(np.uint64)
    out = (d2 < core_lo[p]) | (d2 > core_hi[p])
    key = edge_key(p[out], d2[out], d1[out])
    n0 = int(fill[0])
    room = min(key.size, keys.size - n0)  # in word order, as the loop fills it
    keys[n0:n0 + room] = key[:room]
    fill[0] = n0 + room
    if room < key.size:
        cells, n = np.unique(key[room:], return_counts=True)
        edge.reshape(-1)[cells] += n.astype(np.uint64)


def _self_bounded_loop(words, pos0, n_tdc, phase, core_lo, core_hi, cand, d2nd, keys, fill,
                       edge, class_counts, scratch):
    _mark_others(class_counts, n_tdc, scratch)
    nk = fill[0]
    for b0 in range(0, words.size, SIFT):
        m = _sift(words, b0, min(words.size, b0 + SIFT), (pos0 + b0) % n_tdc, n_tdc, 0,
                  scratch)
        for j in range(m):
            w, pos = words[scratch[0, j]], scratch[1, j]
            cls, p1, p2 = _classify(w, pos, phase)
            if cls == HIT:
                d1 = ((w >> 16) & 0x3F) * 8 + p1
                d2 = ((w >> 26) & 0x1F) * 8 + p2
                cand[pos, d1] += 1
                d2nd[pos, d2] += 1
                if d2 < core_lo[pos] or d2 > core_hi[pos]:
                    if nk < keys.size:
                        keys[nk] = (pos * 256 + d2) * 512 + d1
                        nk += 1
                    else:
                        edge[pos, d2, d1] += 1
            if cls != NO_HIT:
                class_counts[cls, pos] += np.uint64(1)
    fill[0] = nk
    _count_no_hits(class_counts, pos0, words.size, n_tdc, scratch)


# --- the sparse form of raw words --------------------------------------------------------
#
# Most of a capture's words are their position's plain no_hit word (the marker and the
# address, nothing else: 95 % of them at 5 % hits), and a word equal to that is exactly a
# no_hit word (any other word is malformed, invalid, a hit or an artifact). So n words are
# carried whole by the others alone: their indices in the span, ascending, and the words.
# The source makes that form as it reads (one pass, ``_encode_loop``), cutting a fan-out's
# TDC ranges in the same pass, and a histogram worker folds it without looking at the
# no_hit words (``_sparse_loop``: the kernel's second pass, with no sift): at 5 % hits a
# message is a tenth of the words' bytes and the fold a fraction of the dense one's.


def _bswap32(w):
    return (((w & np.uint32(0xFF)) << np.uint32(24)) | ((w & np.uint32(0xFF00)) << np.uint32(8))
            | ((w >> np.uint32(8)) & np.uint32(0xFF00)) | (w >> np.uint32(24)))


def _encode_loop(words, pos0, n_tdc, pattern, lo, hi, swap, index, out, sizes):
    """The sparse form of the words of positions ``lo .. hi - 1`` in ``words`` (the first
    at position ``pos0``): ``index[:sizes[1]]`` (in the range's own word order) and
    ``out[:sizes[1]]``; ``sizes[0]``: the range's words. ``pattern`` is each position's
    no_hit word as ``words`` hold it; ``swap`` byte-swaps the kept words to native order.
    (Stores without a branch, as :func:`_sift`; one call per range: a helper taking every
    range in one pass ran 3x slower.)"""
    m = 0
    sub = 0
    pos = pos0
    if lo == 0 and hi == n_tdc:  # every position (no fan-out): no range test per word
        for i in range(words.size):
            w = words[i]
            index[m] = i
            out[m] = w
            m += w != pattern[pos]
            pos += 1
            if pos == n_tdc:
                pos = 0
        sub = words.size
    for i in range(words.size if sub == 0 else 0):
        if pos >= lo and pos < hi:
            w = words[i]
            index[m] = sub
            out[m] = w
            m += w != pattern[pos]
            sub += 1
        pos += 1
        if pos == n_tdc:
            pos = 0
    if swap:
        for j in range(m):
            out[j] = _bswap32(out[j])
    sizes[0] = sub
    sizes[1] = m


def _sparse_loop(index, words, n, pos0, n_tdc, phase, inblock, hits, class_counts, d2mode,
                 offset, arts, count_arts, scratch):
    """Fold ``n`` words given in sparse form (``index``, ``words``; the first of the span
    at position ``pos0``) as :func:`_kernel_loop` folds them whole. (Its loop body is
    :func:`_kernel_loop`'s, written out: as an inlined helper numba made it 4-7x slower.)"""
    _mark_others(class_counts, n_tdc, scratch)
    for j in range(words.size):
        w = words[j]
        pos = (pos0 + index[j]) % n_tdc
        cls, p1, p2 = _classify(w, pos + offset, phase)
        if cls == HIT:
            d2 = ((w >> 26) & 0x1F) * 8 + p2
            code = d2 if d2mode else ((w >> 16) & 0x3F) * 8 + p1
            if inblock[pos, d2]:
                hits[pos, code] += np.uint64(1)
            else:
                cls = ARTIFACT
                if count_arts:
                    arts[pos, code] += np.uint64(1)
        if cls != NO_HIT:
            class_counts[cls, pos] += np.uint64(1)
    _count_no_hits(class_counts, pos0, n, n_tdc, scratch)


@functools.lru_cache(maxsize=64)
def no_hit_words(n_tdc: int, tdc_offset: int = 0, swapped: bool = False) -> np.ndarray:
    """Each position's plain no_hit word (uint32, read-only): marker bit 9 and the address
    (its 8 bits); ``swapped``: byte-swapped (as big-endian words hold it). The one
    definition: the sparse form and the journal's ``zstd-nohit`` frames both use it."""
    address = (np.arange(n_tdc, dtype=np.uint32) + np.uint32(tdc_offset)) & np.uint32(0xFF)
    out = np.uint32(MARKER_VALUE) | (address << np.uint32(1))
    if swapped:
        out = out.byteswap()
    out.flags.writeable = False
    return out


@dataclass(frozen=True)
class SparseWords:
    """``n`` consecutive raw words in sparse form: ``index`` (uint32, ascending, each below
    ``n``) of the words that are not their position's plain no_hit word, and those
    ``words`` (native uint32). Sliced like the words (``sw[a:b]``), and ``size`` is ``n``,
    so code that cuts a stream of words cuts this alike."""

    n: int
    index: np.ndarray
    words: np.ndarray

    @property
    def size(self) -> int:
        return self.n

    def __getitem__(self, part: slice) -> SparseWords:
        start, stop, step = part.indices(self.n)
        if step != 1:
            raise ValueError("sparse words are cut by ranges only")
        stop = max(start, stop)
        lo, hi = np.searchsorted(self.index, [start, stop])
        return SparseWords(stop - start, self.index[lo:hi] - np.uint32(start),
                           self.words[lo:hi])

    def problem(self) -> str | None:
        """What makes this not a sparse form of ``n`` words (None: nothing): a sender's
        message is checked before it is folded, as whole words are by their class."""
        if self.index.dtype != np.uint32 or self.words.dtype != np.uint32:
            return f"index and words must be uint32, found {self.index.dtype}, {self.words.dtype}"
        if self.index.shape != self.words.shape or self.index.ndim != 1:
            return f"{self.index.size} indices for {self.words.size} words"
        if self.index.size > self.n or (self.index.size and int(self.index[-1]) >= self.n):
            return f"an index beyond the span of {self.n} words"
        if self.index.size > 1 and not bool(np.all(self.index[1:] > self.index[:-1])):
            return "indices not strictly ascending"
        return None

    def cut(self, first_word: int, n_tdc: int, ranges: list[tuple[int, int]]
            ) -> list[SparseWords]:
        """Each TDC range's words (a fan-out's), as :func:`sparse_encode` with ``ranges``
        gives them, from the form of whole cycles starting at ``first_word`` (numpy over
        the listed words only: a tenth of the words at 5 % hits)."""
        if first_word % n_tdc or self.n % n_tdc:
            raise ValueError(f"a cut by TDC range needs whole cycles: {self.n} words at word "
                             f"{first_word} with {n_tdc} TDCs per cycle")
        cycle, pos = np.divmod(self.index.astype(np.int64), n_tdc)
        out = []
        for a, b in ranges:
            mine = (pos >= a) & (pos < b)
            out.append(SparseWords(self.n // n_tdc * (b - a),
                                   (cycle[mine] * (b - a) + pos[mine] - a).astype(np.uint32),
                                   self.words[mine]))
        return out

    def dense(self, first_word: int, n_tdc: int, tdc_offset: int = 0) -> np.ndarray:
        """The words whole (native uint32), the first at stream index ``first_word``."""
        pos = (first_word + np.arange(self.n, dtype=np.int64)) % n_tdc
        out = no_hit_words(n_tdc, tdc_offset)[pos]
        out[self.index.astype(np.intp)] = self.words
        return out


def sparse_encode(words: np.ndarray, first_word: int, n_tdc: int,
                  ranges: list[tuple[int, int]] | None = None,
                  engine: str | None = None) -> list[SparseWords]:
    """The sparse form of ``words`` (uint32 of either byte order, word ``i`` at stream
    index ``first_word + i``), one per TDC range of ``ranges`` (default: one range, all
    TDCs): range (a, b)'s words are those of positions a..b-1, in stream order, as a
    fan-out by TDC range sends them (its first at ``first_word // n_tdc * (b - a)`` when
    ``first_word`` starts a cycle)."""
    words = np.ascontiguousarray(words).ravel()
    if words.dtype not in (np.dtype("<u4"), np.dtype(">u4")):
        raise TypeError(f"words must be uint32, found {words.dtype}")
    ranges = ranges or [(0, n_tdc)]
    swap = not words.dtype.isnative
    raw = words.view(np.uint32)
    pattern = no_hit_words(n_tdc, 0, swap)
    pos0 = first_word % n_tdc
    engine = engine or default_engine()
    if engine not in ENGINES:
        raise ValueError(f"engine must be one of {ENGINES}, found {engine!r}")
    parts, sizes = [], []
    if engine == "numpy":
        pos = (pos0 + np.arange(raw.size, dtype=np.int64)) % n_tdc
        differs = raw != pattern[pos]
    for a, b in ranges:
        if engine == "numba":
            cap = raw.size // n_tdc * (b - a) + min(raw.size, b - a)  # the range's words, at most
            index, out = np.empty(cap, np.uint32), np.empty(cap, np.uint32)
            got = np.zeros(2, np.int64)
            fn = _native("encode")
            if fn is not None:
                fn(raw.ctypes.data, raw.size, pos0, n_tdc, pattern.ctypes.data, a, b, swap,
                   index.ctypes.data, out.ctypes.data, got.ctypes.data)
            else:
                _jitted("encode")(raw, pos0, n_tdc, pattern, a, b, swap, index, out, got)
            parts.append((index[:got[1]], out[:got[1]]))
            sizes.append(got[0])
        else:
            mine = (pos >= a) & (pos < b)
            keep = mine & differs
            kept = raw[keep]
            parts.append(((np.cumsum(mine) - 1)[keep].astype(np.uint32),
                          kept.byteswap() if swap else kept))
            sizes.append(int(mine.sum()))
    return [SparseWords(int(n), i, w) for (i, w), n in zip(parts, sizes, strict=True)]


def accumulate_sparse(sparse: SparseWords, first_word: int, tables: WordTables,
                      hits: np.ndarray, class_counts: np.ndarray, engine: str | None = None,
                      artifacts: np.ndarray | None = None) -> None:
    """Fold words given in sparse form as :func:`accumulate` folds them whole (the same
    counts; ``sparse`` checked by its :meth:`SparseWords.problem` first)."""
    engine = engine or default_engine()
    if engine == "numpy":
        _accumulate_numpy(sparse.dense(first_word, tables.n_tdc, tables.tdc_offset),
                          first_word, tables, hits, class_counts, artifacts)
        return
    if engine != "numba":
        raise ValueError(f"engine must be one of {ENGINES}, found {engine!r}")
    count = artifacts is not None
    arts = artifacts if count else np.zeros((1, 1), np.uint64)
    scratch = _scratch()
    index = np.ascontiguousarray(sparse.index, np.uint32)
    words = np.ascontiguousarray(sparse.words, np.uint32)
    pos0 = first_word % tables.n_tdc
    fn = _native("sparse")
    if fn is not None and all(_plain(a, np.uint64) for a in (hits, class_counts, arts)):
        fn(index.ctypes.data, words.ctypes.data, words.size, sparse.n, pos0, tables.n_tdc,
           PHASE_DECODE.ctypes.data, tables.in_block_u8.ctypes.data, hits.ctypes.data,
           hits.shape[1], class_counts.ctypes.data, tables.mode == "d2nd",
           tables.tdc_offset, arts.ctypes.data, arts.shape[0], arts.shape[1], count,
           scratch.ctypes.data)
        return
    _jitted("sparse")(index, words, sparse.n, pos0, tables.n_tdc, PHASE_DECODE,
                      tables.in_block, hits, class_counts, tables.mode == "d2nd",
                      tables.tdc_offset, arts, count, scratch)


# --- the numba engine: the loops above, compiled -----------------------------------------
#
# The same loop bodies run either as numba-dispatched functions (``_jitted``, numba's cache)
# or as C callbacks loaded without numba (``_native``, stages.nativecode): arrays go in as
# pointers and sizes and are rebuilt with ``numba.carray``. Either way the loop is compiled
# with the helpers it calls compiled and inlined (``_numba_loop``). A C callback cannot
# allocate, so the index buffer of the two passes comes from the caller (``_scratch``).

_P, _I = ctypes.c_void_p, ctypes.c_int64
_ARGTYPES = {
    # words, n, pos0, n_tdc, phase, inblock(u8), hits, n_bins, class_counts, d2mode,
    # offset, arts, arts_rows, arts_cols, count_arts, scratch (int64 (3, SIFT))
    "kernel": [_P, _I, _I, _I, _P, _P, _P, _I, _P, _I, _I, _P, _I, _I, _I, _P],
    # words, n, pos0, n_tdc, phase, core_lo, core_hi, cand, d2nd, keys, capacity, fill,
    # edge, edge dims (3), class_counts, scratch
    "self_bounded": [_P, _I, _I, _I, _P, _P, _P, _P, _P, _P, _I, _P, _P, _I, _I, _I, _P, _P],
    # index, words, m, n, pos0, n_tdc, phase, inblock(u8), hits, n_bins, class_counts,
    # d2mode, offset, arts, arts_rows, arts_cols, count_arts, scratch
    "sparse": [_P, _P, _I, _I, _I, _I, _P, _P, _P, _I, _P, _I, _I, _P, _I, _I, _I, _P],
    # words, n, pos0, n_tdc, pattern, lo, hi, swap, index, out, sizes
    "encode": [_P, _I, _I, _I, _P, _I, _I, _I, _P, _P, _P],
}
_LOOPS = {"kernel": _kernel_loop, "self_bounded": _self_bounded_loop,
          "sparse": _sparse_loop, "encode": _encode_loop}
_HELPERS = (_others, _mark_others, _count_no_hits, _sift, _classify, _bswap32)
_JITTED: dict = {}


def _scratch() -> np.ndarray:
    """The index buffer of one call of a loop, and room for a count per TDC (96 KiB: a
    call per chunk of words)."""
    return np.empty((3, SIFT), np.int64)


def _numba_loop(name: str, **options):
    """The loop ``name`` compiled by numba with ``options``, its helpers inlined: the
    functions' code objects with globals where the helpers' names are their compiled
    twins (the module's own globals keep the plain functions: the loops also run in
    Python)."""
    import types

    import numba

    def twin(f, scope):
        g = types.FunctionType(f.__code__, scope, f.__name__, f.__defaults__)
        g.__qualname__, g.__module__ = f.__qualname__, f.__module__
        return g

    scope = dict(_LOOPS[name].__globals__)  # helpers are typed at the loop's first compile
    scope.update({h.__name__: numba.njit(inline="always")(twin(h, scope)) for h in _HELPERS})
    return numba.njit(**options)(twin(_LOOPS[name], scope))


def _plain(a: np.ndarray, dtype) -> bool:
    return a.dtype == dtype and a.flags.c_contiguous and a.flags.writeable


def _jitted(name: str):
    """The loop ``name`` through numba's dispatcher (and numba's on-disk cache)."""
    fn = _JITTED.get(name)
    if fn is None:
        fn = _JITTED[name] = _numba_loop(name, cache=True, nogil=True)
    return fn


def _native(name: str):
    """The loop ``name`` as a C kernel loaded without numba, or None (then ``_jitted``)."""
    from stages import nativecode

    return nativecode.kernel(name, __file__, _ARGTYPES[name], lambda: _build(name))


def _build(name: str):
    import numba
    from numba import carray, types

    loop = _numba_loop(name, nogil=True)
    p = types.CPointer
    u32, u64, i64, i8, u8 = types.uint32, types.uint64, types.int64, types.int8, types.uint8
    if name == "kernel":
        sig = types.void(p(u32), i64, i64, i64, p(i8), p(u8), p(u64), i64, p(u64), i64,
                         i64, p(u64), i64, i64, i64, p(i64))

        def c_kernel(w, n, pos0, n_tdc, phase, inblock, hits, n_bins, cc, d2mode, offset,
                     arts, arts_rows, arts_cols, count_arts, scratch):
            loop(carray(w, (n,)), pos0, n_tdc, carray(phase, (16,)),
                 carray(inblock, (n_tdc, N_CODES_2ND)), carray(hits, (n_tdc, n_bins)),
                 carray(cc, (N_CLASSES, n_tdc)), d2mode != 0, offset,
                 carray(arts, (arts_rows, arts_cols)), count_arts != 0,
                 carray(scratch, (3, SIFT)))

        return numba.cfunc(sig, nopython=True)(c_kernel)
    if name == "sparse":
        sig = types.void(p(u32), p(u32), i64, i64, i64, i64, p(i8), p(u8), p(u64), i64,
                         p(u64), i64, i64, p(u64), i64, i64, i64, p(i64))

        def c_sparse(index, w, m, n, pos0, n_tdc, phase, inblock, hits, n_bins, cc, d2mode,
                     offset, arts, arts_rows, arts_cols, count_arts, scratch):
            loop(carray(index, (m,)), carray(w, (m,)), n, pos0, n_tdc, carray(phase, (16,)),
                 carray(inblock, (n_tdc, N_CODES_2ND)), carray(hits, (n_tdc, n_bins)),
                 carray(cc, (N_CLASSES, n_tdc)), d2mode != 0, offset,
                 carray(arts, (arts_rows, arts_cols)), count_arts != 0,
                 carray(scratch, (3, SIFT)))

        return numba.cfunc(sig, nopython=True)(c_sparse)
    if name == "encode":
        sig = types.void(p(u32), i64, i64, i64, p(u32), i64, i64, i64, p(u32), p(u32),
                         p(i64))

        def c_encode(w, n, pos0, n_tdc, pattern, lo, hi, swap, index, out, sizes):
            cap = n // n_tdc * (hi - lo) + min(n, hi - lo)
            loop(carray(w, (n,)), pos0, n_tdc, carray(pattern, (n_tdc,)), lo, hi, swap != 0,
                 carray(index, (cap,)), carray(out, (cap,)), carray(sizes, (2,)))

        return numba.cfunc(sig, nopython=True)(c_encode)
    sig = types.void(p(u32), i64, i64, i64, p(i8), p(i64), p(i64), p(u64), p(u64), p(u32),
                     i64, p(i64), p(u64), i64, i64, i64, p(u64), p(i64))

    def c_self_bounded(w, n, pos0, n_tdc, phase, lo, hi, cand, d2nd, keys, capacity, fill,
                       edge, e0, e1, e2, cc, scratch):
        loop(carray(w, (n,)), pos0, n_tdc, carray(phase, (16,)), carray(lo, (n_tdc,)),
             carray(hi, (n_tdc,)), carray(cand, (n_tdc, N_CODES)),
             carray(d2nd, (n_tdc, N_CODES_2ND)), carray(keys, (capacity,)),
             carray(fill, (1,)), carray(edge, (e0, e1, e2)), carray(cc, (N_CLASSES, n_tdc)),
             carray(scratch, (3, SIFT)))

    return numba.cfunc(sig, nopython=True)(c_self_bounded)
