"""One pass over a capture's words without artifact bounds: candidates by code, the D2nd
marginal and the edge words, from which the bounds and the hits follow exactly at the end
(:class:`stages.histogram.SelfBoundingHistogram` drives it).

What it may import: numpy, schemas.constants, stages.codec, and the tables and kernels
beside it.
"""

from __future__ import annotations

import numpy as np

from schemas.constants import HIT, N_CLASSES, N_CODES, N_CODES_2ND
from stages.codec import PHASE_DECODE
from stages.datapath import kernels
from stages.datapath.tables import ENGINES, HAVE_NUMBA, default_engine

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
        scratch = kernels._scratch()
        fn = kernels._native("self_bounded")
        if fn is not None and all(kernels._plain(a, np.uint64) for a in (cand, d2nd, edge,
                                                                  class_counts)) \
                and kernels._plain(keys, np.uint32) and kernels._plain(fill, np.int64):
            fn(words.ctypes.data, words.size, first_word % n_tdc, n_tdc,
               PHASE_DECODE.ctypes.data, core_lo.ctypes.data, core_hi.ctypes.data,
               cand.ctypes.data, d2nd.ctypes.data, keys.ctypes.data, keys.size,
               fill.ctypes.data, edge.ctypes.data, edge.shape[0], edge.shape[1],
               edge.shape[2], class_counts.ctypes.data, scratch.ctypes.data)
        else:
            kernels._jitted("self_bounded")(words, first_word % n_tdc, n_tdc, PHASE_DECODE, core_lo,
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


