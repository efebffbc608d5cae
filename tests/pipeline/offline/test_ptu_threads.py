"""A PTU T3 file histogrammed on several threads (`fold_ptu`) gives, byte for byte,
what one pass in file order gives: the counts, the overflow count, the sync total and every
record class, wherever the chunks' edges fall (a photon, a marker, an overflow record or an
invalid one at a chunk's first or last record), on every engine and fallback."""

import tempfile
from itertools import product
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import stages.instruments.ptu as ptu
from pipeline.io.ptu import PtuError, read_header, read_records, write_ptu
from pipeline.offline.instruments import fold_ptu, histogram_ptu
from stages.instruments.accumulate import PtuT3Accumulator

T3_CODES = sorted(c for c, f in ptu.FORMATS.items() if f.is_t3)


def record(code: int, kind: str, a: int, b: int, nsync: int) -> int:
    """One record of ``kind``, its fields from ``a``, ``b`` and ``nsync``, written from
    PicoQuant's bit layouts (not from the decoders under test)."""
    if ptu.FORMATS[code].layout == ptu.PICOHARP:  # channel 4 | dtime 12 | nsync 16
        return {"photon": ((1 + a % 4) << 28) | ((b % 4096) << 16) | nsync,
                "overflow": 15 << 28 | (a % 65536),
                "marker": 15 << 28 | ((1 + b % 15) << 16) | nsync,
                "invalid": (a % 2) * (5 + b % 10) << 28 | (b % 65536)}[kind]
    # special 1 | channel 6 | dtime 15 | nsync 10
    return {"photon": ((a % 6) << 25) | ((b % 32768) << 10) | nsync,
            "overflow": 1 << 31 | 63 << 25 | (b % 4 if b % 3 else b % 1024),
            "marker": 1 << 31 | (1 + b % 15) << 25 | nsync,
            "invalid": 1 << 31 | (16 + b % 47) << 25 | (a % 1024)}[kind]


def file_of(code: int, recs, directory) -> Path:
    """A PTU file of ``recs`` (kind, a, b): the events' sync numbers never go back, as an
    instrument writes them (they climb by ``a % 3`` and start again after an overflow)."""
    wrap, nsync, words = ptu.FORMATS[code].wrap, 0, []
    for kind, a, b in recs:
        nsync = 0 if kind == "overflow" else min(wrap - 1, nsync + a % 3)
        words.append(record(code, kind, a, b, nsync))
    return write_ptu(Path(directory) / "f.ptu", code, [np.array(words, np.uint32)])


records = st.lists(st.tuples(st.sampled_from(["photon", "photon", "overflow", "marker",
                                               "invalid"]),
                             st.integers(0, 1 << 20), st.integers(0, 1 << 20)),
                   min_size=1, max_size=300)


def state(acc: PtuT3Accumulator) -> dict:
    return {k: v.tobytes() for k, v in acc.checkpoint().items()}


def reference(path: Path) -> dict:
    """What the accumulator must hold, from the decoded events (the numpy engine's
    decoder, held to PicoQuant's description in tests/stages/test_ptu.py), not from the
    accumulator: counts per (channel, dtime); the overflow count; the sync periods, past
    the last event or the last wrap; the records; the classes."""
    h = read_header(path)
    fmt, n_ch = h.format, h.n_input_channels
    words = np.fromfile(path, "<u4", offset=h.data_offset).astype(np.uint32)
    d = ptu.decode_records(words, fmt, engine="numpy")
    photon = d.kind == ptu.PHOTON
    ch, dt = d.channel[photon].astype(np.int64), d.dtime[photon].astype(np.int64)
    ok = (ch < n_ch) & (dt < fmt.n_dtime_codes)
    counts = np.zeros((n_ch, fmt.n_dtime_codes), np.uint64)
    np.add.at(counts, (ch[ok], dt[ok]), np.uint64(1))
    syncs = max(int(d.time[-1]) + 1 if len(d) else 0, d.wraps * fmt.wrap)
    classes = [int(ok.sum()), d.n_markers, d.n_overflow_records, d.n_invalid,
               int((~ok).sum())]  # photons, markers, overflow, invalid, out of range
    return {"inst_counts": counts.tobytes(),
            "inst_position": np.array([d.wraps, syncs, words.size], np.int64).tobytes(),
            "inst_classes": np.array(classes, np.int64).tobytes()}


def one_pass(path: Path, engine: str | None) -> dict:
    """Every record in one update, in file order."""
    h = read_header(path)
    acc = PtuT3Accumulator(h.format, h.resolution_s, h.n_input_channels, engine)
    acc.update(np.fromfile(path, "<u4", offset=h.data_offset).astype(np.uint32))
    return state(acc)


def threaded(path: Path, engine: str | None, chunk: int, threads: int) -> dict:
    h = read_header(path)
    acc = PtuT3Accumulator(h.format, h.resolution_s, h.n_input_channels, engine)
    fold_ptu(path, acc, chunk, threads)
    return state(acc)


@settings(max_examples=30, deadline=None)
@given(code=st.sampled_from(T3_CODES), recs=records, chunk=st.integers(1, 40),
       threads=st.integers(2, 3))
def test_threads_give_the_one_pass_result_byte_for_byte(code, recs, chunk, threads):
    with tempfile.TemporaryDirectory() as tmp:
        path = file_of(code, recs, tmp)
        want = reference(path)
        assert one_pass(path, "numba") == want
        assert threaded(path, "numba", chunk, threads) == want
        assert threaded(path, "numpy", chunk, threads) == want
        assert threaded(path, "numba", chunk, 1) == want  # the same chunks, in one pass


def test_every_kind_of_record_at_every_edge():
    """Each kind of record as a chunk's last and the next one's first, for every pair."""
    kinds = ["photon", "overflow", "marker", "invalid"]
    for code in T3_CODES:
        recs = [(k, i, 3 * i + 1) for i, pair in enumerate(product(kinds, kinds))
                for k in pair]  # every ordered pair of kinds, adjacent
        with tempfile.TemporaryDirectory() as tmp:
            path = file_of(code, recs, tmp)
            want = reference(path)
            for chunk in (1, 2, 3):
                assert threaded(path, None, chunk, 2) == want, (hex(code), chunk)


@pytest.fixture(scope="module")
def many_chunks(tmp_path_factory):
    """A HydraHarp V2 T3 file of 40 chunks of 5,000 records: photons on 4 inputs, an
    overflow record (of 1 to 3 wraps) every 97th and a marker every 1,001st record."""
    rng = np.random.default_rng(25)
    n = 200_000
    w = ((rng.integers(0, 4, n, dtype=np.uint32) << 25)
         | (rng.integers(0, 3000, n, dtype=np.uint32) << 10)
         | rng.integers(0, 1024, n, dtype=np.uint32))
    w[::97] = (1 << 31) | (63 << 25) | rng.integers(0, 4, w[::97].size, dtype=np.uint32)
    w[::1001] = (1 << 31) | (2 << 25) | 5
    path = tmp_path_factory.mktemp("ptu") / "many.ptu"
    return write_ptu(path, 0x01010304, [w])


def test_the_command_path_is_the_same_on_any_number_of_threads(many_chunks):
    tables = {}
    for threads in (1, 2, 4):
        table, summary = histogram_ptu(many_chunks, chunk_records=5_000, threads=threads)
        tables[threads] = (table, summary.records, summary.events, summary.counted,
                           summary.notes)
    assert tables[1][1] == 200_000 and tables[1][2] > 190_000  # records, photons
    for threads in (2, 4):
        assert tables[threads][0].equals(tables[1][0])
        assert tables[threads][1:] == tables[1][1:]


def test_the_fallbacks_thread_alike(many_chunks, monkeypatch):
    """numba's dispatcher (where the C kernel cannot be had) and the plain Python loop
    behind it, on threads: the one-pass result."""
    want = reference(many_chunks)
    monkeypatch.setattr(ptu, "_native", lambda name: None)
    assert threaded(many_chunks, "numba", 5_000, 2) == want
    monkeypatch.setattr(ptu, "_jitted", lambda name: ptu._LOOPS[name])
    assert threaded(many_chunks, "numba", 50_000, 2) == want


def test_a_file_that_shrinks_while_read_is_one_clear_error(many_chunks, tmp_path,
                                                           monkeypatch):
    path = tmp_path / "shrinks.ptu"
    path.write_bytes(many_chunks.read_bytes())
    header = read_header(path)
    with open(path, "r+b") as fh:
        fh.truncate(header.data_offset + 4 * 150_000 + 2)
    with open(path, "rb") as fh, pytest.raises(PtuError, match=r"shrank while reading "
                                               r"\(record 100000: got 200002 of 400000"):
        read_records(fh, header, 100_000, np.empty(100_000, "<u4"))
    monkeypatch.setattr("pipeline.io.ptu.read_header", lambda p: header)  # read before
    acc = PtuT3Accumulator(header.format, header.resolution_s, header.n_input_channels)
    with pytest.raises(PtuError, match=r"shrinks\.ptu: file shrank while reading"):
        fold_ptu(path, acc, 5_000, 2)


def test_the_c_kernels_release_the_gil():
    """What the threads rest on: the kernels are called through ctypes as C functions
    (CDLL / CFUNCTYPE), which release the GIL for the call; PyDLL's would hold it."""
    import ctypes

    for name in ("histogram_hydraharp_t3", "histogram_picoharp_t3", "decode_hydraharp_t3"):
        fn = ptu._native(name)
        assert fn is not None
        assert not fn._flags_ & ctypes._FUNCFLAG_PYTHONAPI, name
    assert ctypes.PyDLL(None).PyGILState_Check._flags_ & ctypes._FUNCFLAG_PYTHONAPI
