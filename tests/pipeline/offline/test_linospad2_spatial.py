"""The real LinoSPAD2 capture as time-of-flight histograms (``python -m
pipeline.io.linospad2_tof``), ranged per pixel and with the neighbours (``--spatial
--geometry linospad2``). The capture was taken under uniform light with no laser
(tests/data/README.md): its photons are pure background, so every detection is a false
surface. Folded from the format description here, independently of the code under test."""

import csv
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest

ROOT = Path(__file__).parents[3]
DATA = ROOT / "tests" / "data" / "linospad2"  # public files, see tests/data/README.md
DAT = DATA / "test_data_2212b.dat"
CSV = DATA / "TDC_A5_#36_2212b.csv"
PERIOD_PS, BINS = 80_000.0, 1024          # 32 periods of the board's 2.5 ns clock
EMPTY = [107, 111, 113, 125, 150]         # no photon in this capture (instruments_linospad2.md)

pytestmark = pytest.mark.skipif(not DAT.exists() or not CSV.exists(),
                                reason=f"the shared LinoSPAD2 sample is not in {DATA}")


def run(*args):
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.run([sys.executable, *map(str, args)], capture_output=True, text=True,
                          timeout=300, env=env)


def independent_fold(table_ps=None):
    """(256, BINS) counts from the words' bits alone: pixel 4 x line + bits 29:28 (2212b),
    time = code // 140 x 2500 ps + the fine code's nominal or calibrated centre."""
    w = np.fromfile(DAT, "<u4").astype(np.int64).reshape(-1, 65, 200)[:, :64]
    line = np.broadcast_to(np.arange(64)[None, :, None], w.shape)
    sel = w >= 2**31
    code = w[sel] % 2**28
    pixel = 4 * line[sel] + (w[sel] >> 28) % 4
    fine = code % 140
    if table_ps is None:
        within = fine * 2500 / 140
    else:
        lower = np.concatenate([np.zeros((256, 1)), table_ps[:, :-1]], axis=1)
        within = (lower[pixel, fine] + table_ps[pixel, fine]) / 2
    t = code // 140 * 2500.0 + within
    counts = np.zeros((256, BINS), np.int64)
    np.add.at(counts, (pixel, (t % PERIOD_PS // (PERIOD_PS / BINS)).astype(np.int64)), 1)
    return counts


def published_table():
    with open(CSV, newline="") as fh:
        rows = list(csv.reader(fh))[1:]
    return np.array([[float(x) for x in r[1:]] for r in rows])


@pytest.fixture(scope="module")
def tof(tmp_path_factory):
    d = tmp_path_factory.mktemp("linospad2_tof")
    for name, extra in (("cal", ["--code-times", CSV]), ("nominal", [])):
        r = run("-m", "pipeline.io.linospad2_tof", DAT, "--period-ps", PERIOD_PS, "--bins",
                BINS, "--out", d / f"{name}.parquet", *extra)
        assert r.returncode == 0, r.stderr
        assert "131,560 photons of 20 cycles" in r.stderr
        assert ("warning" in r.stderr) == (name == "nominal"), r.stderr
    return d


def _ranged(tof, name, *spatial):
    out = tof / f"{name}{'_sp' if spatial else ''}.r.parquet"
    r = run("-m", "pipeline.cli", "range", tof / f"{name}.parquet", "--delay-ps", "0",
            "--irf-ps", "42.5", *spatial, "--out", out, "--overwrite")
    assert r.returncode == 0, r.stderr
    return pl.read_parquet(out).filter(pl.col("return_index") == 0).sort("tdc"), r.stderr


def test_the_histograms_are_the_capture_folded_on_the_laser_period(tof):
    for name, table in (("nominal", None), ("cal", published_table())):
        h = pl.read_parquet(tof / f"{name}.parquet").sort("tdc")
        assert h["tdc"].to_list() == list(range(256)) and (h["row"] == 0).all()
        assert h["col"].to_list() == list(range(256))
        assert np.allclose(h["bin_width_ps"].to_numpy(), PERIOD_PS / BINS)
        np.testing.assert_array_equal(np.array(h["counts"].to_list()), independent_fold(table))


def test_without_the_code_density_table_the_carry_chain_makes_a_comb(tof):
    """A period of whole clock periods folds every pulse's dead and wide codes onto the
    same bins: summed over the 256 pixels, the nominal times leave bins empty and the
    spread is ~4x Poisson's; the board's table brings it back to ~Poisson."""
    def spread(name):
        s = np.array(pl.read_parquet(tof / f"{name}.parquet")["counts"].to_list()).sum(0)
        return s.min(), s.std() / np.sqrt(s.mean())
    lo, ratio = spread("nominal")
    assert lo == 0 and ratio > 3
    lo, ratio = spread("cal")
    assert lo > 50 and ratio < 1.5


def test_real_background_has_no_surface_per_pixel_or_with_the_neighbours(tof):
    """Calibrated, the real background (~514 photons a pixel, no laser) gives no false
    surface in 256 pixels either way (0.26 expected at P_fa 1e-3 a pixel; 0 measured); the
    5 empty pixels have their row, not detected."""
    for spatial in ((), ("--spatial", "--geometry", "linospad2")):
        r, err = _ranged(tof, "cal", *spatial)
        assert r.height == 256 and r["tdc"].to_list() == list(range(256))
        assert r["detected"].sum() <= 1, r.filter(pl.col("detected"))
        empty = r.filter(pl.col("tdc").is_in(EMPTY))
        assert not empty["detected"].any()
        if spatial:  # its candidate is its neighbours', and its row says so
            assert empty["flag"].str.starts_with("no photon in its histogram").all()
            others = r.filter(~pl.col("tdc").is_in(EMPTY))
            assert not others["flag"].str.contains("no photon").any()
        assert ("no return detected" in err) == (r["detected"].sum() == 0)
        assert "nan" not in err


def test_the_geometry_places_the_pixels_as_the_files_row_and_col(tof):
    a, _ = _ranged(tof, "nominal", "--spatial")
    b, _ = _ranged(tof, "nominal", "--spatial", "--geometry", "linospad2")
    assert a.select("tdc", "row", "col").equals(b.select("tdc", "row", "col"))
    assert np.array_equal(a["distance_m"].to_numpy(), b["distance_m"].to_numpy(),
                          equal_nan=True)


def test_the_converter_refuses_bad_arguments_in_one_line(tmp_path):
    for args, said in ((["--period-ps", "0"], "--period-ps must be > 0"),
                       (["--period-ps", "80000", "--code-times", CSV, "--firmware", "2208"],
                        "invalid choice"),
                       (["--period-ps", "80000", "--bins", "2"], "--bins must be >= 3"),
                       (["--period-ps", "80000", "--code-times", DAT], "not a text CSV")):
        r = run("-m", "pipeline.io.linospad2_tof", DAT, *args, "--out", tmp_path / "h.parquet")
        assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
        assert not (tmp_path / "h.parquet").exists(), r.stderr
        assert said in r.stderr, r.stderr
    png = tmp_path / "pic.png"
    png.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(65 * 200 * 4))
    r = run("-m", "pipeline.io.linospad2_tof", png, "--period-ps", "80000", "--out",
            tmp_path / "h.parquet")
    assert r.returncode == 2 and "not a LinoSPAD2 capture" in r.stderr, r.stderr


def test_known_surfaces_on_the_real_background(tmp_path):
    """The real background (calibrated) plus 10 signal photons a pixel drawn on a plane at
    3.0 m, an edge to a plane slanted 4.0 -> 4.8 m, and empty sky
    (benchmarks/linospad2_spatial.py): with the neighbours nearly every surface pixel is
    detected (per pixel ~2/3), none of the sky, no edge blurred (every error < 5 cm), the
    error smaller and its sigma covering it as per pixel."""
    import pyarrow.parquet as pq

    from benchmarks.linospad2_spatial import PERIOD_PS as P
    from benchmarks.linospad2_spatial import SIGMA_PS, scene, score, summary, with_signal
    from pipeline.io.geometry import load_geometry
    from pipeline.io.linospad2 import read_published_calibration
    from pipeline.io.linospad2_tof import tof_counts, tof_table
    from pipeline.offline.generic import range_generic
    from pipeline.offline.spatial import range_spatial

    background, _ = tof_counts(DAT, P, BINS, read_published_calibration(CSV))
    truth, rng = scene(), np.random.default_rng(11)
    per, sp = [], []
    for k in range(3):
        h = tmp_path / f"h{k}.parquet"
        pq.write_table(tof_table(with_signal(background, truth, 10, rng), P, f"m{k}"), h)
        per.append(score(range_generic(h, None, 0.0, None, SIGMA_PS * 1e-12, "ml", 1e-3)[0],
                         truth))
        sp.append(score(range_spatial(h, 0.0, SIGMA_PS * 1e-12, 1e-3,
                                      load_geometry("linospad2"))[0], truth))
    per, sp = summary(per), summary(sp)
    assert sp["surface"] == 540 and sp["sky"] == 228
    assert sp["detected"] >= 0.97 * 540 and per["detected"] <= 0.8 * 540, (per, sp)
    assert sp["false"] == 0 and per["false"] == 0
    assert sp["outliers"] == 0 and per["outliers"] == 0
    assert sp["rmse_mm"] < per["rmse_mm"] and sp["rmse_mm"] < 2.5, (per, sp)
    assert sp["cover"] > 0.9 and per["cover"] > 0.9, (per, sp)
