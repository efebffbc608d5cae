"""The fused engines against the reference classifier, on clean and corrupted streams."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from schemas import ARTIFACT, HIT, N_CLASSES
from stages.artifact import ArtifactBounds
from stages.codec import classify_words, decode_fields, positions
from stages.datapath import CHUNK_WORDS, STATE_CLASSES, WordTables, accumulate
from stages.testpattern import pattern_words


def reference(words, n_tdc, first_word, bounds, mode="d1st"):
    cls = classify_words(words, n_tdc, first_word, bounds.n_min, bounds.n_max)
    pos = positions(words.size, n_tdc, first_word).astype(np.int64)
    f = decode_fields(words)
    code = f.d1st if mode == "d1st" else f.d2nd
    n_bins = 512 if mode == "d1st" else 256
    hit = cls == HIT
    hits = np.bincount(pos[hit] * n_bins + code[hit], minlength=n_tdc * n_bins)
    cc = np.bincount(cls.astype(np.int64) * n_tdc + pos, minlength=N_CLASSES * n_tdc)
    return hits.reshape(n_tdc, n_bins), cc.reshape(N_CLASSES, n_tdc)


def run(words, n_tdc, first_word, bounds, engine, mode="d1st"):
    t = WordTables(n_tdc, bounds, mode)
    hits = np.zeros((n_tdc, t.n_bins), np.uint64)
    cc = np.zeros((N_CLASSES, n_tdc), np.uint64)
    accumulate(words, first_word, t, hits, cc, engine)
    return hits, cc


def corrupt(words, rng, frac):
    """Flip random bits in a fraction of the words: every kind of bad input appears."""
    words = words.copy()
    idx = np.flatnonzero(rng.random(words.size) < frac)
    words[idx] ^= (np.uint32(1) << rng.integers(0, 32, idx.size).astype(np.uint32))
    return words


@pytest.mark.parametrize("n_tdc", [1, 7, 128, 256])
@pytest.mark.parametrize("mode", ["d1st", "d2nd"])
def test_engines_equal_reference_on_corrupted_streams(engine, n_tdc, mode, rng):
    words, truth = pattern_words(600, n_tdc, hit_prob=0.3, artifact_prob=0.05,
                                 invalid_prob=0.02, malformed_prob=0.02, rng=rng)
    words = corrupt(words, rng, 0.05)
    bounds = ArtifactBounds(truth.n_min, truth.n_max)
    first = int(rng.integers(0, 10_000))
    hits, cc = run(words, n_tdc, first, bounds, engine, mode)
    ref_hits, ref_cc = reference(words, n_tdc, first, bounds, mode)
    assert np.array_equal(hits, ref_hits)
    assert np.array_equal(cc, ref_cc)
    assert cc.sum() == words.size  # every word accounted for


@pytest.mark.parametrize("n_tdc", [1, 7, 128])
def test_artifact_words_counted_by_code_on_both_engines(engine, n_tdc, rng):
    """Optional third array: the artifact words' D1st histogram (a density test needs
    them: an artifact ends the cycle's risk like a hit)."""
    words, truth = pattern_words(600, n_tdc, hit_prob=0.3, artifact_prob=0.1,
                                 invalid_prob=0.02, malformed_prob=0.02, rng=rng)
    words = corrupt(words, rng, 0.02)
    bounds = ArtifactBounds(truth.n_min, truth.n_max)
    first = n_tdc * int(rng.integers(0, 1000))  # aligned: the words' addresses hold
    t = WordTables(n_tdc, bounds)
    hits = np.zeros((n_tdc, 512), np.uint64)
    cc = np.zeros((N_CLASSES, n_tdc), np.uint64)
    arts = np.zeros((n_tdc, 512), np.uint64)
    accumulate(words, first, t, hits, cc, engine, artifacts=arts)
    cls = classify_words(words, n_tdc, first, bounds.n_min, bounds.n_max)
    pos = positions(words.size, n_tdc, first).astype(np.int64)
    art = cls == ARTIFACT
    ref = np.bincount(pos[art] * 512 + decode_fields(words).d1st[art], minlength=n_tdc * 512)
    assert np.array_equal(arts, ref.reshape(n_tdc, 512))
    assert np.array_equal(arts.sum(1), cc[ARTIFACT]) and arts.sum() > 0
    ref_hits, ref_cc = reference(words, n_tdc, first, bounds)
    assert np.array_equal(hits, ref_hits) and np.array_equal(cc, ref_cc)


@settings(max_examples=60, deadline=None)
@given(st.lists(st.integers(0, 2**32 - 1), min_size=0, max_size=400),
       st.integers(1, 256), st.integers(0, 1000), st.integers(0, 255), st.integers(0, 255))
def test_engines_agree_on_arbitrary_words(raw, n_tdc, first, lo, hi):
    words = np.array(raw, np.uint32)
    lo, hi = min(lo, hi), max(lo, hi)
    bounds = ArtifactBounds(np.full(n_tdc, lo), np.full(n_tdc, hi))
    ref = reference(words, n_tdc, first, bounds)
    for engine in ("numpy", "numba"):
        hits, cc = run(words, n_tdc, first, bounds, engine)
        assert np.array_equal(hits, ref[0]) and np.array_equal(cc, ref[1]), engine


def test_numpy_chunk_boundaries(rng):
    n_tdc = 128
    words, truth = pattern_words(3 * CHUNK_WORDS // n_tdc + 3, n_tdc, hit_prob=0.2, rng=rng)
    words = words[5:]  # not a whole number of cycles, starting mid-cycle
    bounds = ArtifactBounds(truth.n_min, truth.n_max)
    got = run(words, n_tdc, 5, bounds, "numpy")
    ref = reference(words, n_tdc, 5, bounds)
    assert np.array_equal(got[0], ref[0]) and np.array_equal(got[1], ref[1])


def test_state_table_precedence():
    # (hi_state, lo_state) -> class, spelled out: malformed > invalid > no_hit > artifact.
    assert STATE_CLASSES.tolist() == [
        [0, 0, 3, 4],   # hi ok
        [2, 2, 3, 4],   # hi artifact
        [0, 1, 3, 4],   # hi all zero, D2nd = 0 inside the block
        [2, 1, 3, 4],   # hi all zero, D2nd = 0 outside the block
        [3, 3, 3, 4],   # hi invalid phase
        [4, 4, 4, 4],   # hi malformed (bit 31)
    ]


def test_empty_input(engine):
    hits, cc = run(np.zeros(0, np.uint32), 128, 0, ArtifactBounds.unbounded(128), engine)
    assert hits.sum() == 0 and cc.sum() == 0


def test_bad_arguments():
    with pytest.raises(ValueError, match="n_tdc must be in 1..256"):
        WordTables(0, ArtifactBounds.unbounded(1))
    with pytest.raises(ValueError, match="bounds are for 4 TDCs, data has 8"):
        WordTables(8, ArtifactBounds.unbounded(4))
    t = WordTables(4, ArtifactBounds.unbounded(4))
    with pytest.raises(ValueError, match="engine must be one of"):
        accumulate(np.zeros(4, np.uint32), 0, t, np.zeros((4, 512), np.uint64),
                   np.zeros((5, 4), np.uint64), "cuda")


@pytest.mark.parametrize("kernel", ["kernel", "self_bounded", "sparse", "encode"])
def test_the_numba_engine_loads_natively_and_both_ways_agree(kernel, rng, monkeypatch):
    """The numba engine's loops run as C kernels loaded without numba (stages.nativecode)
    or through numba's dispatcher, and as plain Python: the same results, the numpy
    twin's (the words span several blocks of the loops' two passes, from position 5)."""
    import stages.datapath as dp
    from stages import nativecode

    assert dp.kernels._native(kernel) is not None, nativecode.failures.get(kernel)
    n = 16
    words = corrupt(pattern_words(3000, n, hit_prob=0.3, artifact_prob=0.02, rng=3)[0],
                    rng, 0.02)
    bounds = ArtifactBounds(np.full(n, 20), np.full(n, 150))

    def once(engine):
        if kernel in ("sparse", "encode"):  # the sparse form of the words (big-endian, as a
            (sw,) = dp.sparse_encode(words.astype(">u4"), 5, n, engine=engine)  # capture)
            t = WordTables(n, bounds)
            out = (np.zeros((n, 512), np.uint64), np.zeros((N_CLASSES, n), np.uint64),
                   np.zeros((n, 512), np.uint64))
            dp.accumulate_sparse(sw, 5, t, out[0], out[1], engine, out[2])
            return (sw.index, sw.words, *out)
        if kernel == "kernel":
            t = WordTables(n, bounds)
            out = (np.zeros((n, 512), np.uint64), np.zeros((N_CLASSES, n), np.uint64),
                   np.zeros((n, 512), np.uint64))
            accumulate(words, 5, t, out[0], out[1], engine, out[2])
            return out
        out = (np.zeros((n, 512), np.uint64), np.zeros((n, 256), np.uint64),
               np.zeros(4000, np.uint32), np.zeros(1, np.int64),
               np.zeros((n, 256, 512), np.uint64), np.zeros((N_CLASSES, n), np.uint64))
        dp.accumulate_self_bounded(words, 5, n, np.full(n, 40), np.full(n, 120), *out[:6],
                                   engine)
        return out

    native = once("numba")
    monkeypatch.setattr(dp.kernels, "_native", lambda name: None)
    dispatched = once("numba")
    monkeypatch.setattr(dp.kernels, "_jitted", lambda name: dp._LOOPS[name])
    plain = once("numba")
    twin = once("numpy")
    assert words.size > 3 * dp.SIFT
    for a, b, c, d in zip(native, dispatched, plain, twin, strict=True):
        assert np.array_equal(a, b) and np.array_equal(a, c) and np.array_equal(a, d)


def test_a_process_with_the_kernels_cached_runs_them_without_numba():
    """What `tcspc histogram` gains at start-up: once built, the C kernels load without
    importing numba (0.5-0.9 s of a fresh process's start before)."""
    import subprocess
    import sys

    import stages.datapath as dp

    assert dp.kernels._native("self_bounded") is not None and dp._native("kernel") is not None
    code = ("import sys, numpy as np; from stages import datapath as dp; "
            "from stages.histogram import SelfBoundingHistogram; "
            "from stages.testpattern import pattern_words; "
            "w, _ = pattern_words(500, 8, hit_prob=0.5, rng=1); "
            "a = SelfBoundingHistogram(8, engine='numba'); a.update(w, 0); a.finish(); "
            "print(sorted(m for m in ('numba', 'scipy') if m in sys.modules))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True)
    assert res.stdout.strip() == "[]", res.stdout + res.stderr


def test_without_a_linker_the_kernel_is_loaded_from_its_object_code(tmp_path, monkeypatch,
                                                                    rng):
    """No cc or ld on the machine: the object code is mapped with llvmlite's MCJIT, and a
    second process-like load reads it back from the cache; same counts as the numpy twin."""
    import stages.datapath as dp
    from stages import nativecode

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(nativecode.shutil, "which", lambda name: None)
    n = 8
    words = corrupt(pattern_words(2000, n, hit_prob=0.3, rng=4)[0], rng, 0.02)
    t = WordTables(n, ArtifactBounds(np.full(n, 20), np.full(n, 150)))
    ref = run(words, n, 0, t.bounds, "numpy")
    for _ in range(2):  # built, then loaded from the cache
        monkeypatch.setattr(nativecode, "_loaded", {})
        assert dp.kernels._native("kernel") is not None, nativecode.failures
        hits, cc = run(words, n, 0, t.bounds, "numba")
        assert np.array_equal(hits, ref[0]) and np.array_equal(cc, ref[1])
    assert not list(tmp_path.glob("*.so")) and list(tmp_path.glob("kernels.kernel-*.o"))
