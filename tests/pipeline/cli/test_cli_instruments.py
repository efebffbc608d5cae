"""The offline commands on real instruments' files: the format read from the content, the
same commands as for the thesis chip, one-line errors and non-zero exits on bad files."""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pyarrow.parquet as pq
import pytest

from pipeline.io.formats import FormatError, detect_format

DATA = Path(__file__).parents[2] / "data"
T3 = DATA / "picoquant" / "hydraharp_v20_t3.ptu"
T2 = DATA / "picoquant" / "picoharp_v30_t2.ptu"
LINO = DATA / "linospad2" / "test_data_2212b.dat"
ROOT = Path(__file__).parents[3]


_CLI = []


@pytest.fixture(autouse=True, scope="module")
def _cli(cli_process):
    _CLI[:] = [cli_process]


def tcspc(*args, cwd=None):
    """`python -m pipeline.cli ARGS`, a process forked from one that imported the
    commands' modules (tests/conftest.py ``CliProcess``)."""
    return _CLI[0].run(*args, cwd=cwd)


def test_formats_are_read_from_the_content(tmp_path):
    assert detect_format(T3) == "ptu" and detect_format(T2) == "ptu"
    assert detect_format(LINO) == "linospad2"
    renamed = tmp_path / "run.dat"
    renamed.write_bytes(T3.read_bytes())
    assert detect_format(renamed) == "ptu"  # the extension is not trusted
    junk = tmp_path / "junk.bin"
    junk.write_bytes(np.random.default_rng(1).bytes(52_000))
    with pytest.raises(FormatError, match="give --format"):
        detect_format(junk)


def test_t3_histogram_decode_and_their_accounting(tmp_path):
    h, e = tmp_path / "h.parquet", tmp_path / "e.parquet"
    # a long path: a captured message stays one line (CI's checkout path once split it)
    deep = tmp_path / ("a-long-directory-name-" * 4) / T3.name
    deep.parent.mkdir()
    deep.write_bytes(T3.read_bytes())
    r = tcspc("histogram", deep, "--out", h)
    assert r.returncode == 0, r.stderr
    line = next(x for x in r.stderr.splitlines() if x.startswith(str(deep)))
    assert "106,349 records" in line and "28,466 overflow" in line
    hist = pl.read_parquet(h)
    assert hist.height == 2 and hist["instrument"].unique().to_list() == ["picoquant-t3"]
    assert hist["bin_width_ps"].to_list() == [64.0, 64.0]
    assert pq.read_schema(h).metadata[b"tcspc.version"] == b"2.0"
    r = tcspc("decode", T3, "--out", e)
    assert r.returncode == 0, r.stderr
    ev = pl.read_parquet(e)
    assert ev.columns == ["kind", "channel", "nsync", "dtime"]
    # the decoded photons histogram to the same counts, channel by channel
    for ch in (0, 1):
        d = ev.filter((pl.col("kind") == 0) & (pl.col("channel") == ch))["dtime"].to_numpy()
        counts = np.stack(hist.sort("tdc")["counts"].to_numpy())[ch]
        assert np.array_equal(np.bincount(d, minlength=counts.size), counts)


def test_t2_decode_and_refusal_to_histogram(tmp_path):
    r = tcspc("decode", T2, "--out", tmp_path / "t2.parquet")
    assert r.returncode == 0, r.stderr
    ev = pl.read_parquet(tmp_path / "t2.parquet")
    assert ev.columns == ["kind", "channel", "time_ps"]
    assert (ev["time_ps"].diff().drop_nulls() >= 0).all()  # overflow-corrected: monotone
    r = tcspc("histogram", T2, "--out", tmp_path / "h.parquet")
    assert r.returncode == 2 and "T2 records" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "h.parquet").exists()


def test_linospad2_by_tdc_and_pixel(tmp_path):
    for by, rows in (("tdc", 64), ("pixel", 256)):
        r = tcspc("histogram", LINO, "--by", by, "--out", tmp_path / f"{by}.parquet")
        assert r.returncode == 0, r.stderr
        h = pl.read_parquet(tmp_path / f"{by}.parquet")
        assert h.height == rows and h["counts"].list.len().unique().to_list() == [140]
        assert h["cycles"].unique().to_list() == [20]
    a = np.stack(pl.read_parquet(tmp_path / "tdc.parquet")["counts"].to_numpy())
    b = np.stack(pl.read_parquet(tmp_path / "pixel.parquet")["counts"].to_numpy())
    assert np.array_equal(a, b.reshape(64, 4, 140).sum(axis=1))  # 2212b: pixel = 4 TDC + k


@pytest.mark.parametrize("damage", ["magic", "empty"])
def test_bad_files_give_one_line_and_a_nonzero_exit(tmp_path, damage):
    raw = T3.read_bytes()
    bad = tmp_path / "bad.ptu"
    bad.write_bytes(b"NOTAPTU!" + raw[8:] if damage == "magic" else b"")
    r = tcspc("histogram", bad, "--out", tmp_path / "h.parquet")
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) <= 3
    r = tcspc("histogram", bad, "--format", "ptu", "--out", tmp_path / "h.parquet")
    assert r.returncode == 2 and "Traceback" not in r.stderr


@pytest.mark.parametrize("keep", [0, 50_000])
def test_a_truncated_file_keeps_what_decodes_flags_it_and_exits_3(tmp_path, keep):
    """The real file cut short (its header declares 106,349 records): none left after
    the header (histograms all zero: once written with exit 0), or 50,000 and half a
    record. The output holds the whole records, flagged; the exit is 3 (the documented
    code) unless --allow-truncated."""
    from pipeline.io.ptu import read_header

    raw = T3.read_bytes()
    start = read_header(T3).data_offset
    cut = tmp_path / "cut.ptu"
    cut.write_bytes(raw[:start + 4 * keep + (2 if keep else 0)])
    # the records kept, histogrammed here from the bytes (hydraharp layout: a photon is a
    # record with the special bit clear; channel 6 bits, dtime 15 bits)
    w = np.frombuffer(raw[start:start + 4 * keep], "<u4").astype(np.int64)
    photon = (w >> 31) == 0
    want = [np.bincount(((w >> 10) & 0x7FFF)[photon & (((w >> 25) & 0x3F) == ch)],
                        minlength=1) for ch in (0, 1)]
    for cmd in ("histogram", "decode"):
        out = tmp_path / f"{cmd}.parquet"
        r = tcspc(cmd, cut, "--out", out, "-q")
        assert r.returncode == 3, r.stderr
        assert "truncated" in r.stderr and "--allow-truncated" in r.stderr
        assert "Traceback" not in r.stderr
        meta = pq.read_schema(out).metadata
        assert meta[b"tcspc.truncated"] == b"True"
        if cmd == "histogram":
            counts = np.stack(pl.read_parquet(out).sort("tdc")["counts"].to_numpy())
            for ch in (0, 1):
                got = counts[ch]
                n = max(got.size, want[ch].size)
                assert np.array_equal(np.pad(got, (0, n - got.size)),
                                      np.pad(want[ch], (0, n - want[ch].size)))
        else:
            assert pl.read_parquet(out).filter(pl.col("kind") == 0).height == photon.sum()
        r = tcspc(cmd, cut, "--out", out, "-q", "--allow-truncated", "--overwrite")
        assert r.returncode == 0, r.stderr
        assert "truncated" in r.stderr  # said all the same


def test_a_truncated_linospad2_file_exits_3(tmp_path):
    cut = tmp_path / "cut.dat"
    cut.write_bytes(LINO.read_bytes()[:-100])
    # (cut short, the content no longer says LinoSPAD2: the format is given)
    r = tcspc("histogram", cut, "--format", "linospad2", "--out", tmp_path / "h.parquet", "-q")
    assert r.returncode == 3 and "truncated" in r.stderr, r.stderr
    assert pq.read_schema(tmp_path / "h.parquet").metadata[b"tcspc.truncated"] == b"True"
    r = tcspc("histogram", cut, "--format", "linospad2", "--out", tmp_path / "h.parquet", "-q",
              "--allow-truncated", "--overwrite")
    assert r.returncode == 0, r.stderr


def test_chip_options_are_refused_on_an_instrument_file(tmp_path):
    r = tcspc("histogram", T3, "--calibration", tmp_path, "--out", tmp_path / "h.parquet")
    assert r.returncode == 2 and "not for a ptu file" in r.stderr


def test_decode_to_photon_hdf5(tmp_path):
    """A valid Photon-HDF5 file, its detectors the histogram's hits, and no file left
    open at the command's exit (PyTables' UnclosedFileWarning); docs/instruments_ptu.md
    says how to make one."""
    phconvert = pytest.importorskip("phconvert")  # dev and hdf5 extras install it
    out = tmp_path / "hh.h5"
    r = tcspc("decode", T3, "--out", out)
    assert r.returncode == 0, r.stderr
    assert "UnclosedFileWarning" not in r.stderr and out.stat().st_size, r.stderr
    doc = (ROOT / "docs" / "instruments_ptu.md").read_text()
    assert "tcspc decode FILE.ptu --out FILE.h5" in doc and "not** a dependency" not in doc
    import tables

    with tables.open_file(str(out)) as h5:  # (given a path, phconvert leaves it open)
        phconvert.hdf5.assert_valid_photon_hdf5(h5, warnings=False)
        det = h5.root.photon_data.detectors.read()
        assert np.bincount(det).tolist() == [45012, 32871]  # the histogram's n_hit per channel
    r = tcspc("decode", LINO, "--out", tmp_path / "l.h5")
    assert r.returncode != 0 and "takes a PTU file" in r.stderr


BLAS = """
import os, sys
from threadpoolctl import threadpool_info
from pipeline.cli.app import cli
cli.main(sys.argv[1:], standalone_mode=False)
print(os.environ.get("OPENBLAS_NUM_THREADS"),
      [p["num_threads"] for p in threadpool_info() if p["internal_api"] == "openblas"])
"""


@pytest.mark.parametrize("command", ["histogram", "decode"])
def test_instrument_commands_load_numpy_without_a_blas_thread_pool(tmp_path, command):
    """numpy's OpenBLAS starts a thread per core when it loads (50-130 ms of CPU of a
    command on 2 cores): `histogram` and `decode`, which do no linear algebra, ask for one
    before numpy loads; a user's OPENBLAS_NUM_THREADS is kept."""
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    args = [sys.executable, "-c", BLAS, command, str(T3), "--out", str(tmp_path / "o.parquet"),
            "-q"]
    for given, want in ((None, "1 [1]"), ("2", "2 [")):
        run_env = {**env, "PYTHONPATH": str(ROOT)}
        if given:
            run_env["OPENBLAS_NUM_THREADS"] = given
        r = subprocess.run(args, capture_output=True, text=True, env=run_env, timeout=120)
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip().startswith(want), r.stdout


def test_every_stage_process_asks_for_one_blas_thread():
    """A stage is one core's work whoever starts it (the daemon, a systemd unit, a shell):
    `tcspc stage ...` asks for one OpenBLAS thread before numpy loads (a user's own
    setting kept), so no pool spins on the cores the graph's other stages need."""
    script = BLAS.replace("print(", "import numpy\nprint(")
    env = {k: v for k, v in os.environ.items() if k != "OPENBLAS_NUM_THREADS"}
    for given, want in ((None, "1 [1]"), ("2", "2 [")):
        run_env = {**env, "PYTHONPATH": str(ROOT), **({"OPENBLAS_NUM_THREADS": given}
                                                       if given else {})}
        r = subprocess.run([sys.executable, "-c", script, "stage", "sink", "--help"],
                           capture_output=True, text=True, env=run_env, timeout=120)
        assert r.returncode == 0, r.stderr
        assert r.stdout.strip().splitlines()[-1].startswith(want), r.stdout[-300:]
