"""One pass without a calibration gives what two passes give: bounds, histograms, counts."""

import numpy as np
import pytest

from stages.artifact import estimate_bounds
from stages.codec import encode_words
from stages.histogram import HistogramAccumulator, SelfBoundingHistogram
from stages.testpattern import pattern_words


def two_pass(words, n_tdc, chunks, engine=None, count_artifacts=False):
    probe = HistogramAccumulator(n_tdc, engine=engine, mode="d2nd")
    for first, w in chunks(words):
        probe.update(w, first)
    bounds = estimate_bounds(probe.snapshot().hits)
    acc = HistogramAccumulator(n_tdc, bounds, engine=engine, count_artifacts=count_artifacts)
    for first, w in chunks(words):
        acc.update(w, first)
    return acc.snapshot(), bounds


def split(size):
    def chunks(words):
        for s in range(0, words.size, size):
            yield s, words[s:s + size]
    return chunks


@pytest.mark.parametrize("engine", ["numba", "numpy"])
@pytest.mark.parametrize("size", [10_007, 1 << 20])
def test_one_pass_equals_two_passes(engine, size):
    n = 16
    words, _ = pattern_words(30_000, n, hit_prob=0.3, malformed_prob=0.01, invalid_prob=0.01,
                             rng=5)
    one = SelfBoundingHistogram(n, engine=engine, count_artifacts=True)
    for first, w in split(size)(words):
        one.update(w, first)
    got, b1 = one.finish()
    ref, b2 = two_pass(words, n, split(size), engine, count_artifacts=True)
    assert got is not None
    assert np.array_equal(b1.n_min, b2.n_min) and np.array_equal(b1.n_max, b2.n_max)
    assert np.array_equal(got.hits, ref.hits)
    assert np.array_equal(got.class_counts, ref.class_counts)
    assert np.array_equal(got.artifacts, ref.artifacts)
    assert got.words == ref.words == words.size


def test_the_engines_agree_on_arbitrary_words():
    rng = np.random.default_rng(3)
    n = 8
    words = rng.integers(0, 2**32, 50_000, dtype=np.uint64).astype(np.uint32)
    good, _ = pattern_words(6250, n, hit_prob=0.5, rng=4)
    words[::2] = good[::2]  # half well-formed at their positions, half anything
    states = []
    for engine in ("numba", "numpy"):
        acc = SelfBoundingHistogram(n, engine=engine, count_artifacts=True)
        acc.update(words[:7000], 0)
        acc.update(words[7000:], 7000)
        states.append(acc.finish())
    (a, ba), (b, bb) = states
    assert (a is None) == (b is None)
    assert np.array_equal(ba.n_min, bb.n_min) and np.array_equal(ba.n_max, bb.n_max)
    if a is not None:
        assert np.array_equal(a.hits, b.hits)
        assert np.array_equal(a.class_counts, b.class_counts)


def test_a_misleading_first_chunk_is_caught():
    """The first chunk's block is narrower than the capture's (the light changed): the
    provisional core is then outside the final block on some TDC, and finish() says so
    rather than giving wrong histograms."""
    n = 2
    rng = np.random.default_rng(0)

    def hits(cycles, d2_lo, d2_hi):
        d2 = rng.integers(d2_lo, d2_hi + 1, (cycles, n))
        d1 = rng.integers(1, 512, (cycles, n))
        tdc = np.tile(np.arange(n), (cycles, 1))
        return encode_words(d1 >> 3, d1 & 7, d2 >> 3, d2 & 7, tdc).ravel()

    first = hits(1000, 150, 200)     # the first chunk sees a block at 150..200
    rest = hits(400_000, 20, 100)    # the capture's block is 20..100
    acc = SelfBoundingHistogram(n)
    acc.update(first, 0)
    acc.update(rest, first.size)
    state, bounds = acc.finish()
    assert state is None
    assert bounds.n_min.tolist() == [20, 20] and bounds.n_max.tolist() == [100, 100]


def test_an_empty_capture_and_a_no_hit_capture():
    acc = SelfBoundingHistogram(4)
    state, bounds = acc.finish()
    assert state is not None and state.words == 0
    acc = SelfBoundingHistogram(4)
    acc.update(encode_words([0] * 8, [0] * 8, [0] * 8, [0] * 8, [0, 1, 2, 3] * 2), 0)
    state, bounds = acc.finish()
    assert state.totals()["no_hit"] == 8 and state.hits.sum() == 0
    assert bounds.n_min.tolist() == [0] * 4 and bounds.n_max.tolist() == [255] * 4
