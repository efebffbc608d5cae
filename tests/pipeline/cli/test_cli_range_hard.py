"""`tcspc range` on hand-made bad histograms (issue 24.6): a one-line error or a flagged
row, never a traceback, never a negative distance."""

import numpy as np
import polars as pl
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from pipeline.cli import cli
from schemas.outputs import HISTOGRAMS


def write(path, counts, width_ps=16.0, cycles=1_000_000):
    """A histograms 2.0 file as another tool would write it (plain pyarrow)."""
    rows = len(counts)
    widths = width_ps if isinstance(width_ps, list) else [width_ps] * rows
    cyc = cycles if isinstance(cycles, list) else [cycles] * rows
    t = pa.table({
        "measurement": ["hand"] * rows, "tdc": pa.array(range(rows), pa.uint16()),
        "cycles": pa.array(cyc, pa.uint64()),
        "counts": pa.array([list(map(int, c)) for c in counts], pa.list_(pa.uint64())),
        "n_hit": pa.array([int(sum(c)) for c in counts], pa.uint64()),
        **{k: pa.array([0] * rows, pa.uint64()) for k in ("n_no_hit", "n_artifact",
                                                          "n_invalid_phase", "n_malformed")},
        "instrument": ["picoquant-t3"] * rows,
        "bin_width_ps": pa.array(widths, pa.float64()),
    }, schema=HISTOGRAMS.schema)
    pq.write_table(t, path)
    return path


def a_return(n=2000, at=1200, size=400):
    c = np.random.default_rng(0).poisson(1.0, n)
    c[at - 2:at + 2] += size
    return c


def run(tmp_path, hist, *args):
    out = tmp_path / "r.parquet"
    res = CliRunner().invoke(cli, ["range", str(hist), "--out", str(out), *args])
    # never a traceback: an exit through click (SystemExit) or none
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exc_info
    return res, (pl.read_parquet(out) if out.exists() and res.exit_code == 0 else None)


@pytest.mark.parametrize("case, counts, width, args, words", [
    ("zero bin width", [a_return()], 0.0, [], "bin widths"),
    ("negative bin width", [a_return()], -16.0, [], "bin widths"),
    ("no bins", [[]], 16.0, [], "at least one bin"),
    ("NaN p_fa", [a_return()], 16.0, ["--p-fa", "nan"], "p_fa"),
    ("zero IRF", [a_return()], 16.0, ["--irf-ps", "0"], "--irf-ps"),
    ("IRF wider than the window", [a_return()], 16.0, ["--irf-ps", "1e9"], "no wider"),
])
def test_a_bad_histogram_or_argument_is_a_one_line_error(tmp_path, case, counts, width,
                                                         args, words):
    hist = write(tmp_path / "h.parquet", counts, width)
    res, _ = run(tmp_path, hist, "--delay-ps", "1000", *args)
    # exit 2: bad input (docs/design.md), in one line
    assert res.exit_code == 2 and words in res.output, res.output
    assert "Traceback" not in res.output and len(res.output.strip().splitlines()) == 1


def test_inconsistent_rows_are_flagged_not_detected(tmp_path):
    """Row 0: fewer cycles than counts (0 was a detection with sigma = inf, 0.7476 m);
    row 1: a NaN bin width (no time axis); row 2: fine."""
    hist = write(tmp_path / "h.parquet", [a_return()] * 3, [16.0, float("nan"), 16.0],
                 [0, 1_000_000, 1_000_000])
    res, r = run(tmp_path, hist, "--delay-ps", "1000", "--max-returns", "1")
    assert res.exit_code == 0, res.output
    assert r["detected"].to_list() == [False, False, True]
    assert r["flag"][0] == "fewer cycles than counts" and r["flag"][1] == "no finite time axis"
    assert r["flag"][2] == "" and 0 < r["distance_m"][2]


def test_a_delay_beyond_the_return_is_flagged_never_a_negative_distance(tmp_path):
    """The return at 1200 x 16 ps = 19.2 ns, the delay 25 ns: was -0.45 m, no warning."""
    hist = write(tmp_path / "h.parquet", [a_return()])
    res, r = run(tmp_path, hist, "--delay-ps", "25000")
    assert res.exit_code == 0, res.output
    row = r.filter(pl.col("return_index") == 0)
    assert not row["detected"][0] and "before the zero" in row["flag"][0]
    assert not (r["distance_m"] < 0).any()


def test_an_instruments_file_is_ranged_one_return_a_pixel_unless_asked(tmp_path):
    """The real HydraHarp sample (a decay with a long tail): with three returns asked, the
    tail is found as surfaces 1 and 2 m further (the search models tails as Gaussian), so
    an instrument's file defaults to one return, and asking for more warns."""
    from pathlib import Path

    ptu = Path(__file__).parents[2] / "data" / "picoquant" / "hydraharp_v20_t3.ptu"
    runner = CliRunner()
    out = tmp_path / "one.parquet"
    res = runner.invoke(cli, ["range", str(ptu), "--delay-ps", "0", "--out", str(out), "-q"])
    assert res.exit_code == 0, res.output
    assert pl.read_parquet(out)["return_index"].max() == 0
    out3 = tmp_path / "three.parquet"
    res = runner.invoke(cli, ["range", str(ptu), "--delay-ps", "0", "--out", str(out3), "-q",
                              "--max-returns", "3"])
    assert res.exit_code == 0 and "the response's own tail" in res.output
    assert pl.read_parquet(out3)["return_index"].max() > 0  # the tail, found as surfaces


def test_with_a_zero_file_further_returns_are_searched_with_its_measured_response(tmp_path):
    """The same file as its own zero: its returns are the measured response, tail and all,
    so three returns asked find the one there is, at distance 0 on both channels (the
    delay's instrument sigma is the ranges' too: with the returns' FWHM in its place the
    file came out 2.07 m from itself)."""
    from pathlib import Path

    ptu = Path(__file__).parents[2] / "data" / "picoquant" / "hydraharp_v20_t3.ptu"
    out = tmp_path / "self.parquet"
    res = CliRunner().invoke(cli, ["range", str(ptu), "--zero", str(ptu), "--out", str(out),
                                   "--max-returns", "3"])
    assert res.exit_code == 0, res.output
    assert "own tail" not in res.output and "further returns modelled on the response" \
        in res.output
    r = pl.read_parquet(out)
    assert r.height == 2 and r["return_index"].max() == 0  # no tail found as a surface
    assert r["detected"].all() and (r["distance_m"] == 0).all()


def test_a_truncated_instrument_file_is_not_ranged_unless_allowed(tmp_path):
    """A PTU file cut short, as the target or as the zero: nothing written, exit 3 (a
    delay measured on half a zero file put the file's own return 1-2 cm away, exit 0);
    --allow-truncated ranges it, flagged in the output's metadata."""
    from pathlib import Path

    import pyarrow.parquet as pq

    ptu = Path(__file__).parents[2] / "data" / "picoquant" / "hydraharp_v20_t3.ptu"
    cut = tmp_path / "cut.ptu"
    cut.write_bytes(ptu.read_bytes()[:200_002])
    runner = CliRunner()
    for args in (["range", str(ptu), "--zero", str(cut)], ["range", str(cut), "--zero", str(ptu)],
                 ["range", str(cut), "--delay-ps", "0"]):
        out = tmp_path / "r.parquet"
        res = runner.invoke(cli, [*args, "--out", str(out)])
        assert res.exit_code == 3 and "cut.ptu is truncated" in res.output, res.output
        assert not out.exists()
    res = runner.invoke(cli, ["range", str(ptu), "--zero", str(cut), "--out", str(out),
                              "--allow-truncated", "-q"])
    assert res.exit_code == 0, res.output
    assert pq.read_schema(out).metadata[b"tcspc.truncated"] == b"True"
