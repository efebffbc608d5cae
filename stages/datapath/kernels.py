"""The numba engine's loops, as plain Python, and their compilation: each loop runs compiled
by numba (its dispatcher and on-disk cache) or as a C kernel loaded without numba
(:mod:`stages.nativecode`), and as plain Python in the tests. Every loop the engine
compiles lives in this one module: :mod:`stages.nativecode` keys a cached kernel by its
module's source, so a change to any loop rebuilds it.

What it may import: numpy, ctypes, schemas.constants, stages.codec; numba only when a
loop is compiled.
"""

from __future__ import annotations

import ctypes

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
from stages.codec import MARKER_MASK, MARKER_VALUE

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

# --- the one pass without bounds (stages.datapath.selfbounded says what it keeps) --------


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

# --- the sparse form (stages.datapath.sparse says what it is) ----------------------------


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
