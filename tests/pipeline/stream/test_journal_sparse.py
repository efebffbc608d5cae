"""A chip's source journals the sparse form it sends: the zstd-nohit frame made from it is
byte for byte the frame made from the words (so every reader, old or new, reads it)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.io import nohit
from pipeline.stream.journal import FrameEncoder, JournalWriter, read_range
from stages.datapath import sparse_encode


@settings(max_examples=50, deadline=None)
@given(n_tdc=st.integers(1, 40), n=st.integers(0, 600), first=st.integers(0, 10**9),
       p=st.sampled_from([0.0, 0.05, 0.5, 1.0]), big=st.booleans(), seed=st.integers(0, 2**31))
def test_the_frame_from_the_sparse_form_is_the_frame_from_the_words(n_tdc, n, first, p, big,
                                                                     seed):
    rng = np.random.default_rng(seed)
    pos = (first + np.arange(n)) % n_tdc
    words = ((1 << 9) | (pos << 1)).astype(np.uint32)  # no-hit words, from the contract
    other = rng.random(n) < p
    words[other] = rng.integers(0, 1 << 32, int(other.sum()), dtype=np.uint64)
    held = words.astype(">u4") if big else words
    (sw,) = sparse_encode(held, first, n_tdc)
    assert nohit.encode_sparse(sw.index, sw.words, n, first, n_tdc) == nohit.encode(
        held, first, n_tdc)
    enc = FrameEncoder("zstd-nohit", n_tdc)
    assert enc.encode(first, held, sw)[0] == enc.encode(first, held)[0]


def test_a_journal_written_from_sparse_forms_reads_back_every_word(tmp_path):
    rng = np.random.default_rng(5)
    n_tdc = 16
    words = ((1 << 9) | (np.tile(np.arange(n_tdc), 3000) << 1)).astype(np.uint32)
    hit = rng.random(words.size) < 0.1
    words[hit] = rng.integers(0, 1 << 32, int(hit.sum()), dtype=np.uint64)
    jw = JournalWriter(tmp_path, "r", n_tdc, 140.0)
    for a in range(0, words.size, 4096):
        chunk = words[a:a + 4096].astype(">u4")
        jw.append(a, chunk, sparse=sparse_encode(chunk, a, n_tdc)[0])
    jw.close()
    got = np.concatenate([w for _, w in read_range(tmp_path, "r", 0, words.size)])
    np.testing.assert_array_equal(got.astype(np.uint32), words)
