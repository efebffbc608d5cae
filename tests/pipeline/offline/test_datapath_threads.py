"""`histogram_capture` gives the same histograms and counts on any number of threads."""

import numpy as np
import pytest

from pipeline.io.capture import Capture, write_capture
from pipeline.offline.datapath import histogram_capture
from stages.artifact import ArtifactBounds
from stages.testpattern import pattern_words

N = 128


@pytest.fixture(scope="module")
def dirty(tmp_path_factory):
    """Hits, artifacts, invalid phases, malformed words, and a few words made garbage."""
    words, truth = pattern_words(20_000, N, hit_prob=0.2, artifact_prob=0.005,
                                 invalid_prob=0.002, malformed_prob=0.002, rng=11)
    rng = np.random.default_rng(11)
    idx = rng.integers(0, words.size, 2000)
    words[idx] = rng.integers(0, 2**32, idx.size, dtype=np.uint64).astype(np.uint32)
    path = tmp_path_factory.mktemp("dirty") / "c"
    write_capture(path, words, N)
    return path, words, truth


class OneBuffer:
    """A source whose chunks are views of one reused buffer (a simulator's, a journal's)."""

    def __init__(self, cap):
        self.cap, self.meta = cap, cap.meta

    def iter_chunks(self):
        buf = np.empty(1 << 16, np.uint32)
        for first, w in self.cap.iter_chunks(1 << 16):
            buf[:w.size] = w
            yield first, buf[:w.size]


@pytest.mark.parametrize("calibrated", [False, True])
def test_threads_change_nothing(dirty, calibrated):
    path, words, truth = dirty
    bounds = ArtifactBounds(truth.n_min, truth.n_max) if calibrated else None
    runs = {}
    for name, threads, engine in (("numba x1", 1, "numba"), ("numba x2", 2, "numba"),
                                  ("numba x3", 3, "numba"), ("numpy", 1, "numpy")):
        cap = Capture(path)
        cap_chunks = cap.iter_chunks
        cap.iter_chunks = lambda chunk_words=1 << 16, _f=cap_chunks: _f(chunk_words)
        runs[name] = histogram_capture(cap, bounds, engine, threads=threads)
        assert cap.chunk_ring == 1  # (set back)
    runs["one buffer, x2"] = histogram_capture(OneBuffer(Capture(path)), bounds, threads=2)
    ref, rb = runs.pop("numba x1")
    assert int(ref.class_counts.sum()) == words.size  # every word accounted for
    assert all(ref.totals()[c] > 0 for c in ("hit", "artifact", "invalid_phase",
                                             "malformed", "no_hit"))
    for name, (state, b) in runs.items():
        assert np.array_equal(state.hits, ref.hits), name
        assert np.array_equal(state.class_counts, ref.class_counts), name
        assert np.array_equal(b.n_min, rb.n_min) and np.array_equal(b.n_max, rb.n_max), name
