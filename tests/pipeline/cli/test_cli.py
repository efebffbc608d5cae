"""The CLI on captures written by an independent encoder (struct, bit by bit, Table 5.1)."""

import json
import subprocess
import sys

import numpy as np
import polars as pl
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from pipeline.cli.app import cli
from schemas import HISTOGRAMS, validate

JOHNSON = np.array([0b0000, 0b0001, 0b0011, 0b0111, 0b1111, 0b1110, 0b1100, 0b1000])
N_MIN, N_MAX = 20, 140


def independent_bytes(c1st, p1st_bits, c2nd, p2nd_bits, addr, marker_bits=0b0010):
    """Words as the FPGA's four bytes, composed from Table 5.1 (not from stages.codec).

    Byte 1: 0, C2nd4..0, P2nd3..2. Byte 2: P2nd1..0, C1st5..0. Byte 3: P1st3..0, then the
    markers 0 0 1, then A7. Byte 4: A6..0, then the marker 0. ``marker_bits`` holds the
    four marker bits in that order (0b0010 is correct).
    """
    b1 = (c2nd << 2) | (p2nd_bits >> 2)
    b2 = ((p2nd_bits & 0b11) << 6) | c1st
    b3 = (p1st_bits << 4) | ((marker_bits >> 1) << 1) | (addr >> 7)
    b4 = ((addr & 0x7F) << 1) | (marker_bits & 1)
    return np.stack([b1, b2, b3, b4], axis=-1).astype(np.uint8).tobytes()


def write_independent_capture(path, n_tdc, cycles, seed, hit=0.3):
    """A capture with an intended class per word; returns the intended hits and counts."""
    rng = np.random.default_rng(seed)
    n = n_tdc * cycles
    addr = np.arange(n) % n_tdc
    u = rng.random(n)
    edges = np.cumsum([hit, 0.002, 0.018, 0.02])
    kind = np.select([u < e for e in edges],
                     ["hit", "artifact", "invalid_phase", "malformed"], "no_hit")
    code = rng.integers(0, 512, n)
    d2 = np.where(kind == "artifact", rng.integers(N_MAX + 1, 256, n),
                  rng.integers(N_MIN, N_MAX + 1, n))
    zero = kind == "no_hit"
    c1, p1 = np.where(zero, 0, code // 8), np.where(zero, 0, JOHNSON[code % 8])
    c2, p2 = np.where(zero, 0, d2 // 8), np.where(zero, 0, JOHNSON[d2 % 8])
    p1 = np.where(kind == "invalid_phase", 0b0101, p1)  # a bubble
    marker = np.where(kind == "malformed", 0b0110, 0b0010)
    path.with_suffix(".bin").write_bytes(independent_bytes(c1, p1, c2, p2, addr, marker))
    path.with_suffix(".json").write_text(json.dumps({
        "format": "tcspc-raw", "version": 1, "n_tdc": n_tdc, "window_ns": 80.0,
        "t_laser_win_ns": 140.0, "cycles": cycles}))
    hit = kind == "hit"
    hits = np.zeros((n_tdc, 512), np.int64)
    np.add.at(hits, (addr[hit], code[hit]), 1)
    classes = {k: int((kind == k).sum()) for k in
               ("hit", "no_hit", "artifact", "invalid_phase", "malformed")}
    return hits, classes


def write_bounds_calibration(caldir, n_tdc):
    """A calibration directory holding the encoder's Nmin/Nmax (other columns nominal)."""
    import pyarrow as pa

    from schemas import CALIBRATION_TDC

    caldir.mkdir()
    t = pa.table({
        "tdc": pa.array(np.arange(n_tdc), pa.uint16()),
        "lsb_ps": np.full(n_tdc, 200.0),
        "lsb_poly": pa.FixedSizeListArray.from_arrays(
            pa.array(np.tile([200.0, 0, 0, 0], n_tdc)), 4),
        "n_min": pa.array(np.full(n_tdc, N_MIN), pa.uint16()),
        "n_max": pa.array(np.full(n_tdc, N_MAX), pa.uint16()),
        "n_th": pa.array(np.full(n_tdc, N_MIN), pa.uint16()),
        "pdm": pa.array(np.full(n_tdc, N_MIN), pa.uint16()),
        "delay_ps": pa.array([None] * n_tdc, pa.float64()),
        "ok": pa.array(np.ones(n_tdc, bool)),
    }, schema=CALIBRATION_TDC.schema)
    pq.write_table(t, caldir / "tdc.parquet")
    return caldir


def test_independent_encoder_agrees_with_table_5_1_spot_check():
    from stages.codec import encode_words

    b = independent_bytes(np.array([0b110011]), np.array([0b1110]), np.array([0b10101]),
                          np.array([0b0111]), np.array([0b10010110]))
    assert b == int(encode_words(0b110011, 0b1110, 0b10101, 0b0111, 0b10010110,
                                 raw_phase=True)).to_bytes(4, "big")


@pytest.fixture(scope="module")
def independent(tmp_path_factory):
    base = tmp_path_factory.mktemp("ind")
    hits, classes = write_independent_capture(base / "ind", 128, 4000, seed=5)
    return base / "ind", hits, classes, write_bounds_calibration(base / "cal", 128)


@pytest.fixture(scope="module")
def independent_dense(tmp_path_factory):
    """A density-test-like capture: ~30 hits per D2nd code, so bounds are identifiable."""
    base = tmp_path_factory.mktemp("dense")
    hits, classes = write_independent_capture(base / "dense", 128, 4000, seed=6, hit=0.9)
    return base / "dense", hits, classes, None


@pytest.mark.parametrize("engine", ["numpy", "numba"])
@pytest.mark.parametrize("case", ["independent", "independent_dense"])
def test_histogram_equals_what_the_independent_encoder_intended(case, tmp_path, engine,
                                                                request):
    """Exact per-TDC hits and class counts: a sparse capture with the encoder's bounds
    given as a calibration, and a dense one with the bounds estimated from the capture."""
    path, hits, classes, caldir = request.getfixturevalue(case)
    out = tmp_path / "h.parquet"
    cal = ["--calibration", str(caldir)] if caldir else []
    res = CliRunner().invoke(cli, ["histogram", str(path) + ".bin", "--out", str(out),
                                   "--engine", engine, *cal])
    assert res.exit_code == 0, res.output
    table = pq.read_table(out)
    validate(table, HISTOGRAMS)
    df = pl.from_arrow(table).sort("tdc")
    got = np.stack(df["counts"].to_numpy())
    assert np.array_equal(got, hits)
    assert {k: int(df[f"n_{k}"].sum()) for k in classes} == classes
    assert df["cycles"].to_list() == [4000] * 128
    assert f"{sum(classes.values()):,}" in res.output  # the summary's total


def test_decode_writes_every_non_empty_word(independent, tmp_path):
    path, _, classes, caldir = independent
    out = tmp_path / "e.parquet"
    res = CliRunner().invoke(cli, ["decode", str(path), "--out", str(out),
                                   "--calibration", str(caldir)])
    assert res.exit_code == 0, res.output
    df = pl.read_parquet(out)
    counts = dict(df.group_by("word_class").len().iter_rows())
    assert counts == {k: v for k, v in classes.items() if k != "no_hit"}
    assert df.filter(pl.col("word_class") == "malformed")["d1st"].null_count() == \
        classes["malformed"]


@pytest.mark.parametrize("seed", [1, 2])
def test_randomly_corrupted_captures_are_fully_accounted(tmp_path, seed):
    from pipeline.io.capture import Capture, write_capture
    from pipeline.offline.datapath import histogram_capture
    from stages.testpattern import pattern_words

    words, _ = pattern_words(2000, 128, hit_prob=0.2, rng=seed)
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, words.size, 5000)
    words[idx] ^= np.uint32(1) << rng.integers(0, 32, idx.size).astype(np.uint32)
    garbage = rng.integers(0, 2**32, 3000, dtype=np.uint64).astype(np.uint32)
    words[:3000] = garbage
    write_capture(tmp_path / "c", words, 128)
    state, _ = histogram_capture(Capture(tmp_path / "c"))
    assert state.class_counts.sum() == words.size
    assert state.cycles.tolist() == [2000] * 128


def test_cli_errors_are_one_clear_line(tmp_path):
    (tmp_path / "c.bin").write_bytes(b"\0" * 10)
    (tmp_path / "c.json").write_text("{}")
    proc = subprocess.run([sys.executable, "-m", "pipeline.cli", "histogram",
                           str(tmp_path / "c.bin"), "--out", str(tmp_path / "h.parquet")],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert "error:" in proc.stderr and "Traceback" not in proc.stderr
    assert "format is None" in proc.stderr


def test_pattern_and_schema_commands(tmp_path):
    res = CliRunner().invoke(cli, ["pattern", str(tmp_path / "p"), "--cycles", "100"])
    assert res.exit_code == 0, res.output
    meta = json.loads((tmp_path / "p.json").read_text())
    assert sum(meta["truth"]["class_counts"].values()) == 100 * 128
    res = CliRunner().invoke(cli, ["schema", "--markdown"])
    assert "### `histograms` (version 2.0)" in res.output


def test_histogram_makes_a_second_pass_when_the_first_chunk_misleads(tmp_path, monkeypatch):
    """One pass normally; a capture whose first chunk shows another D2nd block than the
    whole (the light changed) gets a second pass, said on stderr, and exact histograms."""
    from pipeline.io.capture import Capture, CaptureWriter
    from pipeline.offline.datapath import histogram_capture
    from stages.artifact import estimate_bounds
    from stages.codec import encode_words
    from stages.histogram import HistogramAccumulator

    rng = np.random.default_rng(0)
    n = 2

    def hits(cycles, d2_lo, d2_hi):
        d2 = rng.integers(d2_lo, d2_hi + 1, (cycles, n))
        d1 = rng.integers(1, 512, (cycles, n))
        return encode_words(d1 >> 3, d1 & 7, d2 >> 3, d2 & 7, np.tile(np.arange(n), (cycles, 1)))

    with CaptureWriter(tmp_path / "c", n_tdc=n) as w:
        w.write(hits(1000, 150, 200).ravel())
        w.write(hits(200_000, 20, 100).ravel())
    orig = Capture.iter_chunks
    monkeypatch.setattr(Capture, "iter_chunks", lambda self, chunk_words=2000:
                        orig(self, chunk_words))
    said = []
    state, bounds = histogram_capture(Capture(tmp_path / "c.bin"), log=said.append)
    assert said and "second pass" in said[0]
    words = np.concatenate([w.copy() for _, w in orig(Capture(tmp_path / "c.bin"))])
    probe = HistogramAccumulator(n, mode="d2nd")
    probe.update(words)
    ref = HistogramAccumulator(n, estimate_bounds(probe.snapshot().hits))
    ref.update(words)
    assert np.array_equal(state.hits, ref.snapshot().hits)
    assert np.array_equal(state.class_counts, ref.snapshot().class_counts)
    assert bounds.n_max.tolist() == [100, 100]


def imported_after(code: str, modules: tuple[str, ...]) -> list[str]:
    """Which of ``modules`` a fresh interpreter has imported after running ``code``."""
    import ast
    import subprocess
    import sys

    check = f"; import sys; print(sorted(m for m in {modules!r} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code + check], capture_output=True,
                         text=True, check=True).stdout.strip()
    return ast.literal_eval(out.splitlines()[-1])  # a printed list of names


def test_the_command_line_starts_without_the_heavy_modules():
    """`tcspc --help` stays fast (0.6 s before, 0.08 s after): importing the CLI and printing
    its help imports none of numpy, pyarrow, numba, scipy, polars or prefect, nor rich's
    console, progress bar or table (each command imports what it uses; a command group's
    modules load when it is named)."""
    code = ("from pipeline.cli.app import cli; from click.testing import CliRunner; "
            "r = CliRunner().invoke(cli, ['--help']); assert r.exit_code == 0, r.output")
    assert imported_after(code, ("numpy", "pyarrow", "numba", "scipy", "polars", "prefect",
                                 "rich.progress", "rich.table", "rich.console")) == []


def test_the_histogram_command_reaches_its_loop_without_pyarrow(tmp_path):
    """The modules of the hot path, and the whole histogramming of a capture, import
    neither pyarrow nor scipy (schemas.constants holds the contract's numbers): pyarrow
    is imported by the command that writes a file, when it writes it."""
    from pipeline.io.capture import CaptureWriter
    from stages.testpattern import pattern_words

    with CaptureWriter(tmp_path / "p", n_tdc=8) as w:
        w.write(pattern_words(2000, 8, hit_prob=0.3, rng=1)[0])
    code = ("from pipeline.cli.instruments import detect; "
            "from pipeline.io.capture import Capture; "
            "from pipeline.offline.datapath import histogram_capture; "
            f"path = {str(w.bin_path)!r}; assert detect(path, None) == 'tcspc'; "
            "state, bounds = histogram_capture(Capture(path)); "
            "assert state.class_counts.sum() == 16000")
    assert imported_after(code, ("pyarrow", "scipy", "polars")) == []
