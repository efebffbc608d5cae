import json

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from pipeline.cli import cli
from schemas import CALIBRATION_INL, CALIBRATION_TDC, validate

SCENE = """
name = "density8"
[sensor]
n_pixels = 8
hot_pixels = []
[[ambient]]
kind = "lux"
lux = 1500.0
"""


def run(*args, ok=True):
    res = CliRunner().invoke(cli, list(args))
    if ok:
        assert res.exit_code == 0, res.output
    return res


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    d = tmp_path_factory.mktemp("cal")
    (d / "density8.toml").write_text(SCENE)
    run("simulate", str(d / "density8.toml"), "--cycles", "600000", "--out",
        str(d / "dens.bin"), "-q")
    return d


def test_density_calibration_directory(capture):
    out = capture / "caldir"
    run("calibrate", "density", str(capture / "dens.bin"), "--out", str(out), "--plot",
        str(capture / "dens.png"))
    tdc, inl = pq.read_table(out / "tdc.parquet"), pq.read_table(out / "inl.parquet")
    validate(tdc, CALIBRATION_TDC)
    validate(inl, CALIBRATION_INL)
    meta = json.loads((out / "meta.json").read_text())
    assert meta["schema_version"] == CALIBRATION_TDC.version and meta["software"]
    assert len(meta["sources"][0]["sha256"]) == 64 and meta["created"]
    truth = json.loads((capture / "dens.json").read_text())["truth"]["chip"]
    np.testing.assert_array_equal(tdc.column("n_min").to_numpy(), truth["n_min"])
    np.testing.assert_allclose(tdc.column("lsb_ps").to_numpy(), truth["lsb_window_ps"],
                               atol=0.15)
    assert (capture / "dens.png").read_bytes()[:4] == b"\x89PNG"
    # the histogram command takes the calibration's bounds
    run("histogram", str(capture / "dens.bin"), "--out", str(capture / "h.parquet"),
        "--calibration", str(out), "-q")


def test_density_filled_from_a_dimmer_test(capture):
    """``--fill``: a density test at half the light measures the codes under the first
    one's reset peak (accuracy: tests/stages/test_calibration.py); both are sources."""
    (capture / "dim8.toml").write_text(SCENE.replace("lux = 1500.0", "lux = 750.0"))
    run("simulate", str(capture / "dim8.toml"), "--cycles", "600000", "--out",
        str(capture / "dim.bin"), "-q", "--seed", "3")
    out, plain = capture / "caldir_fill", capture / "caldir_plain"
    run("calibrate", "density", str(capture / "dens.bin"), "--fill", str(capture / "dim.bin"),
        "--out", str(out))
    run("calibrate", "density", str(capture / "dens.bin"), "--out", str(plain))
    meta = json.loads((out / "meta.json").read_text())
    assert [p["path"].rsplit("/", 1)[-1] for p in meta["sources"]] == ["dens.bin", "dim.bin"]
    filled, before = (pq.read_table(d / "inl.parquet") for d in (out, plain))
    validate(filled, CALIBRATION_INL)
    a, b = (t.column("inl_lsb").to_numpy(zero_copy_only=False) for t in (filled, before))
    assert not np.allclose(a, b, equal_nan=True)
    truth = json.loads((capture / "dens.json").read_text())["truth"]["chip"]
    tdc = pq.read_table(out / "tdc.parquet")
    np.testing.assert_allclose(tdc.column("lsb_ps").to_numpy(), truth["lsb_window_ps"],
                               atol=0.15)


def test_too_small_capture_is_refused_and_the_old_calibration_stays(capture):
    out = capture / "caldir2"
    run("calibrate", "density", str(capture / "dens.bin"), "--out", str(out))
    before = (out / "tdc.parquet").read_bytes()
    res = run("calibrate", "density", str(capture / "dens.bin"), "--out", str(out),
              "--inl-rms", "0.05", ok=False)
    assert res.exit_code != 0
    assert "needs about" in str(res.exception) and "cycles" in str(res.exception)
    assert (out / "tdc.parquet").read_bytes() == before


def test_range_end_to_end_against_the_truth(capture):
    """simulate -> calibrate density -> calibrate delay -> range, on an 8-TDC chip."""
    d = capture
    def mirror_scene(name, pixels, distance_m, reflectivity, ambient):
        base = SCENE.replace('name = "density8"', f'name = "{name}"')
        base = base.replace("lux = 1500.0", f"lux = {ambient}") if ambient else \
            base.split("[[ambient]]")[0]
        (d / f"{name}.toml").write_text(base + f"""
[gate]
t_laser_win_ns = 140.0
delay_ns = 100.0
[[targets]]
pixels = {pixels}
distance_m = {distance_m}
reflectivity = {reflectivity}
surface = "mirror"
""")

    mirror_scene("delay8", [0, 7], 0.001, 0.0005, None)
    mirror_scene("range8", [0, 3], 2.0, 0.002, 300.0)
    run("simulate", str(d / "delay8.toml"), "--cycles", "200000", "--out", str(d / "z.bin"),
        "-q")
    run("simulate", str(d / "range8.toml"), "--cycles", "100000", "--out", str(d / "r.bin"),
        "-q", "--seed", "7")
    cal = d / "caldir_range"
    # LSB against light over a range that covers the delay (~0.02) and range captures
    levels = []
    for lux in (100, 600, 2000, 6000):
        (d / f"d{lux}.toml").write_text(SCENE.replace("lux = 1500.0", f"lux = {lux}.0"))
        run("simulate", str(d / f"d{lux}.toml"), "--cycles", "600000", "--out",
            str(d / f"d{lux}.bin"), "-q")
        levels.append(str(d / f"d{lux}.bin"))
    run("calibrate", "lsb", *levels, "--out", str(cal), "--inl-rms", "1.0")
    run("calibrate", "delay", str(d / "z.bin"), "--out", str(cal))
    run("range", str(d / "r.bin"), "--calibration", str(cal), "--out", str(d / "r.parquet"))
    import polars as pl

    df = pl.read_parquet(d / "r.parquet").sort("tdc")
    target = df.filter(pl.col("tdc") < 4)
    assert target["detected"].all()
    # limited by the 6e5-cycle density tests (INL ~0.4 LSB ~ 1.3 cm), not by photons
    assert (target["distance_m"] - 2.0).abs().max() < 0.05
    assert df.filter(pl.col("tdc") >= 4)["detected"].sum() <= 1
