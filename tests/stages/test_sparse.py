"""Raw words in sparse form (stages.datapath: SparseWords, sparse_encode, accumulate_sparse):
the source's one pass and the worker's fold carry every word, whatever the words are.

The words here are drawn independently of the code under test: no_hit words of the right
address, of another address (malformed), arbitrary 32-bit values and coded hits."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas.errors import Rejected
from stages import datapath as dp
from stages.artifact import ArtifactBounds
from stages.codec import encode_words
from stages.histogram import HistogramAccumulator
from stages.stream import HistogramCore

ENGINES = ["numba", "numpy"]


def _words(rng: np.random.Generator, cycles: int, n_tdc: int, p_other: float) -> np.ndarray:
    """Whole cycles of words: mostly their position's no_hit word (bit 9 and the address,
    written out here from docs/design.md, not taken from the code), the rest a mix."""
    pos = np.tile(np.arange(n_tdc, dtype=np.uint32), cycles)
    words = (1 << 9) | (pos << 1)
    other = rng.random(words.size) < p_other
    k = int(other.sum())
    kind = rng.integers(0, 3, k)
    hits = encode_words(rng.integers(0, 64, k), rng.integers(0, 8, k), rng.integers(0, 32, k),
                        rng.integers(0, 8, k), pos[other])
    junk = rng.integers(0, 1 << 32, k, dtype=np.uint64).astype(np.uint32)
    wrong_addr = (1 << 9) | (((pos[other] + 1) % 256) << 1)
    words[other] = np.where(kind == 0, hits, np.where(kind == 1, junk, wrong_addr))
    return words.astype(np.uint32)


def _ranges(n_tdc: int, cuts: list[int]) -> list[tuple[int, int]]:
    edges = [0, *sorted({c for c in cuts if 0 < c < n_tdc}), n_tdc]
    return list(zip(edges[:-1], edges[1:], strict=True))


@settings(max_examples=60, deadline=None)
@given(n_tdc=st.integers(1, 20), cycles=st.integers(0, 40), p=st.sampled_from([0, .05, .5, 1]),
       start=st.integers(0, 10**6), cuts=st.lists(st.integers(1, 19), max_size=3),
       big_endian=st.booleans(), seed=st.integers(0, 2**31))
def test_sparse_form_carries_every_word(n_tdc, cycles, p, start, cuts, big_endian, seed):
    words = _words(np.random.default_rng(seed), cycles, n_tdc, p)
    ranges = _ranges(n_tdc, cuts)
    first = start * n_tdc  # whole cycles: a fan-out cuts cycles
    held = words.astype(">u4") if big_endian else words
    got = {e: dp.sparse_encode(held, first, n_tdc, ranges, engine=e) for e in ENGINES}
    grid = words.reshape(-1, n_tdc)
    for r, (a, b) in enumerate(ranges):
        sw = got["numba"][r]
        assert sw.problem() is None
        np.testing.assert_array_equal(sw.index, got["numpy"][r].index)
        np.testing.assert_array_equal(sw.words, got["numpy"][r].words)
        mine = np.ascontiguousarray(grid[:, a:b]).ravel()
        assert sw.size == mine.size
        np.testing.assert_array_equal(sw.dense(start * (b - a), b - a, a), mine)


@settings(max_examples=40, deadline=None)
@given(n_tdc=st.integers(1, 9), n=st.integers(0, 300), first=st.integers(0, 10**6),
       p=st.sampled_from([0, .1, 1]), seed=st.integers(0, 2**31))
def test_any_start_without_a_fanout(n_tdc, n, first, p, seed):
    """One range: a batch may start and end mid-cycle (a UDP-sized or resumed batch)."""
    words = _words(np.random.default_rng(seed), -(-(n + n_tdc) // n_tdc), n_tdc, p)
    pos0 = first % n_tdc
    words = words[pos0:pos0 + n]
    for e in ENGINES:
        (sw,) = dp.sparse_encode(words, first, n_tdc, engine=e)
        np.testing.assert_array_equal(sw.dense(first, n_tdc), words)


@pytest.mark.parametrize("engine", ENGINES)
@pytest.mark.parametrize("p", [0.0, 0.05, 0.3, 1.0])
def test_the_fold_of_the_sparse_form_is_the_fold_of_the_words(engine, p):
    """Counts, histograms and artifact histograms as the dense kernel gives them, with
    bounds that make artifacts, a worker's TDC range and the batch cut anywhere."""
    rng = np.random.default_rng(7)
    n_tdc, lo, hi = 12, 4, 10
    words = _words(rng, 500, n_tdc, p)
    w = hi - lo
    bounds = ArtifactBounds(np.full(w, 40), np.full(w, 200))
    ref = HistogramAccumulator(w, bounds, engine=engine, tdc_offset=lo, count_artifacts=True)
    sub = np.ascontiguousarray(words.reshape(-1, n_tdc)[:, lo:hi]).ravel()
    ref.update(sub, 0)
    (sw,) = dp.sparse_encode(words, 0, n_tdc, [(0, lo), (lo, hi), (hi, n_tdc)],
                             engine=engine)[1:2]
    acc = HistogramAccumulator(w, bounds, engine=engine, tdc_offset=lo, count_artifacts=True)
    cuts = sorted(rng.integers(0, sw.size, 5).tolist())
    for a, b in zip([0, *cuts], [*cuts, sw.size], strict=True):
        acc.update(sw[a:b], a)
    s, r = acc.snapshot(), ref.snapshot()
    np.testing.assert_array_equal(s.hits, r.hits)
    np.testing.assert_array_equal(s.class_counts, r.class_counts)
    np.testing.assert_array_equal(s.artifacts, r.artifacts)
    assert s.words == r.words == sub.size
    if p:
        assert r.totals()["artifact"] and r.totals()["malformed"] and r.totals()["hit"]


def test_slices_follow_the_words():
    sw = dp.SparseWords(10, np.array([1, 4, 9], np.uint32), np.array([7, 8, 9], np.uint32))
    part = sw[3:10]
    assert part.size == 7 and part.index.tolist() == [1, 6] and part.words.tolist() == [8, 9]
    assert sw[5:5].size == 0 and sw[5:5].index.size == 0
    assert sw[8:3].size == 0
    with pytest.raises(ValueError, match="ranges"):
        sw[::2]


@pytest.mark.parametrize("index, problem", [
    ([3, 1], "ascending"),
    ([1, 1], "ascending"),
    ([1, 10], "beyond"),
])
def test_a_sender_cannot_make_the_fold_count_wrong(index, problem):
    """An index out of order, repeated or beyond the span would count a word twice or
    outside its message: the worker rejects the message (counted, quarantined)."""
    import pyarrow as pa

    from pipeline.stream.wire import decode, encode  # (the wire is the worker's edge)
    from schemas.words import RAW_SPARSE

    core = HistogramCore(4)
    head = {"kind": "data", "schema": "raw_sparse", "version": "1.0", "run": "r", "seq": 0,
            "step": "source", "first_word": 0, "n_words": 10, "n_tdc": 4,
            "t_laser_win_ns": 140.0}
    batch = pa.record_batch([pa.array(index, pa.uint32()), pa.array([7, 8], pa.uint32())],
                            schema=RAW_SPARSE.schema)
    h, b = decode(encode(head, batch), core.in_spec)
    with pytest.raises(Rejected, match=problem) as exc:
        core.process(h, b)
    assert exc.value.reason == "bad_payload"
    assert core.words_total == 0
    sw = dp.SparseWords(10, np.array([1], np.uint32), np.array([1, 2], np.uint32))
    assert "indices" in sw.problem()


def test_an_instrument_worker_refuses_sparse_words():
    import pyarrow as pa

    from schemas.words import RAW_SPARSE
    from stages.instruments.accumulate import Linospad2Accumulator

    core = HistogramCore(1, accumulator=Linospad2Accumulator())
    batch = pa.record_batch([pa.array([], pa.uint32()), pa.array([], pa.uint32())],
                            schema=RAW_SPARSE.schema)
    with pytest.raises(Rejected, match="instrument"):
        core.process({"schema": "raw_sparse", "n_words": 4, "first_word": 0, "seq": 0}, batch)


@settings(max_examples=40, deadline=None)
@given(n_tdc=st.integers(1, 20), cycles=st.integers(0, 30), start=st.integers(0, 10**5),
       cuts=st.lists(st.integers(1, 19), max_size=3), seed=st.integers(0, 2**31))
def test_a_fanout_cut_from_the_whole_form_is_the_form_of_each_range(n_tdc, cycles, start, cuts,
                                                                    seed):
    words = _words(np.random.default_rng(seed), cycles, n_tdc, 0.3)
    ranges = _ranges(n_tdc, cuts)
    (whole,) = dp.sparse_encode(words, start * n_tdc, n_tdc)
    direct = dp.sparse_encode(words, start * n_tdc, n_tdc, ranges)
    for got, want in zip(whole.cut(start * n_tdc, n_tdc, ranges), direct, strict=True):
        assert got.size == want.size and got.index.dtype == np.uint32
        np.testing.assert_array_equal(got.index, want.index)
        np.testing.assert_array_equal(got.words, want.words)
    if n_tdc > 1:
        with pytest.raises(ValueError, match="whole cycles"):
            whole.cut(start * n_tdc + 1, n_tdc, ranges)


def test_a_cut_holds_near_the_end_of_the_uint32_index():
    """The cut computes in uint32 (an index is below the batch's words, < 2**32): words
    at the last cycles of a 2**32-word span land where the int64 arithmetic puts them."""
    n_tdc = 96
    n = (2**32 // n_tdc) * n_tdc
    index = np.array([0, 95, 96, n - 97, n - 96, n - 50, n - 1], np.uint32)
    sw = dp.SparseWords(n, index, np.arange(index.size, dtype=np.uint32))
    for a, b in [(0, 40), (40, 95), (95, 96)]:
        (got,) = sw.cut(0, n_tdc, [(a, b)])
        cyc, pos = np.divmod(index.astype(np.int64), n_tdc)
        mine = (pos >= a) & (pos < b)
        np.testing.assert_array_equal(got.index, cyc[mine] * (b - a) + pos[mine] - a)
        np.testing.assert_array_equal(got.words, sw.words[mine])
        assert got.n == n // n_tdc * (b - a)
