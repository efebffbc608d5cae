"""Raw words in sparse form: the words that are not their position's plain no_hit word,
with their indices (what a chip's source sends and its journal keeps), made and folded as
whole words are.

What it may import: numpy, schemas.constants, stages.codec, and the tables and kernels
beside it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

from stages.codec import MARKER_VALUE, PHASE_DECODE
from stages.datapath import kernels
from stages.datapath.tables import ENGINES, WordTables, _accumulate_numpy, default_engine

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
        # in uint32 (an index is < n < 2**32): a word at cycle c, position p (index
        # c * n_tdc + p) is word c * (b - a) + p - a of range (a, b), i.e. its index less
        # c * (n_tdc - (b - a)) + a; `p - a < b - a` tests a <= p < b in one compare (p < a
        # wraps round); p as i - i // n_tdc * n_tdc (numpy's uint32 `%` by a scalar is 10x
        # slower than its `//`). 4x as fast as int64 divmod, two compares and boolean
        # indexing (docs/performance.md)
        idx, n_tdc_u = np.asarray(self.index, np.uint32), np.uint32(n_tdc)
        pos = idx - idx // n_tdc_u * n_tdc_u
        out = []
        for a, b in ranges:
            mine = (pos - np.uint32(a)) < np.uint32(b - a)
            i = np.compress(mine, idx)
            i -= i // n_tdc_u * np.uint32(n_tdc - (b - a)) + np.uint32(a)
            out.append(SparseWords(self.n // n_tdc * (b - a), i, np.compress(mine, self.words)))
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
            fn = kernels._native("encode")
            if fn is not None:
                fn(raw.ctypes.data, raw.size, pos0, n_tdc, pattern.ctypes.data, a, b, swap,
                   index.ctypes.data, out.ctypes.data, got.ctypes.data)
            else:
                kernels._jitted("encode")(raw, pos0, n_tdc, pattern, a, b, swap, index, out, got)
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
    scratch = kernels._scratch()
    index = np.ascontiguousarray(sparse.index, np.uint32)
    words = np.ascontiguousarray(sparse.words, np.uint32)
    pos0 = first_word % tables.n_tdc
    fn = kernels._native("sparse")
    if fn is not None and all(kernels._plain(a, np.uint64) for a in (hits, class_counts, arts)):
        fn(index.ctypes.data, words.ctypes.data, words.size, sparse.n, pos0, tables.n_tdc,
           PHASE_DECODE.ctypes.data, tables.in_block_u8.ctypes.data, hits.ctypes.data,
           hits.shape[1], class_counts.ctypes.data, tables.mode == "d2nd",
           tables.tdc_offset, arts.ctypes.data, arts.shape[0], arts.shape[1], count,
           scratch.ctypes.data)
        return
    kernels._jitted("sparse")(index, words, sparse.n, pos0, tables.n_tdc, PHASE_DECODE,
                      tables.in_block, hits, class_counts, tables.mode == "d2nd",
                      tables.tdc_offset, arts, count, scratch)

