"""PTU files: the two shared instrument files against a decode written here from PicoQuant's
description, every record type through write_ptu, streaming, and broken files."""

import struct
import tracemalloc
from pathlib import Path

import numpy as np
import pyarrow as pa
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.io.formats import is_ptu
from pipeline.io.ptu import (
    DecodeReport,
    PtuError,
    decode,
    histogram_t3,
    iter_chunks,
    iter_decoded_batches,
    read_header,
    write_ptu,
)
from schemas import PTU_T2_EVENTS, PTU_T3_EVENTS, TcspcError, validate
from stages.instruments.ptu import (
    FORMATS,
    SYNC_CHANNEL,
    decode_records,
    histogram_records,
    record_format,
)

DATA = Path(__file__).parents[2] / "data" / "picoquant"  # public files, see tests/data/README.md
HH_T3 = DATA / "hydraharp_v20_t3.ptu"
PH_T2 = DATA / "picoharp_v30_t2.ptu"
needs_data = pytest.mark.skipif(not (HH_T3.is_file() and PH_T2.is_file()),
                                reason="shared PicoQuant files not present")
ALL_CODES = sorted(FORMATS)


def raw_records(path):
    """The records of a PTU file, found without the code under test: the data starts right
    after the Header_End tag (48 bytes: 32 name, 4 index, 4 type, 8 value)."""
    blob = Path(path).read_bytes()
    at = blob.index(b"Header_End\0")
    return np.frombuffer(blob, "<u4", offset=at + 48).astype(np.uint32)


# --- the shared files, decoded here with plain numpy bit operations -----------------------

@needs_data
def test_hydraharp_v2_t3_file_exact():
    h = read_header(HH_T3)
    assert (h.record_type, h.format.name, h.n_records) == (0x01010304, "HydraHarp2T3", 106349)
    assert round(h.resolution_s * 1e12, 6) == 64.0 and h.sync_rate_hz == 4999960
    assert h.n_input_channels == 2 and not h.truncated and h.records_in_file == h.n_records
    assert h.tags["HW_Type"] == "HydraHarp" and h.version == "1.0.00"

    # HydraHarp V2 T3, from the MSB: special 1, channel 6, dtime 15, nsync 10; special +
    # channel 63 = overflow of nsync (0 means 1) x 1024 syncs; special + 1..15 = markers
    w = raw_records(HH_T3).astype(np.int64)
    special, chan = w >> 31, (w >> 25) & 63
    dtime, nsync = (w >> 10) & 0x7FFF, w & 0x3FF
    ovf = (special == 1) & (chan == 63)
    ofl = np.cumsum(np.where(ovf, np.where(nsync == 0, 1, nsync), 0)) * 1024
    photon = special == 0
    marker = (special == 1) & (chan >= 1) & (chan <= 15)
    assert (photon.sum(), marker.sum(), ovf.sum()) == (77883, 0, 28466)  # golden
    assert np.bincount(chan[photon]).tolist() == [45012, 32871]

    t = decode(HH_T3, chunk_records=10000)
    validate(t, PTU_T3_EVENTS)
    assert t.column("kind").to_numpy().tolist() == [0] * 77883
    assert np.array_equal(t.column("channel").to_numpy(), chan[photon])
    assert np.array_equal(t.column("nsync").to_numpy(), (ofl + nsync)[photon])
    assert np.array_equal(t.column("dtime").to_numpy(), dtime[photon])
    md = t.schema.metadata
    assert md[b"ptu.records_read"] == b"106349" and md[b"ptu.overflow_records"] == b"28466"
    assert md[b"ptu.invalid"] == b"0" and md[b"ptu.truncated"] == b"false"
    assert int(t.column("nsync")[-1].as_py()) == 49999358  # 10 s at 5 MHz

    counts, header, tally, truncated = histogram_t3(HH_T3, chunk_records=4096)
    want = np.zeros((2, 32768), np.uint64)
    np.add.at(want, (chan[photon], dtime[photon]), 1)
    assert counts.shape == (2, 32768) and np.array_equal(counts, want)
    assert (tally.n_photons, tally.n_overflow_records, tally.n_out_of_range,
            tally.max_dtime, tally.n_records, truncated) == (77883, 28466, 0, 3124, 106349,
                                                             False)
    assert tally.wraps * 1024 == ofl[-1]


@needs_data
def test_picoharp_t2_file_exact():
    h = read_header(PH_T2)
    assert (h.record_type, h.format.name, h.n_records) == (0x00010203, "PicoHarpT2", 929254)
    assert h.global_resolution_s == 4e-12

    # PicoHarp T2, from the MSB: channel 4, timetag 28; channel 15 = special, its low 4
    # bits markers, 0 = overflow of 210698240; channel 0 is the sync input
    w = raw_records(PH_T2).astype(np.int64)
    chan, timetag = w >> 28, w & 0x0FFFFFFF
    ovf = (chan == 15) & ((w & 15) == 0)
    ofl = np.cumsum(ovf) * 210698240
    event = chan != 15
    assert np.bincount(chan[event]).tolist() == [531477, 388700]  # golden: sync, input 1
    assert ovf.sum() == 9077 and ((chan == 15) & ~ovf).sum() == 0

    t = decode(PH_T2, chunk_records=65536)
    validate(t, PTU_T2_EVENTS)
    assert t.num_rows == 920177
    want_channel = np.where(chan[event] == 0, SYNC_CHANNEL, chan[event] - 1)
    assert np.array_equal(t.column("channel").to_numpy(), want_channel)
    assert np.array_equal(t.column("time_ps").to_numpy(), (ofl + timetag)[event] * 4)
    md = t.schema.metadata
    assert (md[b"ptu.photons"], md[b"ptu.sync"], md[b"ptu.overflow_records"]) == (
        b"388700", b"531477", b"9077")
    with pytest.raises(PtuError, match="PicoHarpT2 is T2 data: there is no dtime"):
        histogram_t3(PH_T2)


@needs_data
def test_shared_files_agree_with_tttrlib():
    tttrlib = pytest.importorskip("tttrlib")
    d = tttrlib.TTTR(str(HH_T3))
    t = decode(HH_T3)
    photons = np.asarray(d.get_event_type()) == 0
    assert photons.sum() == t.num_rows
    assert np.array_equal(np.asarray(d.get_micro_times())[photons],
                          t.column("dtime").to_numpy())
    assert np.array_equal(np.asarray(d.get_macro_times())[photons],
                          t.column("nsync").to_numpy())


# --- every record type, synthesised -----------------------------------------------------------

def some_records(code, n, seed=0):
    rng = np.random.default_rng(seed)
    words = rng.integers(0, 1 << 32, n, dtype=np.uint64).astype(np.uint32)
    if FORMATS[code].layout == "picoharp":
        special = rng.random(n) < 0.2
        words[special] |= np.uint32(0xF << 28)
        words[special & (rng.random(n) < 0.5)] &= np.uint32(
            0xF000FFFF if FORMATS[code].is_t3 else 0xFFFFFFF0)
    else:
        ovf = rng.random(n) < 0.1
        words[ovf] |= np.uint32(0xFE000000)
    return words


@pytest.mark.parametrize("code", ALL_CODES, ids=hex)
def test_every_record_type_through_a_file(tmp_path, code, engine):
    fmt = record_format(code)
    words = some_records(code, 5000, seed=code)
    path = write_ptu(tmp_path / "x.ptu", code, [words[:1234], words[1234:]],
                     resolution_s=4e-12 if fmt.n_channels == 4 else 25e-12,
                     tags={"HW_Type": "synthetic", "HWInpChan_Enabled(0)": True,
                           "HWInpChan_Enabled(1)": True})
    assert is_ptu(path)
    h = read_header(path)
    assert (h.record_type, h.format, h.n_records, h.data_offset + 4 * 5000) == (
        code, fmt, 5000, h.file_bytes)
    assert h.tags["HW_Type"] == "synthetic" and h.tags["HWInpChan_Enabled(1)"] is True
    got = np.concatenate([w.copy() for _, w in iter_chunks(path, chunk_records=777)])
    assert np.array_equal(got, words)

    want = decode_records(words, fmt)
    report = DecodeReport()
    batches = list(iter_decoded_batches(path, chunk_records=999, report=report,
                                        engine=engine))
    table = pa.Table.from_batches(batches)
    assert report.n_records_read == 5000 == (
        report.n_photons + report.n_sync + report.n_markers + report.n_overflow_records
        + report.n_invalid)
    assert np.array_equal(table.column("kind").to_numpy(), want.kind)
    assert np.array_equal(table.column("channel").to_numpy(), want.channel)
    if fmt.is_t3:
        assert np.array_equal(table.column("nsync").to_numpy(), want.time)
        assert np.array_equal(table.column("dtime").to_numpy(), want.dtime)
        counts, _, tally, truncated = histogram_t3(path, chunk_records=1000, engine=engine)
        ref = np.zeros((fmt.n_channels, fmt.n_dtime_codes), np.uint64)
        histogram_records(words, fmt, ref)
        rows = max(2, int(np.flatnonzero(ref.any(axis=1))[-1]) + 1)
        assert counts.shape[0] == (4 if fmt.n_channels == 4 else rows)
        assert np.array_equal(counts, ref[:counts.shape[0]]) and not truncated
        assert tally.n_records == 5000 and tally.n_out_of_range == 0
        small, _, t2, _ = histogram_t3(path, n_channels=1, n_bins=100, engine=engine)
        assert int(small.sum()) == t2.n_photons - t2.n_out_of_range
        assert np.array_equal(small, ref[:1, :100])
    else:
        ps = {4e-12: 4, 25e-12: 25}[h.global_resolution_s]
        assert np.array_equal(table.column("time_ps").to_numpy(), want.time * ps)


def test_hydraharp_t2_picoseconds(tmp_path):
    """HydraHarp T2 at 1 ps: time_ps is the timetag; a 2.5 ps unit rounds half up."""
    words = np.array([(3 << 25) | 5, (1 << 31) | (0x3F << 25) | 2, (1 << 31) | 7], np.uint32)
    p = write_ptu(tmp_path / "a.ptu", 0x01010204, words, resolution_s=9.999999960041972e-13)
    t = decode(p)
    assert t.column("time_ps").to_pylist() == [5, 2 * 33554432 + 7]
    assert t.column("channel").to_pylist() == [3, SYNC_CHANNEL]
    p = write_ptu(tmp_path / "b.ptu", 0x01010204, words, resolution_s=2.5e-12)
    assert decode(p).column("time_ps").to_pylist() == [13, (2 * 33554432 + 7) * 5 // 2 + 1]


@settings(max_examples=15, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(chunk=st.integers(1, 3000), code=st.sampled_from(ALL_CODES))
def test_chunk_size_does_not_change_the_result(tmp_path, chunk, code):
    path = write_ptu(tmp_path / f"{code:x}.ptu", code, some_records(code, 3000, seed=3))
    whole = decode(path)
    assert decode(path, chunk_records=chunk).equals(whole, check_metadata=True)


def test_histogram_memory_is_bounded(tmp_path):
    """48 MB of records histogrammed with 1 MiB chunks: the peak is the chunk buffer and
    the 64 x 32768 counts, not the file."""
    block = some_records(0x01010304, 1 << 20, seed=9)
    path = write_ptu(tmp_path / "big.ptu", 0x01010304, (block for _ in range(12)))
    assert read_header(path).n_records == 12 << 20
    histogram_t3(path, chunk_records=1 << 18)  # compile outside the measurement
    tracemalloc.start()
    try:
        counts, _, tally, _ = histogram_t3(path, chunk_records=1 << 18)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert tally.n_records == 12 << 20
    assert peak < 24 << 20, f"peak {peak / 2**20:.1f} MiB"


# --- broken files --------------------------------------------------------------------------

@pytest.fixture
def good(tmp_path):
    words = some_records(0x00010303, 100, seed=1)
    return write_ptu(tmp_path / "good.ptu", 0x00010303, words), words


def one_line_error(fn, *args, match, **kw):
    with pytest.raises(PtuError, match=match) as info:
        fn(*args, **kw)
    msg = str(info.value)
    assert "\n" not in msg and isinstance(info.value, TcspcError | ValueError)
    return msg


def test_truncated_mid_record(good, tmp_path):
    path, words = good
    h = read_header(path)
    cut = tmp_path / "cut.ptu"
    cut.write_bytes(path.read_bytes()[:h.data_offset + 4 * 60 + 3])
    hc = read_header(cut)
    assert hc.truncated and hc.records_in_file == 60 and hc.n_readable == 60
    assert hc.warning == hc.truncation and "60 and 3 bytes" in hc.warning
    t = decode(cut)  # lenient: whole records decoded, flagged
    assert t.equals(decode_table(words[:60], 0x00010303))
    assert t.schema.metadata[b"ptu.truncated"] == b"true"
    assert t.schema.metadata[b"ptu.records_read"] == b"60"
    counts, _, tally, truncated = histogram_t3(cut)
    assert truncated and tally.n_records == 60
    msg = one_line_error(decode, cut, strict=True, match="truncated: the header declares "
                         "100 records, the file holds 60 and 3 bytes of a partial record")
    assert str(cut) in msg
    one_line_error(histogram_t3, cut, strict=True, match="truncated")


def test_bytes_after_the_declared_records_are_reported(good, tmp_path):
    path, words = good
    extra = tmp_path / "extra.ptu"
    extra.write_bytes(path.read_bytes() + b"\1\2\3\4\5\6")
    h = read_header(extra)
    assert not h.truncated and h.trailing_bytes == 6 and h.n_readable == 100
    assert h.warning == f"{extra}: 6 bytes after the 100 declared records, not read"
    assert decode(extra).equals(decode(path))
    assert read_header(path).warning == ""


def decode_table(words, code):
    d = decode_records(words, record_format(code))
    return pa.table([d.kind, d.channel, d.time, d.dtime], schema=PTU_T3_EVENTS.schema)


def test_truncated_anywhere_in_the_header(good, tmp_path):
    path, _ = good
    blob = path.read_bytes()
    h = read_header(path)
    cut = tmp_path / "cut.ptu"
    for n in range(h.data_offset):
        cut.write_bytes(blob[:n])
        one_line_error(read_header, cut, match=r"not a PTU file|cut short|no Header_End|"
                                               r"past the end of the file")
    cut.write_bytes(blob[:h.data_offset])  # header whole, no records at all
    assert read_header(cut).truncated and decode(cut).num_rows == 0
    one_line_error(decode, cut, strict=True, match="the file holds 0")


def test_wrong_magic(good, tmp_path):
    path, _ = good
    bad = tmp_path / "bad.ptu"
    bad.write_bytes(b"PQHISTO\0" + path.read_bytes()[8:])
    msg = one_line_error(read_header, bad, match=r"not a PTU file: starts with "
                                                 r"b'PQHISTO\\x00', expected b'PQTTTR")
    assert str(bad) in msg and not is_ptu(bad) and is_ptu(path)
    assert not is_ptu(tmp_path / "missing.ptu")
    one_line_error(read_header, tmp_path / "missing.ptu", match="cannot open")


def test_unknown_record_type(tmp_path):
    p = write_ptu(tmp_path / "u.ptu", 0x00010307, np.zeros(4, np.uint32),
                  tags={"TTResultFormat_TTTRRecType": 0x00010308})
    one_line_error(read_header, p, match="unknown PicoQuant record type 0x00010308")
    p = write_ptu(tmp_path / "v.ptu", 0x00010307, np.zeros(4, np.uint32),
                  tags={"TTResultFormat_TTTRRecType": "T3"})
    one_line_error(read_header, p, match="TTResultFormat_TTTRRecType must be an integer")


def test_header_without_end_tag(good, tmp_path):
    path, _ = good
    blob = path.read_bytes()
    at = blob.index(b"Header_End")
    bad = tmp_path / "noend.ptu"
    bad.write_bytes(blob[:at])  # the tags, then the end of the file
    one_line_error(read_header, bad, match="header has no Header_End tag")
    bad.write_bytes(blob.replace(b"Header_End", b"Header_Xnd"))  # records read as tags
    one_line_error(read_header, bad, match="no Header_End tag|unknown type|past the end")


def test_zero_records(tmp_path):
    p = write_ptu(tmp_path / "z.ptu", 0x01010304, np.zeros(0, np.uint32))
    one_line_error(decode, p, match=r"holds no records \(TTResult_NumberOfRecords = 0\)")


def test_tag_overrunning_the_file(good, tmp_path):
    path, _ = good
    blob = bytearray(path.read_bytes())
    at = blob.index(b"File_Comment")
    blob[at + 40:at + 48] = struct.pack("<q", 1 << 40)  # the string's length
    bad = tmp_path / "over.ptu"
    bad.write_bytes(bytes(blob))
    one_line_error(read_header, bad, match=r"tag File_Comment at byte \d+ declares "
                                           r"1099511627776 bytes of data, past the end")


def test_missing_mandatory_tags_and_bad_values(tmp_path):
    words = np.zeros(3, np.uint32)
    p = write_ptu(tmp_path / "a.ptu", 0x00010203, words,
                  tags={"MeasDesc_GlobalResolution": 0.0})
    one_line_error(read_header, p, match="MeasDesc_GlobalResolution must be a positive")
    p = write_ptu(tmp_path / "b.ptu", 0x00010203, words,
                  tags={"MeasDesc_GlobalResolution": 1.2345e-13})
    one_line_error(read_header, p, match="not a fraction of a picosecond")
    p = write_ptu(tmp_path / "c.ptu", 0x00010303, words, tags={"TTResult_NumberOfRecords": -5})
    one_line_error(read_header, p, match="holds no records")
    p = write_ptu(tmp_path / "d.ptu", 0x00010303, words,
                  tags={"TTResultFormat_BitsPerRecord": 64})
    one_line_error(read_header, p, match="records of 64 bits")


def test_a_t2_time_unit_of_seconds_is_a_corrupt_header(tmp_path):
    """Found by the byte-flip test below: a T2 global resolution of 1e300 s made the
    times' conversion to ps overflow (an OverflowError, not a PtuError)."""
    words = some_records(0x01010204, 64, seed=2)
    p = write_ptu(tmp_path / "r.ptu", 0x01010204, words, global_resolution_s=1e300)
    one_line_error(read_header, p, match="is no T2 time unit")


def test_a_tag_name_with_a_newline_is_named_on_one_line(tmp_path):
    """Found by the byte-flip test below (a full run, 2026-11-25): a corrupt tag's name held a
    newline byte, and the error that names the tag split in two lines."""
    p = write_ptu(tmp_path / "r.ptu", 0x01010204, some_records(0x01010204, 8, seed=2))
    blob = bytearray(p.read_bytes())
    at = blob.index(b"TTResultFormat_TTTRRecType")
    blob[at + 2] = ord("\n")
    blob[at + 36:at + 40] = (0x553EA040).to_bytes(4, "little")  # an unknown type
    p.write_bytes(bytes(blob))
    msg = one_line_error(read_header, p, match="unknown type")
    assert "TT\\x0aesultFormat" in msg


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(flips=st.lists(st.tuples(st.integers(0, 10 ** 6), st.integers(0, 255)),
                      min_size=1, max_size=6))
def test_corrupt_header_fails_cleanly(tmp_path, flips):
    """Bytes changed anywhere in a header: a header, or a PtuError; never another error."""
    words = some_records(0x01010204, 64, seed=2)
    src = tmp_path / "src.ptu"
    if not src.exists():
        write_ptu(src, 0x01010204, words, tags={"File_Comment": "x" * 30,
                                                "Blob": b"\1\2\3", "Arr": np.ones(2)})
    blob = bytearray(src.read_bytes())
    n_header = len(blob) - 4 * 64
    for pos, byte in flips:
        blob[pos % n_header] = byte
    bad = tmp_path / "bad.ptu"
    bad.write_bytes(bytes(blob))
    try:
        decode(bad)
    except PtuError as exc:
        assert "\n" not in str(exc)


# --- Photon-HDF5 (phconvert: the hdf5 extra, and in dev so these run in CI) --------------

def test_photon_hdf5_without_phconvert_says_how_to_get_it(good, tmp_path, monkeypatch):
    from pipeline.io.ptu import export_photon_hdf5

    monkeypatch.setitem(__import__("sys").modules, "phconvert", None)
    with pytest.raises(ModuleNotFoundError, match=r"needs phconvert \(pip install phconvert"):
        export_photon_hdf5(good[0], tmp_path / "x.h5")
    assert not (tmp_path / "x.h5").exists()


@pytest.mark.parametrize("code", [0x01010304, 0x00010203], ids=hex)
def test_photon_hdf5_holds_the_photons(tmp_path, code):
    phconvert = pytest.importorskip("phconvert")
    tables = pytest.importorskip("tables")
    from pipeline.io.ptu import export_photon_hdf5

    words = some_records(code, 4000, seed=4)
    src = write_ptu(tmp_path / "s.ptu", code, words)
    out = tmp_path / "s.h5"
    got = export_photon_hdf5(src, out)
    d = decode_records(words, record_format(code))
    photon = (d.kind == 0) & (d.channel != SYNC_CHANNEL)
    assert got["n_records_read"] == 4000 and got["n_photons"] == photon.sum()
    with tables.open_file(str(out)) as h5:  # (given a path, phconvert leaves it open)
        phconvert.hdf5.assert_valid_photon_hdf5(h5, warnings=False)
        pd = h5.root.photon_data
        assert np.array_equal(pd.timestamps.read(), d.time[photon].astype(np.int64))
        assert np.array_equal(pd.detectors.read(), d.channel[photon])
        if d.dtime is not None:
            assert np.array_equal(pd.nanotimes.read(), d.dtime[photon])
        assert h5.root.identity.filename.read().decode() == "s.h5"
