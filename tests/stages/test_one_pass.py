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


def dirty_words(cycles, n, seed):
    """A capture with every class: hits, artifacts, invalid phases, malformed words."""
    words, _ = pattern_words(cycles, n, hit_prob=0.3, artifact_prob=0.01, invalid_prob=0.01,
                             malformed_prob=0.01, rng=seed)
    return words


@pytest.mark.parametrize("engine", ["numba", "numpy"])
def test_forks_filled_in_threads_merge_to_the_single_pass(engine):
    """The parts of a stream folded into forks in other threads, then merged, give what
    one accumulator over the whole stream gives: histograms, counts, bounds, artifacts."""
    from concurrent.futures import ThreadPoolExecutor

    n = 16
    words = dirty_words(40_000, n, 8)
    single = SelfBoundingHistogram(n, engine=engine, count_artifacts=True)
    for first, w in split(50_000)(words):
        single.update(w, first)
    ref, rb = single.finish()

    head = SelfBoundingHistogram(n, engine=engine, count_artifacts=True)
    head.update(words[:50_000], 0)
    forks = [head.fork() for _ in range(3)]
    parts = list(split(50_000)(words))[1:]
    with ThreadPoolExecutor(3) as pool:
        list(pool.map(lambda i: [forks[i].update(w, first) for first, w in parts[i::3]],
                      range(3)))
    for f in forks:
        head.merge(f)
    got, gb = head.finish()
    assert got is not None and ref is not None
    assert np.array_equal(gb.n_min, rb.n_min) and np.array_equal(gb.n_max, rb.n_max)
    for field in ("hits", "class_counts", "artifacts"):
        assert np.array_equal(getattr(got, field), getattr(ref, field)), field
    assert got.words == words.size and int(got.class_counts.sum()) == words.size
    assert got.totals()["malformed"] > 0 and got.totals()["invalid_phase"] > 0
    assert got.totals()["artifact"] > 0


@pytest.mark.parametrize("engine", ["numba", "numpy"])
def test_edge_words_beyond_the_key_buffer_go_to_the_dense_table(engine, monkeypatch):
    """A buffer too small for the edge words (a dark capture's case) changes nothing."""
    import stages.histogram as sh

    n = 8
    words = dirty_words(20_000, n, 9)
    full = SelfBoundingHistogram(n, engine=engine, count_artifacts=True)
    full.update(words[:40_000], 0)
    full.update(words[40_000:], 40_000)
    monkeypatch.setattr(sh, "EDGE_KEYS", 300)
    small = SelfBoundingHistogram(n, engine=engine, count_artifacts=True)
    small.update(words[:40_000], 0)
    small.update(words[40_000:], 40_000)
    assert small._fill[0] == 300 and small._edge.sum() > 0  # both stores used
    (a, ba), (b, bb) = full.finish(), small.finish()
    assert np.array_equal(ba.n_max, bb.n_max)
    for field in ("hits", "class_counts", "artifacts"):
        assert np.array_equal(getattr(a, field), getattr(b, field)), field


def test_merge_takes_only_forks():
    a, b = SelfBoundingHistogram(4), SelfBoundingHistogram(4)
    with pytest.raises(ValueError, match="update"):
        a.fork()
    w, _ = pattern_words(100, 4, hit_prob=0.5, rng=1)
    a.update(w, 0)
    b.update(w, 0)
    with pytest.raises(ValueError, match="fork"):
        a.merge(b)


def test_xlogy_is_scipys_bit_for_bit():
    """estimate_bounds' own xlogy (scipy.special is not imported on the command's path)."""
    from scipy.special import xlogy

    from stages.artifact import _xlogy

    rng = np.random.default_rng(0)
    x = np.concatenate([rng.poisson(3, 20_000).astype(float),
                        [0, 0, 0, 1, 2, -1, np.nan, np.inf, 0, 5, -0.0, 3]])
    y = np.concatenate([rng.uniform(0, 1e6, 20_000) * rng.choice([1, 1e-300, 1e-3], 20_000),
                        [0, np.nan, -1, 0, -0.0, np.inf, 1, 1, np.inf, np.nan, 2, -np.inf]])
    assert np.array_equal(_xlogy(x, y), xlogy(x, y), equal_nan=True)
    assert np.array_equal(_xlogy(2.5, y), xlogy(2.5, y), equal_nan=True)
