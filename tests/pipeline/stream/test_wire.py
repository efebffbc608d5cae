import numpy as np
import pyarrow as pa
import pytest
from hypothesis import given
from hypothesis import strategies as st

from pipeline.stream import datagram, wire
from schemas import HISTOGRAMS, RAW_WORDS
from stages.codec import encode_words


def words_batch(words):
    return pa.record_batch([pa.array(words, pa.uint32())], schema=RAW_WORDS.schema)


HEADER = {"kind": "data", "schema": "raw_words", "version": "1.0", "run": "r1", "seq": 3,
          "step": "src", "first_word": 256, "n_tdc": 128, "t_laser_win_ns": 140.0}


@given(st.lists(st.integers(0, 2**32 - 1), max_size=300))
def test_message_roundtrip(words):
    head, batch = wire.decode(wire.encode(HEADER, words_batch(np.array(words, np.uint32))),
                              RAW_WORDS)
    assert head == HEADER
    assert batch.column("word").to_pylist() == words


@pytest.mark.parametrize("frames, reason", [
    ([b"{not json", b""], "bad_header"),
    ([b'{"kind": "data"}', b""], "bad_header"),
    ([b"x"], "bad_frames"),
])
def test_bad_headers(frames, reason):
    with pytest.raises(wire.WireError) as err:
        wire.decode(frames, RAW_WORDS)
    assert err.value.reason == reason


def test_truncated_payload_schema_mismatch_version_and_size():
    frames = wire.encode(HEADER, words_batch(np.arange(100, dtype=np.uint32)))
    cut = [frames[0], frames[1].to_pybytes()[:40]]
    with pytest.raises(wire.WireError, match="bad_payload"):
        wire.decode(cut, RAW_WORDS)
    with pytest.raises(wire.WireError, match="schema_mismatch"):
        wire.decode(frames, HISTOGRAMS)
    bad_version = wire.encode({**HEADER, "version": "2.0"}, words_batch(np.zeros(1, np.uint32)))
    with pytest.raises(wire.WireError, match="schema_version"):
        wire.decode(bad_version, RAW_WORDS)
    with pytest.raises(wire.WireError, match="oversized"):
        wire.decode(frames, RAW_WORDS, max_bytes=100)


def test_stop_message_has_no_payload():
    head, batch = wire.decode(wire.encode({**HEADER, "kind": "stop"}, None), RAW_WORDS)
    assert head["kind"] == "stop" and batch is None


@given(st.integers(1, 127), st.integers(0, 2**32 - 1), st.integers(0, 2**63))
def test_datagram_roundtrip(n_cycles, seq, first):
    w = encode_words(1, 2, 3, 4, np.tile(np.arange(128), n_cycles))
    d = datagram.decode(datagram.encode(w, seq, first, 128, 140_000, last=True))
    assert (d.seq, d.first_cycle, d.n_cycles, d.n_tdc, d.last) == (seq, first, n_cycles,
                                                                    128, True)
    assert np.array_equal(d.words, w)


@pytest.mark.parametrize("mutate, reason", [
    (lambda b: b[:10], "truncated"),
    (lambda b: b"XXXX" + b[4:], "bad_magic"),
    (lambda b: b[:4] + bytes([2]) + b[5:], "bad_version"),
    (lambda b: b[:-4], "bad_length"),
])
def test_bad_datagrams_are_classified(mutate, reason):
    good = datagram.encode(encode_words(0, 0, 0, 0, np.arange(4)), 1, 0, 4, 140_000)
    with pytest.raises(datagram.DatagramError) as err:
        datagram.decode(mutate(good))
    assert err.value.reason == reason


def test_sequence_gaps_with_wrap():
    t = datagram.SequenceTracker()
    for s in (2**32 - 2, 2**32 - 1, 1, 2, 5):
        t.see(s)
    assert t.lost == 1 + 2 and t.received == 5
