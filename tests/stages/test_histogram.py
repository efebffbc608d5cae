import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas import HISTOGRAMS, validate
from stages.artifact import ArtifactBounds
from stages.histogram import HistogramAccumulator, HistogramState
from stages.testpattern import pattern_words

N_TDC = 16
WORDS, TRUTH = pattern_words(400, N_TDC, hit_prob=0.3, artifact_prob=0.05, invalid_prob=0.02,
                             malformed_prob=0.02, rng=7)
BOUNDS = ArtifactBounds(TRUTH.n_min, TRUTH.n_max)


def whole(engine=None):
    acc = HistogramAccumulator(N_TDC, BOUNDS, engine=engine)
    acc.update(WORDS)
    return acc.snapshot()


def test_matches_the_intended_truth(engine):
    s = whole(engine)
    assert np.array_equal(s.hits, TRUTH.hits)
    assert np.array_equal(s.class_counts, TRUTH.class_counts)
    assert s.cycles.tolist() == [400] * N_TDC


@settings(max_examples=40, deadline=None)
@given(st.lists(st.integers(0, WORDS.size), max_size=6), st.sampled_from(["numpy", "numba"]))
def test_split_stream_equals_merge_of_parts(cuts, engine):
    """The histogram of a stream split anywhere equals the merge of the parts' histograms."""
    edges = [0, *sorted(cuts), WORDS.size]
    parts = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        acc = HistogramAccumulator(N_TDC, BOUNDS, engine=engine)
        acc.update(WORDS[a:b], first_word=a)
        parts.append(acc.snapshot())
    merged = parts[0]
    for p in parts[1:]:
        merged = merged + p
    ref = whole()
    assert np.array_equal(merged.hits, ref.hits)
    assert np.array_equal(merged.class_counts, ref.class_counts)
    assert merged.words == WORDS.size
    # ... and feeding the same parts in sequence to one accumulator gives the same state
    acc = HistogramAccumulator(N_TDC, BOUNDS, engine=engine)
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        acc.update(WORDS[a:b])
    assert np.array_equal(acc.snapshot().hits, ref.hits)


def test_snapshot_is_immutable_and_restore_resumes_exactly():
    acc = HistogramAccumulator(N_TDC, BOUNDS)
    half = WORDS.size // 2 + 3
    acc.update(WORDS[:half], seq=0)
    snap = acc.snapshot()
    with pytest.raises(ValueError):
        snap.hits[0, 0] = 1
    acc.update(WORDS[half:], seq=1)
    assert snap.words == half and snap.last_seq == 0  # later updates do not leak in
    fresh = HistogramAccumulator(N_TDC, BOUNDS)
    fresh.restore(snap)
    fresh.update(WORDS[half:], seq=1)
    assert np.array_equal(fresh.snapshot().hits, acc.snapshot().hits)
    assert fresh.snapshot().last_seq == 1
    with pytest.raises(ValueError, match="snapshot has 16 TDCs, this accumulator 8"):
        HistogramAccumulator(8).restore(snap)


def test_table_roundtrip_and_schema():
    s = whole()
    table = s.to_table("m1")
    validate(table, HISTOGRAMS)
    assert table.num_rows == N_TDC
    back = HistogramState.from_table(table)
    assert np.array_equal(back.hits, s.hits) and np.array_equal(back.class_counts,
                                                                s.class_counts)
    assert sum(s.totals().values()) == WORDS.size


def test_rejects_wrong_dtype():
    with pytest.raises(TypeError, match="histogram: words must be uint32, found int64"):
        HistogramAccumulator(4).update(np.zeros(4, np.int64))


def test_zero_counts_and_merge_mismatch():
    empty = HistogramAccumulator(4).snapshot()
    assert empty.hits.sum() == 0 and empty.cycles.tolist() == [0] * 4
    with pytest.raises(ValueError, match="cannot merge histograms of 4 and 16 TDCs"):
        empty + whole()


@settings(max_examples=15, deadline=None)
@given(lo=st.integers(0, 15), width=st.integers(1, 16), corrupt=st.floats(0, 0.2))
def test_a_worker_of_a_tdc_range_equals_those_rows_of_the_whole(lo, width, corrupt):
    """Fan-out by TDC range: a worker takes each cycle's words of TDCs lo..hi-1 (their
    addresses are lo..hi-1, not 0..) and must find exactly those rows of the whole."""
    n = 16
    hi = min(lo + width, n)
    words, _ = pattern_words(300, n, hit_prob=0.4, peak_code=200.0, rng=lo * 31 + width)
    rng = np.random.default_rng(width)
    bad = rng.random(words.size) < corrupt
    words = np.where(bad, words ^ np.uint32(1 << 3), words).astype(np.uint32)  # address bit
    bounds = ArtifactBounds(np.full(n, 3), np.full(n, 200))
    sub = np.ascontiguousarray(words.reshape(-1, n)[:, lo:hi]).ravel()
    for engine in ("numpy", "numba"):
        whole = HistogramAccumulator(n, bounds, engine=engine)
        whole.update(words)
        part = HistogramAccumulator(hi - lo, ArtifactBounds(bounds.n_min[lo:hi],
                                                            bounds.n_max[lo:hi]),
                                    engine=engine, tdc_offset=lo)
        half = sub.size // 2
        part.update(sub[:half], 0)
        part.update(sub[half:], half)
        w, p = whole.snapshot(), part.snapshot()
        np.testing.assert_array_equal(p.hits, w.hits[lo:hi])
        np.testing.assert_array_equal(p.class_counts, w.class_counts[:, lo:hi])
        t = p.to_table("m")
        assert t.column("tdc").to_pylist() == list(range(lo, hi))
        assert HistogramState.from_table(t).tdc_offset == lo
