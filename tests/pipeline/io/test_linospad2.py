"""LinoSPAD2 files: the real capture decoded exactly, chunking, truncation, detection, the
published calibration's reader."""

from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.io import linospad2 as lio
from schemas.core import validate
from schemas.errors import TcspcError
from schemas.instruments import LINOSPAD2_EVENTS
from stages.instruments import linospad2 as lino

DATA = Path(__file__).parents[2] / "data" / "linospad2"  # public files, see tests/data/README.md
DAT = DATA / "test_data_2212b.dat"
CSV = DATA / "TDC_A5_#36_2212b.csv"
PTU = sorted((Path(__file__).parents[2] / "data" / "picoquant").glob("*.ptu"))

needs_data = pytest.mark.skipif(not DAT.exists() or not CSV.exists(),
                                reason=f"the shared LinoSPAD2 sample is not in {DATA}")


def independent_histograms(raw: bytes, words_per_line=200):
    """Per-pixel (2212b) fine-code counts and word classes, from the format description
    alone, with fresh bit arithmetic (not the code under test)."""
    raw = raw[: len(raw) // 4 * 4]
    w = np.frombuffer(raw, dtype="<u4").astype(np.int64)   # int64: no uint32 surprises
    n = w.size // (65 * words_per_line)
    w = w[: n * 65 * words_per_line].reshape(n, 65, words_per_line)
    line = np.arange(65)[None, :, None] + np.zeros_like(w)
    is_valid = w >= 2**31
    pixel_line = line < 64
    sel = is_valid & pixel_line
    pixel = 4 * line[sel] + (w[sel] // 2**28) % 4
    fine = (w[sel] % 2**28) % 140
    counts = np.zeros((256, 140), np.int64)
    np.add.at(counts, (pixel, fine), 1)
    return counts, {"valid": int(sel.sum()), "invalid": int((~is_valid & pixel_line).sum()),
                    "line65": int((~pixel_line).sum()), "cycles": n}


@pytest.fixture(scope="module")
def real_bytes():
    return DAT.read_bytes()


# ------------------------------------------------------------------------ the real file

@needs_data
def test_real_file_per_pixel_counts_match_an_independent_decode(real_bytes):
    expected, classes = independent_histograms(real_bytes)
    counts, tally = lio.histogram_file(DAT, "2212b", by="pixel")
    assert counts.dtype == np.uint64
    np.testing.assert_array_equal(counts.astype(np.int64), expected)
    by_tdc, tally_tdc = lio.histogram_file(DAT, "2212b", by="tdc")
    np.testing.assert_array_equal(by_tdc.astype(np.int64), expected.reshape(64, 4, 140).sum(1))
    assert tally == tally_tdc
    assert (tally.valid, tally.invalid, tally.line65, tally.cycles) == (
        classes["valid"], classes["invalid"], classes["line65"], classes["cycles"])
    assert tally.accounted and tally.words * 4 == len(real_bytes) and not tally.truncated
    # the sample: 20 cycles of 65 x 200 words, one valid word a cycle in the 65th line
    assert tally.cycles == 20 and tally.line65_valid == 20


@needs_data
def test_real_file_decodes_to_a_valid_events_table(real_bytes):
    table = lio.decode_file(DAT, "2212b")
    validate(table, LINOSPAD2_EVENTS)
    tally = lio.table_tally(table)
    assert table.num_rows == tally.valid and tally.accounted
    assert table.schema.metadata[lio.META_FIRMWARE] == b"2212b"
    expected, _ = independent_histograms(real_bytes)
    pix = table["pixel"].to_numpy().astype(np.int64)
    fine = table["fine"].to_numpy().astype(np.int64)
    np.testing.assert_array_equal(np.bincount(pix * 140 + fine, minlength=256 * 140)
                                  .reshape(256, 140), expected)
    assert np.all(np.diff(table["cycle"].to_numpy().astype(np.int64)) >= 0)
    assert np.all(table["fine"].to_numpy() == table["code"].to_numpy() % 140)
    # the same words read as 2212s: the same TDCs and codes, the pixels remapped
    skip = lio.decode_file(DAT, "2212s")
    assert skip["code"].equals(table["code"]) and skip["tdc"].equals(table["tdc"])
    bits = pix % 4
    np.testing.assert_array_equal(skip["pixel"].to_numpy(), table["tdc"].to_numpy() + 64 * bits)


@needs_data
@settings(max_examples=12, deadline=None)
@given(st.integers(1, 25))
def test_chunked_reading_equals_the_whole(chunk_cycles):
    whole, whole_tally = lio.histogram_file(DAT, "2212b", chunk_cycles=1000)
    counts, tally = lio.histogram_file(DAT, "2212b", chunk_cycles=chunk_cycles)
    np.testing.assert_array_equal(counts, whole)
    assert tally == whole_tally
    chunks = list(lio.iter_cycles(DAT, "2212b", chunk_cycles=chunk_cycles))
    assert len(chunks) == -(-20 // chunk_cycles)
    assert sum((c.tally for c in chunks), lino.Tally()) == whole_tally
    words = np.fromfile(DAT, "<u4").astype(np.uint32)
    ref = lino.decode_words(words, "2212b")
    for name, col in ref.columns().items():
        np.testing.assert_array_equal(np.concatenate([c.columns()[name] for c in chunks]), col)


# ------------------------------------------------------------------------ truncation

@needs_data
@pytest.mark.parametrize("cycles, extra", [(3, 1234), (0, 5000), (1, 3)])
def test_a_truncated_file_uses_the_whole_cycles_and_says_so(tmp_path, real_bytes,
                                                            cycles, extra):
    cut = real_bytes[: cycles * lio.cycle_bytes() + extra]
    path = tmp_path / "cut.dat"
    path.write_bytes(cut)
    expected, classes = independent_histograms(cut)
    counts, tally = lio.histogram_file(path, "2212b")
    np.testing.assert_array_equal(counts.astype(np.int64), expected)
    assert tally.cycles == cycles and tally.truncated_bytes == extra and tally.truncated
    assert tally.words * 4 + tally.truncated_bytes == len(cut) and tally.accounted
    table = lio.decode_file(path, "2212b", chunk_cycles=2)
    assert table.num_rows == classes["valid"] and lio.table_tally(table) == tally
    assert lio.looks_like_linospad2(path) is False
    assert lio.looks_like_linospad2(path, allow_truncated=True) is (cycles > 0)


def test_an_empty_file_reads_as_nothing(tmp_path):
    path = tmp_path / "empty.dat"
    path.write_bytes(b"")
    counts, tally = lio.histogram_file(path, "2212b")
    assert counts.sum() == 0 and tally == lino.Tally()
    assert lio.decode_file(path, "2212b").num_rows == 0
    assert lio.looks_like_linospad2(path) is False


# ------------------------------------------------------------------------- detection

@needs_data
def test_the_real_capture_is_recognised():
    assert lio.looks_like_linospad2(DAT) is True


def test_synthetic_words_are_recognised(tmp_path):
    rng = np.random.default_rng(5)
    w = lino.simulate_words(np.full((64, 140), lino.CODE_PS), 3, rng, words_per_line=50)
    path = tmp_path / "synthetic.dat"
    w.astype("<u4").tofile(path)
    assert lio.looks_like_linospad2(path, words_per_line=50) is True
    assert lio.looks_like_linospad2(path) is False      # 200 words a line: wrong size


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_bytes_are_not_linospad2(tmp_path, seed):
    path = tmp_path / "random.dat"
    path.write_bytes(np.random.default_rng(seed).bytes(3 * lio.cycle_bytes()))
    assert lio.looks_like_linospad2(path) is False


def test_all_zero_words_are_not_linospad2(tmp_path):
    path = tmp_path / "zeros.dat"
    path.write_bytes(bytes(lio.cycle_bytes()))
    assert lio.looks_like_linospad2(path) is False


@needs_data
def test_a_byte_swapped_capture_is_not_linospad2(tmp_path):
    path = tmp_path / "swapped.dat"
    np.fromfile(DAT, "<u4").astype(">u4").tofile(path)
    assert lio.looks_like_linospad2(path) is False


@pytest.mark.skipif(not PTU, reason="no PicoQuant PTU sample in tests/data/picoquant")
@pytest.mark.parametrize("ptu", PTU, ids=lambda p: p.name)
def test_a_ptu_file_is_not_linospad2(ptu, tmp_path):
    assert lio.looks_like_linospad2(ptu) is False
    # nor when cut to a whole number of cycles (the size alone must not decide)
    cut = tmp_path / "cut.ptu"
    raw = ptu.read_bytes()
    cut.write_bytes(raw[: max(1, len(raw) // lio.cycle_bytes()) * lio.cycle_bytes()])
    assert lio.looks_like_linospad2(cut, allow_truncated=True) is False


# ---------------------------------------------------------------- published calibration

@needs_data
def test_the_published_calibration_reads_as_256_by_140_cumulative_ps():
    table = lio.read_published_calibration(CSV)
    assert table.shape == (256, 140) and table.dtype == np.float64
    assert np.all(np.diff(table, axis=1) >= 0)
    live = table[:, -1] > 0
    np.testing.assert_allclose(table[live, -1], 2500.0)   # cumulative: ends at the period
    assert np.flatnonzero(~live).tolist() == [111, 113, 125]
    assert lio.published_name(CSV) == {"daughterboard": "A5", "motherboard": "#36",
                                       "firmware": "2212b"}


def write_csv(path, rows, header=True, index=True):
    lines = []
    if header:
        lines.append("," + ",".join(str(k) for k in range(len(rows[0]))))
    for i, r in enumerate(rows):
        lines.append((f"{i}," if index else "") + ",".join(str(v) for v in r))
    path.write_text("\n".join(lines) + "\n")
    return path


def good_rows():
    return np.tile(np.linspace(0, 2500, 140), (256, 1))


def test_a_bare_table_without_header_or_index_is_accepted(tmp_path):
    path = write_csv(tmp_path / "bare.csv", good_rows(), header=False, index=False)
    np.testing.assert_allclose(lio.read_published_calibration(path), good_rows())


@pytest.mark.parametrize("case, match", [
    ("rows", "256 pixel rows"),
    ("codes", "header should be"),
    ("codes_bare", "256 pixel rows of 140 codes"),
    ("text", "not a number"),
    ("decreasing", "decrease"),
    ("range", "outside 0..2500"),
    ("index", "pixel index"),
    ("empty", "empty"),
])
def test_a_malformed_calibration_is_refused_clearly(tmp_path, case, match):
    rows = good_rows().tolist()
    path = tmp_path / f"{case}.csv"
    if case == "rows":
        write_csv(path, rows[:255])
    elif case == "codes":
        write_csv(path, [r[:139] for r in rows])
    elif case == "codes_bare":
        write_csv(path, [r[:139] for r in rows], header=False, index=False)
    elif case == "text":
        rows[7][3] = "x"
        write_csv(path, rows)
    elif case == "decreasing":
        rows[9][50] = 3000.0
        rows[9][51] = 10.0
        write_csv(path, rows)
    elif case == "range":
        rows[2][139] = 2600.0
        write_csv(path, rows)
    elif case == "index":
        path.write_text("," + ",".join(map(str, range(140))) + "\n" + "\n".join(
            f"{i + 1}," + ",".join(map(str, r)) for i, r in enumerate(rows)) + "\n")
    else:
        path.write_text("")
    with pytest.raises(lio.Linospad2Error, match=match) as info:
        lio.read_published_calibration(path)
    assert str(path) in str(info.value)
    assert isinstance(info.value, TcspcError) and isinstance(info.value, ValueError)


def test_bad_arguments_are_linospad2_errors(tmp_path):
    path = tmp_path / "x.dat"
    path.write_bytes(bytes(lio.cycle_bytes()))
    with pytest.raises(lio.Linospad2Error, match="2208"):
        lio.histogram_file(path, "2208")
    with pytest.raises(lio.Linospad2Error, match="by must be"):
        lio.histogram_file(path, "2212b", by="row")
    with pytest.raises(lio.Linospad2Error, match="chunk_cycles"):
        list(lio.iter_cycles(path, "2212b", chunk_cycles=0))
    with pytest.raises(lio.Linospad2Error, match="no LinoSPAD2 tally"):
        lio.table_tally(pa.table({"a": [1]}))
