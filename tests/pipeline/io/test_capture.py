import json
import tracemalloc

import numpy as np
import pytest

from pipeline.io.capture import Capture, CaptureWriter, write_capture
from schemas import CaptureError
from stages.testpattern import pattern_words


def sidecar(path, **overrides):
    meta = {"format": "tcspc-raw", "version": 1, "n_tdc": 4, "window_ns": 80.0,
            "t_laser_win_ns": 140.0, "cycles": 2}
    meta.update(overrides)
    path.with_suffix(".json").write_text(json.dumps(meta))


@pytest.fixture
def small(tmp_path):
    words, _ = pattern_words(50, 4, hit_prob=0.5, rng=1)
    write_capture(tmp_path / "cap", words, 4, kind="range", truth={"x": 1})
    return tmp_path / "cap", words


def test_roundtrip_and_chunks(small):
    path, words = small
    cap = Capture(path.with_suffix(".bin"))
    assert cap.meta.cycles == 50 and cap.meta.kind == "range" and cap.meta.truth == {"x": 1}
    assert np.array_equal(cap.read_words(0, cap.n_words), words)
    got = [(first, w.copy()) for first, w in cap.iter_chunks(chunk_words=13)]
    assert all(first % 4 == 0 for first, _ in got)  # chunks are whole cycles
    assert np.array_equal(np.concatenate([w for _, w in got]), words)
    assert (path.with_suffix(".bin").read_bytes()[:4]
            == int(words[0]).to_bytes(4, "big"))  # big-endian on disk


def test_size_not_multiple_of_four(tmp_path):
    (tmp_path / "c.bin").write_bytes(b"\0" * 33)
    sidecar(tmp_path / "c.bin")
    with pytest.raises(CaptureError, match=r"c.bin: size 33 bytes is not a multiple of 4"):
        Capture(tmp_path / "c.bin")


def test_missing_and_invalid_sidecar(tmp_path):
    (tmp_path / "c.bin").write_bytes(b"\0" * 32)
    with pytest.raises(CaptureError, match=r"c.json: sidecar not found"):
        Capture(tmp_path / "c.bin")
    (tmp_path / "c.json").write_text("{not json")
    with pytest.raises(CaptureError, match=r"c.json: sidecar is not valid JSON"):
        Capture(tmp_path / "c")
    with pytest.raises(CaptureError, match=r"nothing.bin: capture not found \(.*nothing.bin "
                                           r"does not exist\); a capture is NAME.bin"):
        Capture(tmp_path / "nothing.bin")


def test_a_file_that_is_not_a_capture_is_named(tmp_path):
    """`tcspc calibrate lsb notes.txt` names notes.txt and says what a capture is."""
    (tmp_path / "notes.txt").write_text("a note")
    with pytest.raises(CaptureError) as info:
        Capture(tmp_path / "notes.txt")
    assert str(info.value) == (f"{tmp_path / 'notes.txt'}: not a capture (notes.txt.bin not "
                               "found); a capture is NAME.bin (raw 32-bit words) with "
                               "NAME.json beside it")
    with pytest.raises(CaptureError, match="a directory, not a capture"):
        Capture(tmp_path)


@pytest.mark.parametrize("overrides, message", [
    ({"version": 2}, "format version 2 is not readable by this software, which knows version 1"),
    ({"format": "csv"}, "format is 'csv', expected 'tcspc-raw'"),
    ({"n_tdc": 0}, "n_tdc must be an integer in 1..256, found 0"),
    ({"window_ns": float("nan")}, "window_ns must be a positive number"),
    ({"cycles": 3}, "holds 8 words, but the sidecar says 3 cycles x 4 TDCs = 12"),
])
def test_bad_sidecar_values(tmp_path, overrides, message):
    (tmp_path / "c.bin").write_bytes(b"\0" * 32)
    sidecar(tmp_path / "c.bin", **overrides)
    with pytest.raises(CaptureError, match=message.replace("(", r"\(")):
        Capture(tmp_path / "c.bin")
    if "cycles" in overrides:
        assert Capture(tmp_path / "c.bin", strict=False).n_words == 8


def test_n_tdc_that_does_not_match_the_addresses(tmp_path):
    words, _ = pattern_words(100, 64, hit_prob=0.2, rng=2)
    write_capture(tmp_path / "c", words, 64)
    sidecar(tmp_path / "c.bin", n_tdc=128, cycles=50)
    with pytest.raises(CaptureError, match="n_tdc=128 in the sidecar does not match the "
                                           r"words' addresses.*suggesting n_tdc=64"):
        Capture(tmp_path / "c.bin")


def test_writer_refuses_partial_cycle_and_leaves_nothing(tmp_path):
    with pytest.raises(CaptureError, match="not a whole number of cycles"):
        with CaptureWriter(tmp_path / "c", n_tdc=4) as w:
            w.write(np.zeros(6, np.uint32))
    with pytest.raises(RuntimeError):
        with CaptureWriter(tmp_path / "d", n_tdc=4) as w:
            w.write(np.zeros(8, np.uint32))
            raise RuntimeError("crash mid-capture")
    assert list(tmp_path.iterdir()) == []


def test_reading_is_bounded_in_memory(tmp_path):
    """Memory used while streaming does not grow with the capture (4 MiB chunks)."""
    words, _ = pattern_words(20_000, 128, rng=3)  # 10 MiB on disk
    write_capture(tmp_path / "big", words, 128)
    del words
    cap = Capture(tmp_path / "big")
    tracemalloc.start()
    total = 0
    for _, w in cap.iter_chunks(chunk_words=1 << 18):
        total += int(w.size)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert total == cap.n_words
    assert peak < 2 * 4 * (1 << 18) + (1 << 20)  # one 1 MiB buffer (+ slack), not 10 MiB
