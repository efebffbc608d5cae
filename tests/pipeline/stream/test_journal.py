"""The journal's segments, compressed (zstd-nohit frames, the default, and zstd frames) and
raw: every word range reads back exactly, a closed compressed segment is a capture, and
`zstd -d` turns a zstd one into the raw capture of docs/design.md byte for byte."""

import shutil
import subprocess

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.io.capture import Capture
from pipeline.stream.journal import JournalCapture, JournalWriter, read_range, segment_files
from stages.testpattern import pattern_words

N_TDC = 16


def _journal(path, words, chunks, enc, segment_words=1 << 26):
    w = JournalWriter(path, "r", N_TDC, 140.0, segment_words=segment_words, compression=enc)
    first = 0
    for n in chunks:
        w.append(first, words[first:first + n])
        first += n
    w.close()
    return w


@settings(max_examples=25, deadline=None)
@given(cuts=st.lists(st.integers(1, 40), min_size=1, max_size=12),
       a=st.integers(0, 3000), span=st.integers(0, 3000), seg=st.sampled_from([500, 1 << 20]))
def test_any_word_range_reads_back_exactly(tmp_path_factory, cuts, a, span, seg):
    words, _ = pattern_words(400, N_TDC, hit_prob=0.3, rng=len(cuts))
    chunks = [c * N_TDC for c in cuts]
    chunks[-1] += words.size - sum(chunks) if sum(chunks) < words.size else 0
    total = min(sum(chunks), words.size)
    for enc in ("zstd-nohit", "zstd", None):
        d = tmp_path_factory.mktemp(f"j{enc}")
        _journal(d, words, chunks, enc, segment_words=seg)
        lo, hi = min(a, total), min(a + span, total)
        got = [w for _, w in read_range(d, "r", lo, hi)]
        back = np.concatenate(got) if got else np.empty(0, np.uint32)
        assert np.array_equal(back, words[lo:hi])


@pytest.mark.parametrize("enc, ext", [("zstd", ".bin.zst"), ("zstd-nohit", ".bin.nhz")])
def test_compressed_segments_are_small_captures(tmp_path, enc, ext):
    words, _ = pattern_words(4096, N_TDC, hit_prob=0.05, rng=1)
    _journal(tmp_path / "z", words, [256 * N_TDC] * 16, enc)
    _journal(tmp_path / "raw", words, [256 * N_TDC] * 16, None)
    (z,), (raw,) = segment_files(tmp_path / "z", "r"), segment_files(tmp_path / "raw", "r")
    assert z.name == "r-000000" + ext and raw.name == "r-000000.bin"
    assert z.stat().st_size < 0.2 * raw.stat().st_size  # 5 % hits: mostly no-hit words
    cap = Capture(z)  # the sidecar r-000000.json beside it, kind journal
    assert cap.compressed and cap.meta.kind == "journal" and cap.n_words == words.size
    assert np.array_equal(np.concatenate([w.copy() for _, w in cap.iter_chunks(3000)]),
                          words)
    assert np.array_equal(cap.read_words(1000, 77), words[1000:1077])
    run = JournalCapture(tmp_path / "z", "r")
    assert np.array_equal(np.concatenate([w for _, w in run.iter_chunks()]), words)


@pytest.mark.skipif(shutil.which("zstd") is None, reason="the zstd command is not installed")
def test_zstd_d_gives_the_raw_capture(tmp_path):
    words, _ = pattern_words(1024, N_TDC, hit_prob=0.3, rng=2)
    _journal(tmp_path / "z", words, [64 * N_TDC] * 16, "zstd")
    _journal(tmp_path / "raw", words, [64 * N_TDC] * 16, None)
    z = tmp_path / "z" / "r-000000.bin.zst"
    subprocess.run(["zstd", "-q", "-d", str(z), "-o", str(tmp_path / "out.bin")], check=True)
    assert (tmp_path / "out.bin").read_bytes() == (tmp_path / "raw" / "r-000000.bin").read_bytes()


@pytest.mark.parametrize("enc, ext", [("zstd", ".bin.zst"), ("zstd-nohit", ".bin.nhz")])
def test_a_compressed_capture_shorter_than_its_sidecar_is_refused(tmp_path, enc, ext):
    words, _ = pattern_words(256, N_TDC, hit_prob=0.3, rng=3)
    _journal(tmp_path, words, [128 * N_TDC] * 2, enc)
    z = tmp_path / f"r-000000{ext}"
    frames = z.read_bytes()
    z.write_bytes(frames[: len(frames) // 3])  # cut inside the first frame
    from schemas.errors import CaptureError

    with pytest.raises(CaptureError, match=f"r-000000{ext}"):
        cap = Capture(z)
        for _ in cap.iter_chunks():
            pass


def test_unknown_compression_is_refused(tmp_path):
    with pytest.raises(ValueError, match="journal compression must be one of"):
        JournalWriter(tmp_path, "r", N_TDC, 140.0, compression="gzip")
