"""Per-TDC histograms of first-stage codes over hit words, with per-TDC cycle counts.

:class:`HistogramAccumulator` is the stateful core of the histogram stage: feed it word
batches in any split, read the totals, ``snapshot()`` / ``restore()`` for checkpoints.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from schemas.constants import ARTIFACT, HIT, N_CLASSES, N_CODES, N_CODES_2ND, WORD_CLASSES
from stages.artifact import ArtifactBounds, estimate_bounds
from stages.datapath import (
    EDGE_KEYS,
    SparseWords,
    WordTables,
    accumulate,
    accumulate_self_bounded,
    accumulate_sparse,
)

if TYPE_CHECKING:  # pyarrow is imported where a table is made: not on the hot path
    import pyarrow as pa

#: ``histograms.instrument`` of the thesis chip's D1st histograms
CHIP = "tcspc-chip"


def _frozen(a: np.ndarray) -> np.ndarray:
    a = np.array(a, copy=True)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class HistogramState:
    """An immutable snapshot of a :class:`HistogramAccumulator`.

    ``hits`` is (n_tdc, 512) uint64, ``class_counts`` is (N_CLASSES, n_tdc) uint64,
    ``words`` the number of words folded in, ``last_seq`` the sequence number of the last
    batch (-1 before any), for checkpoint/resume.
    """

    hits: np.ndarray
    class_counts: np.ndarray
    words: int
    last_seq: int = -1
    tdc_offset: int = 0  #: address of row 0 (a worker of a fan-out by TDC range)
    #: artifact words by code (n_tdc, 512), where counted (``count_artifacts``)
    artifacts: np.ndarray | None = None

    @property
    def n_tdc(self) -> int:
        return int(self.hits.shape[0])

    @property
    def cycles(self) -> np.ndarray:
        """Cycles per TDC: every word at a TDC's position is one cycle of that TDC."""
        return self.class_counts.sum(axis=0)

    def totals(self) -> dict[str, int]:
        """Words per class over all TDCs (they add up to ``words``)."""
        return {name: int(self.class_counts[i].sum()) for i, name in enumerate(WORD_CLASSES)}

    def __add__(self, other: HistogramState) -> HistogramState:
        """Merge two states (the histogram of a split stream is the sum of its parts)."""
        if self.hits.shape != other.hits.shape:
            raise ValueError(f"cannot merge histograms of {self.n_tdc} and {other.n_tdc} TDCs")
        if self.tdc_offset != other.tdc_offset:
            raise ValueError("cannot merge histograms of different TDC ranges")
        arts = (None if self.artifacts is None or other.artifacts is None
                else _frozen(self.artifacts + other.artifacts))
        return HistogramState(_frozen(self.hits + other.hits),
                              _frozen(self.class_counts + other.class_counts),
                              self.words + other.words, max(self.last_seq, other.last_seq),
                              self.tdc_offset, arts)

    def to_table(self, measurement: str) -> pa.Table:
        """The ``histograms`` dataset of this state, one row per TDC."""
        import pyarrow as pa

        from schemas.outputs import HISTOGRAMS

        n = self.n_tdc
        cc = self.class_counts
        width = self.hits.shape[1]
        counts = pa.ListArray.from_arrays(
            pa.array(np.arange(n + 1, dtype=np.int32) * np.int32(width)),
            pa.array(self.hits.ravel(), pa.uint64()))
        cols = {
            "measurement": pa.array([measurement] * n, pa.string()),
            "tdc": pa.array(np.arange(n, dtype=np.uint16) + np.uint16(self.tdc_offset)),
            "cycles": pa.array(self.cycles.astype(np.uint64)),
            "counts": counts,
        }
        for i, name in enumerate(WORD_CLASSES):
            cols[f"n_{name}"] = pa.array(cc[i].astype(np.uint64))
        cols["instrument"] = pa.array([CHIP] * n, pa.string())
        cols["bin_width_ps"] = pa.nulls(n, pa.float64())
        return pa.Table.from_pydict(cols, schema=HISTOGRAMS.schema)

    @classmethod
    def from_table(cls, table: pa.Table) -> HistogramState:
        """Rebuild a state from a ``histograms`` table (one measurement, rows by TDC).

        Only the thesis chip's rows: an instrument's histograms (PTU, LinoSPAD2) have no
        word classes or artifact bounds to rebuild, and are refused by name.
        """
        if "instrument" in table.column_names:
            other = set(table.column("instrument").to_pylist()) - {CHIP}
            if other:
                raise ValueError(f"histograms of {sorted(other)} are not the thesis chip's "
                                 "D1st histograms; this path takes only 'tcspc-chip' rows")
        order = np.argsort(table.column("tdc").to_numpy())
        hits = np.stack(table.column("counts").to_numpy(zero_copy_only=False))[order]
        cc = np.stack([table.column(f"n_{name}").to_numpy()[order] for name in WORD_CLASSES])
        tdc = table.column("tdc").to_numpy()
        return cls(_frozen(hits.astype(np.uint64)), _frozen(cc.astype(np.uint64)),
                   int(cc.sum()), tdc_offset=int(tdc.min()) if tdc.size else 0)


class HistogramAccumulator:
    """Accumulate D1st histograms of hit words per TDC, and word-class counts per TDC.

    Parameters
    ----------
    n_tdc : int
        TDCs per cycle.
    bounds : ArtifactBounds, optional
        Valid D2nd range per TDC; None accepts every D2nd (no artifact class).
    engine : {"numba", "numpy"}, optional
    step_id : str
        Name of this stage instance, used in errors.
    mode : {"d1st", "d2nd"}
        Histogram the first-stage code (the product) or the second-stage code of hit
        candidates (what artifact-bound estimation needs).
    tdc_offset : int
        Address of the first TDC: a worker of a fan-out by TDC range takes the words of
        TDCs ``tdc_offset .. tdc_offset + n_tdc - 1`` of each cycle (``bounds`` for those).
    count_artifacts : bool
        Also histogram the artifact words by code (``HistogramState.artifacts``): a
        density test needs them (an artifact ends the cycle's risk like a hit).

    Examples
    --------
    >>> from stages.codec import encode_words
    >>> acc = HistogramAccumulator(n_tdc=2)
    >>> acc.update(encode_words([1, 0], [2, 0], [3, 0], [0, 0], [0, 1]))  # a hit, a no_hit
    >>> s = acc.snapshot(); int(s.hits[0, 10]), s.cycles.tolist(), s.totals()["no_hit"]
    (1, [1, 1], 1)
    """

    def __init__(self, n_tdc: int, bounds: ArtifactBounds | None = None,
                 engine: str | None = None, step_id: str = "histogram",
                 mode: str = "d1st", tdc_offset: int = 0, count_artifacts: bool = False):
        self.step_id = step_id
        self.bounds = bounds if bounds is not None else ArtifactBounds.unbounded(n_tdc)
        self._tables = WordTables(n_tdc, self.bounds, mode, tdc_offset)
        self.tdc_offset = tdc_offset
        self.engine = engine
        self.n_tdc = n_tdc
        self._hits = np.zeros((n_tdc, self._tables.n_bins), np.uint64)
        self._artifacts = (np.zeros_like(self._hits) if count_artifacts else None)
        self._class_counts = np.zeros((N_CLASSES, n_tdc), np.uint64)
        self._words = 0
        self._last_seq = -1

    def update(self, words: np.ndarray, first_word: int | None = None,
               seq: int | None = None) -> None:
        """Fold a batch of native uint32 words in (or their :class:`SparseWords` form).

        ``first_word`` is the stream index of ``words[0]`` (it fixes the TDC of each word);
        by default the batch continues the words already folded in. ``seq`` is the batch's
        sequence number, kept for checkpoints.
        """
        start = self._words if first_word is None else int(first_word)
        if isinstance(words, SparseWords):
            accumulate_sparse(words, start, self._tables, self._hits, self._class_counts,
                              self.engine, self._artifacts)
        else:
            words = np.asarray(words)
            if words.dtype != np.uint32:
                raise TypeError(f"{self.step_id}: words must be uint32, found {words.dtype}")
            accumulate(words.ravel(), start, self._tables, self._hits, self._class_counts,
                       self.engine, self._artifacts)
        self._words += words.size
        if seq is not None:
            self._last_seq = int(seq)

    def class_totals(self) -> np.ndarray:
        """Words of the measurement being filled by class, (N_CLASSES,) uint64 (a sum
        over the TDCs' counts: microseconds; for the live metrics)."""
        return self._class_counts.sum(axis=1)

    def reset(self) -> None:
        """Start a new measurement: zero the histograms and counts in place (the tables,
        costly to build, are kept)."""
        self._hits.fill(0)
        self._class_counts.fill(0)
        if self._artifacts is not None:
            self._artifacts.fill(0)
        self._words = 0

    def snapshot(self) -> HistogramState:
        """An immutable copy of the state."""
        return HistogramState(_frozen(self._hits), _frozen(self._class_counts), self._words,
                              self._last_seq, self.tdc_offset,
                              None if self._artifacts is None else _frozen(self._artifacts))

    def restore(self, state: HistogramState) -> None:
        """Resume exactly from ``state``."""
        if state.n_tdc != self.n_tdc:
            raise ValueError(f"{self.step_id}: snapshot has {state.n_tdc} TDCs, this "
                             f"accumulator {self.n_tdc}")
        self._hits = np.array(state.hits, np.uint64)
        self._class_counts = np.array(state.class_counts, np.uint64)
        if self._artifacts is not None:
            if state.artifacts is None:
                raise ValueError(f"{self.step_id}: the snapshot holds no artifact counts")
            self._artifacts = np.array(state.artifacts, np.uint64)
        self._words = state.words
        self._last_seq = state.last_seq

    @property
    def hit_total(self) -> int:
        return int(self._class_counts[HIT].sum())


_NO_EDGE = np.zeros((1, 1, 1), np.uint64)  # the dense edge table where none can be needed


def _full_edge(n_tdc: int) -> np.ndarray:
    return np.zeros((n_tdc, N_CODES_2ND, N_CODES), np.uint64)  # (pages faulted if touched)


class SelfBoundingHistogram:
    """The histograms of a capture with no calibration, in one pass: the artifact bounds
    come from the capture's own D2nd histogram at the end (:func:`estimate_bounds`).

    The first batch gives provisional bounds; each TDC's core, those bounds shrunk by
    ``margin`` codes, is surely inside the final block, so only the candidates outside
    it are kept by (D2nd, D1st) (:func:`stages.datapath.accumulate_self_bounded`). At
    :meth:`finish` the final bounds are estimated from all the data and the hits are the
    candidates less those outside the bounds: the same histograms, class counts and
    bounds as two passes (bounds first, then histograms), tested. When a final block does
    not contain its core (the first batch misled), :meth:`finish` says so and the caller
    makes the second pass.

    Examples
    --------
    >>> from stages.testpattern import pattern_words
    >>> w, _ = pattern_words(2000, 4, hit_prob=0.5, rng=1)
    >>> acc = SelfBoundingHistogram(4); acc.update(w)
    >>> state, bounds = acc.finish()
    >>> ref = HistogramAccumulator(4, bounds); ref.update(w)
    >>> bool(np.array_equal(state.hits, ref.snapshot().hits))
    True
    """

    def __init__(self, n_tdc: int, engine: str | None = None, margin: int = 4,
                 count_artifacts: bool = False):
        self.n_tdc, self.engine, self.margin = n_tdc, engine, margin
        self.count_artifacts = count_artifacts
        self._cand = np.zeros((n_tdc, N_CODES), np.uint64)
        self._d2nd = np.zeros((n_tdc, N_CODES_2ND), np.uint64)
        # edge words as keys (stages.datapath.edge_key), and the dense (n_tdc, 256, 512)
        # table of those that find the buffer full, made only when that may happen
        self._keys = np.empty(0, np.uint32)
        self._fill = np.zeros(1, np.int64)
        self._edge = _NO_EDGE
        # with those of merged forks: (keys, dense) pairs, summed at finish where needed
        self._parts: list = []
        self._class_counts = np.zeros((N_CLASSES, n_tdc), np.uint64)
        self._words = 0
        self._core: tuple[np.ndarray, np.ndarray] | None = None

    def update(self, words: np.ndarray, first_word: int | None = None) -> None:
        """Fold a batch of native uint32 words in (the first one also sets the cores)."""
        words = np.asarray(words)
        if words.dtype != np.uint32:
            raise TypeError(f"words must be uint32, found {words.dtype}")
        start = self._words if first_word is None else int(first_word)
        if self._core is None:
            self._core = self._provisional_core(words, start)
        if self._keys.size == 0:  # (touched only as it fills)
            self._keys = np.empty(EDGE_KEYS, np.uint32)
        if self._fill[0] + words.size > self._keys.size and self._edge is _NO_EDGE:
            self._edge = np.zeros((self.n_tdc, N_CODES_2ND, N_CODES), np.uint64)
        accumulate_self_bounded(words.ravel(), start, self.n_tdc, *self._core, self._cand,
                                self._d2nd, self._keys, self._fill, self._edge,
                                self._class_counts, self.engine)
        self._words += words.size

    def fork(self) -> SelfBoundingHistogram:
        """An empty accumulator with this one's provisional cores (set by its first
        update), for other words of the same capture, e.g. in another thread (the
        kernels release the GIL); fold it back with :meth:`merge`. Give ``first_word``
        to every update of a fork."""
        if self._core is None:
            raise ValueError("fork() needs the provisional cores: update() first")
        other = SelfBoundingHistogram(self.n_tdc, self.engine, self.margin,
                                      self.count_artifacts)
        other._core = self._core
        return other

    def merge(self, other: SelfBoundingHistogram) -> None:
        """Fold a fork's counts into this accumulator (the sum of the parts of a split
        stream; the edge counts are summed at :meth:`finish`, where they are needed)."""
        if other._core is not self._core:
            raise ValueError("merge() takes a fork of this accumulator")
        self._cand += other._cand
        self._d2nd += other._d2nd
        self._class_counts += other._class_counts
        self._parts += other._edge_parts()
        self._words += other._words

    def _edge_parts(self) -> list:
        return [(self._keys[:self._fill[0]], self._edge), *self._parts]

    def _provisional_core(self, words, start):
        # the candidates' D2nd histogram of this batch, from the same kernel with a core
        # that spans every code (so no edge word is kept)
        d2nd = np.zeros_like(self._d2nd)
        accumulate_self_bounded(words.ravel(), start, self.n_tdc,
                                np.zeros(self.n_tdc, np.int64),
                                np.full(self.n_tdc, N_CODES_2ND - 1, np.int64),
                                np.zeros_like(self._cand), d2nd, np.empty(0, np.uint32),
                                np.zeros(1, np.int64), _full_edge(self.n_tdc),
                                np.zeros_like(self._class_counts), self.engine)
        b = estimate_bounds(d2nd)
        lo = b.n_min.astype(np.int64) + self.margin
        hi = b.n_max.astype(np.int64) - self.margin
        empty = b.uncertain | (lo > hi)
        return np.where(empty, 1, lo), np.where(empty, 0, hi)  # empty core: all edge words

    def _edge_counts(self, outside: np.ndarray) -> np.ndarray:
        """(n_tdc, 512) D1st counts of the edge words whose D2nd is ``outside``."""
        n = self.n_tdc
        arts = np.zeros(n * N_CODES, np.int64)
        # dense rows are read only where they can hold a count: outside, and where some
        # candidate had that D2nd (an untouched row is a page never faulted in)
        rows = outside & (self._d2nd > 0)
        for keys, dense in self._edge_parts():
            k = keys.astype(np.int64)
            sel = k[outside.ravel()[k >> 9]]  # (tdc * 256 + D2nd) selects, D1st is counted
            arts += np.bincount((sel >> 17) * N_CODES + (sel & (N_CODES - 1)),
                                minlength=arts.size)
            if dense is not _NO_EDGE:
                arts += np.stack([dense[t][rows[t]].sum(axis=0) for t in range(n)]) \
                    .astype(np.int64).ravel()
        return arts.reshape(n, N_CODES).astype(np.uint64)

    def finish(self) -> tuple[HistogramState | None, ArtifactBounds]:
        """The state and the bounds estimated from all the data; the state is None when a
        TDC's final block does not contain its core (then histogram again with the
        bounds: a second pass)."""
        bounds = estimate_bounds(self._d2nd)
        lo, hi = self._core if self._core is not None else (np.ones(self.n_tdc, np.int64),
                                                          np.zeros(self.n_tdc, np.int64))
        core_empty = lo > hi
        inside = core_empty | ((bounds.n_min <= lo) & (hi <= bounds.n_max))
        if not inside.all():
            return None, bounds
        arts = self._edge_counts(~bounds.in_block())
        cc = self._class_counts.copy()
        per_tdc = arts.sum(axis=1)
        cc[HIT] -= per_tdc
        cc[ARTIFACT] += per_tdc
        state = HistogramState(_frozen(self._cand - arts), _frozen(cc), self._words,
                               artifacts=_frozen(arts) if self.count_artifacts else None)
        return state, bounds
