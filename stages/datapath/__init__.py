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

The package's rooms (each opens with what it is and what it may import):

``tables``       the word tables, the numpy engine, :func:`accumulate` (whole words)
``selfbounded``  one pass without artifact bounds: candidates, D2nd marginal, edge words
``sparse``       the sparse form of raw words: make it, fold it
``kernels``      the numba engine's loops and their compilation (C kernels or numba)

Every name the single module had is importable from here.
"""

from stages.datapath.kernels import (  # noqa: F401 (the old module's private names)
    _LOOPS,
    SIFT,
    _build,
    _jitted,
    _kernel_loop,
    _native,
    _numba_loop,
    _plain,
    _scratch,
)
from stages.datapath.selfbounded import EDGE_KEYS, accumulate_self_bounded, edge_key
from stages.datapath.sparse import SparseWords, accumulate_sparse, no_hit_words, sparse_encode
from stages.datapath.tables import (  # noqa: F401 (and its private engines)
    BLOCK_WORDS,
    CHUNK_WORDS,
    ENGINES,
    HAVE_NUMBA,
    STATE_CLASSES,
    WordTables,
    _accumulate_numba,
    _accumulate_numpy,
    accumulate,
    default_engine,
)

__all__ = ["BLOCK_WORDS", "CHUNK_WORDS", "EDGE_KEYS", "ENGINES", "HAVE_NUMBA", "SIFT",
           "STATE_CLASSES", "SparseWords", "WordTables", "accumulate",
           "accumulate_self_bounded", "accumulate_sparse", "default_engine", "edge_key",
           "no_hit_words", "sparse_encode"]
