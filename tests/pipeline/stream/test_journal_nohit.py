"""The journal's zstd-nohit frames (pipeline.io.nohit): lossless for any words at any
chunk offset, every damage detected, readable beside older segments, and exported back to
the raw capture byte for byte."""

import json
import os

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.cli import cli
from pipeline.io import nohit
from pipeline.io.capture import Capture, write_capture
from pipeline.stream.journal import (
    JournalCorrupt,
    JournalEncodingUnknown,
    JournalWriter,
    _entries,
    read_range,
    segment_path,
    verify,
)
from stages.codec import encode_words
from stages.testpattern import pattern_words


def _expected(n_tdc: int, first: int, n: int) -> np.ndarray:
    """The no-hit words of positions first .. first + n - 1, from docs/design.md's table
    (markers 0 0 1 at bits 11-9, the address at bits 8-1, every timing field 0), built
    with the codec, not with the code under test."""
    pos = (first + np.arange(n)) % n_tdc
    return encode_words(0, 0, 0, 0, pos & 0xFF).astype(np.uint32)


def test_the_kernel_is_compiled_and_loaded():
    from stages import nativecode

    assert nohit._kernel() is not None, nativecode.failures.get("split")


def test_the_pattern_is_the_chips_no_hit_word():
    for n_tdc in (1, 7, 128, 300):
        assert np.array_equal(nohit.no_hit_words(n_tdc), _expected(n_tdc, 0, n_tdc))


def _words(draw_bits, n_tdc, first, n, p_other, rng):
    """No-hit words with a share replaced by arbitrary 32-bit values (hits, malformed and
    invalid words, wrong addresses: anything)."""
    w = _expected(n_tdc, first, n)
    other = rng.random(n) < p_other
    w[other] = rng.integers(0, 2**32, int(other.sum()), dtype=np.uint64).astype(np.uint32)
    if draw_bits:  # and words one bit away from the no-hit word
        near = rng.random(n) < 0.05
        w[near] ^= np.uint32(1) << rng.integers(0, 32, int(near.sum())).astype(np.uint32)
    return w


@settings(max_examples=200, deadline=None)
@given(n_tdc=st.integers(1, 300), first=st.integers(0, 2**40), n=st.integers(0, 3000),
       p=st.sampled_from([0.0, 0.05, 0.18, 0.5, 1.0]), bits=st.booleans(),
       big=st.booleans(), seed=st.integers(0, 2**32 - 1))
def test_any_words_at_any_offset_round_trip(n_tdc, first, n, p, bits, big, seed):
    rng = np.random.default_rng(seed)
    w = _words(bits, n_tdc, first, n, p, rng)
    content = nohit.encode(w.astype(">u4") if big else w, first, n_tdc)
    # the compiled kernel and its numpy twin write the same frame
    assert nohit.encode(w.astype(">u4") if big else w, first, n_tdc, native=False) == content
    got_first, back = nohit.decode(content, first, n)
    assert got_first == first and back.dtype == np.dtype(">u4")
    assert back.tobytes() == w.astype(">u4").tobytes()  # byte for byte
    # a strided chunk (not contiguous) encodes the same
    if n:
        wide = np.repeat(w, 2)[::2]
        assert nohit.encode(wide, first, n_tdc) == content


@settings(max_examples=30, deadline=None)
@given(cuts=st.lists(st.integers(1, 700), min_size=1, max_size=10),
       seed=st.integers(0, 1000), seg=st.sampled_from([900, 1 << 20]))
def test_chunks_not_on_cycle_boundaries_read_back(tmp_path_factory, cuts, seed, seg):
    """Chunks of any length (so starting anywhere in a cycle), over segments, read back
    exactly over any range, and a segment is a capture."""
    n_tdc = 13
    w, _ = pattern_words(400, n_tdc, hit_prob=0.2, rng=seed)
    w[::97] = 0xFFFFFFFF  # malformed words among them
    d = tmp_path_factory.mktemp("nh")
    j = JournalWriter(d, "r", n_tdc, 140.0, segment_words=seg, compression="zstd-nohit")
    first = 0
    for c in cuts:
        j.append(first, w[first:first + c])
        first += c
    j.close()
    total = min(first, w.size)
    for lo, hi in ((0, total), (total // 3, 2 * total // 3 + 1)):
        got = [x for _, x in read_range(d, "r", lo, hi)]
        assert np.array_equal(np.concatenate(got) if got else w[:0], w[lo:hi])
    v = verify(d, "r")
    assert v["corrupt"] == [] and v["unchecked_chunks"] == 0 and v["words"] == total


@pytest.fixture(scope="module")
def journal(tmp_path_factory):
    d = tmp_path_factory.mktemp("flip")
    rng = np.random.default_rng(7)
    w = _words(True, 4, 0, 4000, 0.2, rng)
    j = JournalWriter(d, "r", 4, 140.0, compression="zstd-nohit")
    for i in range(10):
        j.append(i * 400 + 3, w[i * 400:(i + 1) * 400])  # (not on a cycle boundary)
    j.close()
    seg = segment_path(d, "r", 0, "zstd-nohit")
    return d, w, seg, seg.read_bytes(), [e for e in _entries(d / "r.index.jsonl")
                                         if "first_word" in e]


@settings(max_examples=60, deadline=None)
@given(chunk=st.integers(0, 9), at=st.floats(0, 1, exclude_max=True), bit=st.integers(0, 7))
def test_every_single_bit_flip_is_detected_or_harmless(journal, chunk, at, bit):
    """A flipped bit fails the frame (zstd's decoding or checksum, or the content's own
    sizes), or lies where zstd never reads it (a block's padding) and every word reads
    back exact: never a wrong word."""
    d, w, seg, clean, entries = journal
    e = entries[chunk]
    data = bytearray(clean)
    data[e["offset"] + int(at * e["bytes"])] ^= 1 << bit
    try:
        seg.write_bytes(bytes(data))
        v = verify(d, "r")
        if not v["corrupt"]:  # a bit zstd's decoder never reads (padding): the words hold
            got = np.concatenate([x for _, x in read_range(d, "r", 0, 4003)])
            assert np.array_equal(got, w)
            return
        assert [c[0] for c in v["corrupt"]] == [e["first_word"]]
        with pytest.raises(JournalCorrupt):
            list(read_range(d, "r", 0, 4003))
        got = list(read_range(d, "r", 0, 4003, lambda *a: None))
        keep = np.delete(w, np.s_[chunk * 400:(chunk + 1) * 400])
        assert np.array_equal(np.concatenate([x for _, x in got]), keep)
    finally:
        seg.write_bytes(clean)


def test_a_truncated_frame_is_detected(journal):
    d, w, seg, clean, entries = journal
    try:
        for cut in (1, 7, entries[-1]["bytes"] - 1):
            os.truncate(seg, len(clean) - cut)
            v = verify(d, "r")
            assert [c[0] for c in v["corrupt"]] == [entries[-1]["first_word"]], cut
            assert "truncated" in v["corrupt"][0][2]
    finally:
        seg.write_bytes(clean)
    assert verify(d, "r")["corrupt"] == []


def test_content_that_disagrees_with_itself_or_the_index_is_refused():
    w = _expected(16, 5, 100)
    w[[3, 50]] = 7
    good = nohit.encode(w, 5, 16)
    with pytest.raises(nohit.FrameError, match="index says 99"):
        nohit.decode(good, 5, 99)
    with pytest.raises(nohit.FrameError, match="starts at word 5"):
        nohit.decode(good, 6, 100)
    with pytest.raises(nohit.FrameError, match="whole words"):
        nohit.decode(good[:-1])
    with pytest.raises(nohit.FrameError, match="marks 2 words, 1 follow"):
        nohit.decode(good[:-4])
    with pytest.raises(nohit.FrameError, match="magic"):
        nohit.decode(b"XXXX" + good[4:])
    with pytest.raises(nohit.FrameError, match="n_tdc 16 in the frame header, the sidecar "
                       "says 8"):
        nohit.decode(good, n_tdc=8)
    huge = bytearray(good)
    huge[4:8] = (1 << 31).to_bytes(4, "little")  # (no pattern of 2**31 words is built)
    with pytest.raises(nohit.FrameError, match="n_tdc 2147483648"):
        nohit.decode(bytes(huge))


def test_an_unknown_encoding_is_refused_by_name(tmp_path):
    j = JournalWriter(tmp_path, "r", 4, 140.0)
    j.append(0, np.arange(40, dtype=np.uint32))
    j.close()
    index = tmp_path / "r.index.jsonl"
    lines = index.read_text().splitlines()
    e = json.loads(lines[0])
    e["enc"] = "zstd-future"
    index.write_text("\n".join([json.dumps(e), *lines[1:]]) + "\n")
    for read in (lambda: list(read_range(tmp_path, "r", 0, 40)),
                 lambda: verify(tmp_path, "r")):
        with pytest.raises(JournalEncodingUnknown, match="'zstd-future'.*word 0"):
            read()


def test_a_run_resumed_with_another_encoding_reads_as_one(tmp_path):
    """Raw, zstd and zstd-nohit segments of one run (a daemon restarted with another
    journal_compression, or an old journal) read back, verify and export alike."""
    w, _ = pattern_words(300, 8, hit_prob=0.1, rng=4)
    for k, enc in enumerate((None, "zstd", "zstd-nohit")):
        j = JournalWriter(tmp_path, "r", 8, 140.0, compression=enc)
        j.append(k * 800, w[k * 800:(k + 1) * 800])
        j.close()
    assert [e.get("enc") for e in _entries(tmp_path / "r.index.jsonl")
            if "first_word" in e] == [None, "zstd", "zstd-nohit"]
    assert np.array_equal(np.concatenate([x for _, x in read_range(tmp_path, "r", 0, 2400)]),
                          w)
    assert verify(tmp_path, "r")["corrupt"] == []
    for k, enc in enumerate((None, "zstd", "zstd-nohit")):
        seg = segment_path(tmp_path, "r", k, enc)
        out = tmp_path / f"out{k}"
        res = CliRunner().invoke(cli, ["journal", "export", str(seg), str(out)])
        assert res.exit_code == 0, res.output
        write_capture(tmp_path / f"ref{k}", w[k * 800:(k + 1) * 800], 8, kind="journal")
        assert (out.with_suffix(".bin").read_bytes()
                == (tmp_path / f"ref{k}.bin").read_bytes())
        assert Capture(out).meta.kind == "journal"
    again = CliRunner().invoke(cli, ["journal", "export", str(seg), str(out)])
    assert again.exit_code == 2 and "exists; give --overwrite" in again.output


@pytest.mark.parametrize("enc", ["zstd-nohit", "zstd"])
def test_every_flip_in_a_frame_header_is_detected_or_harmless(tmp_path, enc):
    """Every bit of a frame's first 12 bytes (zstd's magic, descriptor and content size):
    a flip there is reported as corrupt (a content size grown to terabytes included: no
    allocation, no MemoryError), or changes nothing read (the checksum flag turned off:
    the same words)."""
    rng = np.random.default_rng(3)
    w = _words(False, 4, 0, 4000, 0.2, rng)
    j = JournalWriter(tmp_path, "r", 4, 140.0, compression=enc)
    j.append(0, w)
    j.close()
    seg = segment_path(tmp_path, "r", 0, enc)
    clean = seg.read_bytes()
    harmless = 0
    for byte in range(12):
        for bit in range(8):
            data = bytearray(clean)
            data[byte] ^= 1 << bit
            seg.write_bytes(bytes(data))
            if verify(tmp_path, "r")["corrupt_words"] != 4000:
                (_, got), = read_range(tmp_path, "r", 0, 4000)
                assert np.array_equal(got, w), (byte, bit)
                harmless += 1
    assert harmless <= 2


def test_a_segment_is_a_capture_and_a_damaged_one_is_refused(tmp_path):
    """A closed zstd-nohit segment is recognised as a capture and reads as one; a flipped
    bit inside it is a CaptureError naming the file, never words."""
    from pipeline.io.formats import detect_format
    from schemas.errors import CaptureError

    w, _ = pattern_words(2000, 16, hit_prob=0.18, rng=5)
    j = JournalWriter(tmp_path, "r", 16, 140.0, compression="zstd-nohit")
    for i in range(0, w.size, 4000):
        j.append(i, w[i:i + 4000])
    j.close()
    seg = segment_path(tmp_path, "r", 0, "zstd-nohit")
    assert detect_format(seg) == "tcspc"
    assert np.array_equal(np.concatenate([x.copy() for _, x in Capture(seg).iter_chunks(
        5000)]), w)
    data = bytearray(seg.read_bytes())
    data[len(data) // 2] ^= 0x10
    seg.write_bytes(bytes(data))
    with pytest.raises(CaptureError, match="r-000000.bin.nhz"):
        for _ in Capture(seg).iter_chunks(5000):
            pass
