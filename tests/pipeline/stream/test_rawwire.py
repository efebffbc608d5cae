"""The source's one-copy raw-words messages are wire.encode's, byte for byte."""

import numpy as np
import pyarrow as pa
import pytest

from pipeline.io.capture import Capture, CaptureWriter
from pipeline.stream import wire
from pipeline.stream.fanout import TdcSplitter
from pipeline.stream.rawwire import RawWordsEncoder
from schemas.words import RAW_WORDS


def _head(n_tdc):
    return {"kind": "data", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
            "run": "r", "seq": 3, "step": "source", "first_word": 0, "n_tdc": n_tdc,
            "t_laser_win_ns": 140.0}


@pytest.mark.parametrize("n", [0, 1, 3, 8, 1001, 1 << 16])
@pytest.mark.parametrize("order", ["<u4", ">u4"])
def test_frames_equal_wire_encode_in_either_byte_order(n, order):
    w = np.random.default_rng(n).integers(0, 2**32, n, dtype=np.uint64).astype(np.uint32)
    ref = wire.encode(_head(8), pa.record_batch([pa.array(w)], schema=RAW_WORDS.schema), "t")
    enc = RawWordsEncoder()
    for _ in range(2):  # made, then from the kept template
        got = enc.frames(_head(8), w.astype(order), "t")
        assert got[0] == ref[0] and got[1].tobytes() == ref[1].to_pybytes()
        head, batch = wire.decode(got, RAW_WORDS, token="t")
        assert np.array_equal(batch.column("word").to_numpy(), w)


def test_a_capture_read_as_stored_splits_into_the_same_messages(tmp_path):
    """A capture's big-endian words (as the journal takes them), cut by TDC range as
    views: the messages of the native words split by copying."""
    from stages.testpattern import pattern_words

    words, _ = pattern_words(40, 16, hit_prob=0.3, rng=1)
    with CaptureWriter(tmp_path / "c", 16) as cw:
        cw.write(words)
    (first, be), = Capture(tmp_path / "c.bin").iter_chunks(native=False)
    assert be.dtype == np.dtype(">u4") and np.array_equal(be, words)
    ranges = [(0, 5), (5, 16)]
    sp, enc = TdcSplitter(16, ranges), RawWordsEncoder()
    for (f, view), (f2, part), (a, b) in zip(sp.views(first, be), sp.split(first, words),
                                              ranges, strict=True):
        assert f == f2
        h = {**_head(b - a), "first_word": f}
        ref = wire.encode(h, pa.record_batch([pa.array(part)], schema=RAW_WORDS.schema))
        assert enc.frames(h, view)[1].tobytes() == ref[1].to_pybytes()
