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


def test_too_small_capture_is_refused_and_the_old_calibration_stays(capture):
    out = capture / "caldir2"
    run("calibrate", "density", str(capture / "dens.bin"), "--out", str(out))
    before = (out / "tdc.parquet").read_bytes()
    res = run("calibrate", "density", str(capture / "dens.bin"), "--out", str(out),
              "--inl-rms", "0.05", ok=False)
    assert res.exit_code != 0
    assert "needs about" in str(res.exception) and "cycles" in str(res.exception)
    assert (out / "tdc.parquet").read_bytes() == before
