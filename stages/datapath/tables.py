"""The word tables and the numpy engine of the fused hot path, and :func:`accumulate`, the
fold of whole words by either engine (the numba engine's loops: :mod:`.kernels`).

What it may import: numpy, schemas.constants, stages.artifact, stages.codec and the
kernels beside it (no numba at import: the kernels load it when one is compiled).
"""

from __future__ import annotations

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
from stages.codec import MAX_TDC, PHASE_DECODE
from stages.datapath import kernels

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


def _accumulate_numba(words, first_word, tables, hits, class_counts, artifacts=None):
    count = artifacts is not None
    arts = artifacts if count else np.zeros((1, 1), np.uint64)
    scratch = kernels._scratch()
    fn = kernels._native("kernel")
    if fn is not None and all(kernels._plain(a, np.uint64) for a in (hits, class_counts, arts)):
        fn(words.ctypes.data, words.size, first_word % tables.n_tdc, tables.n_tdc,
           PHASE_DECODE.ctypes.data, tables.in_block_u8.ctypes.data, hits.ctypes.data,
           hits.shape[1], class_counts.ctypes.data, tables.mode == "d2nd",
           tables.tdc_offset, arts.ctypes.data, arts.shape[0], arts.shape[1], count,
           scratch.ctypes.data)
        return
    kernels._jitted("kernel")(words, first_word % tables.n_tdc, tables.n_tdc, PHASE_DECODE,
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
