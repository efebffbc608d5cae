import json
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from pipeline.cli.app import cli
from schemas import CALIBRATION_INL, CALIBRATION_TDC, validate

SCENE = """
name = "density8"
[sensor]
n_pixels = 8
hot_pixels = []
[[ambient]]
kind = "lux"
lux = 2009.247
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
    (capture / "dim8.toml").write_text(SCENE.replace("lux = 2009.247", "lux = 1004.624"))
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
              "--inl-rms", "0.05", "--overwrite", ok=False)
    assert res.exit_code == 2
    assert "needs about" in res.output and "cycles" in res.output
    assert (out / "tdc.parquet").read_bytes() == before


@pytest.fixture(scope="module")
def lsb_cal(capture):
    """LSB against light over 0.02-0.69 detections a cycle (covering the delay and range
    captures), 4 density tests of 6e5 cycles on the 8-TDC chip."""
    d = capture
    levels = []
    for lux in (133.950, 803.699, 2678.997, 8036.990):
        name = f"d{round(lux)}"
        (d / f"{name}.toml").write_text(SCENE.replace("lux = 2009.247", f"lux = {lux}"))
        run("simulate", str(d / f"{name}.toml"), "--cycles", "600000", "--out",
            str(d / f"{name}.bin"), "-q")
        levels.append(str(d / f"{name}.bin"))
    run("calibrate", "lsb", *levels, "--out", str(d / "lsb_cal"), "--inl-rms", "1.0")
    return d / "lsb_cal"


def test_range_end_to_end_against_the_truth(capture, lsb_cal):
    """simulate -> calibrate density -> calibrate delay -> range, on an 8-TDC chip."""
    d = capture
    def mirror_scene(name, pixels, distance_m, reflectivity, ambient):
        base = SCENE.replace('name = "density8"', f'name = "{name}"')
        base = base.replace("lux = 2009.247", f"lux = {ambient}") if ambient else \
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
    mirror_scene("range8", [0, 3], 2.0, 0.002, 401.849)
    run("simulate", str(d / "delay8.toml"), "--cycles", "200000", "--out", str(d / "z.bin"),
        "-q")
    run("simulate", str(d / "range8.toml"), "--cycles", "100000", "--out", str(d / "r.bin"),
        "-q", "--seed", "7")
    cal = d / "caldir_range"
    shutil.copytree(lsb_cal, cal)
    run("calibrate", "delay", str(d / "z.bin"), "--out", str(cal))
    run("range", str(d / "r.bin"), "--calibration", str(cal), "--out", str(d / "r.parquet"))
    import polars as pl

    df = pl.read_parquet(d / "r.parquet").sort("tdc")
    target = df.filter(pl.col("tdc") < 4)
    assert target["detected"].all()
    # limited by the 6e5-cycle density tests (INL ~0.4 LSB ~ 1.3 cm), not by photons
    assert (target["distance_m"] - 2.0).abs().max() < 0.05
    assert df.filter(pl.col("tdc") >= 4)["detected"].sum() <= 1


@pytest.mark.slow
def test_delay_from_a_target_at_a_known_distance(capture, lsb_cal):
    """`calibrate delay --distance-m 1.2` on a capture of a target at 1.2 m: range then
    puts a target at 2 m at 2 m (eq. 5.3 with the target's round trip)."""
    d = capture
    for name, dist, seed in (("known8", 1.2, 3), ("far8", 2.0, 7)):
        (d / f"{name}.toml").write_text(SCENE.replace('name = "density8"', f'name = "{name}"')
                                        .split("[[ambient]]")[0] + f"""
[gate]
t_laser_win_ns = 140.0
delay_ns = 100.0
[[targets]]
pixels = [0, 3]
distance_m = {dist}
reflectivity = 0.002
surface = "mirror"
""")
        run("simulate", str(d / f"{name}.toml"), "--cycles", "100000", "--out",
            str(d / f"{name}.bin"), "-q", "--seed", str(seed))
    cal = d / "caldir_known"
    shutil.copytree(lsb_cal, cal)
    run("calibrate", "delay", str(d / "known8.bin"), "--out", str(cal), "--distance-m", "1.2")
    run("range", str(d / "far8.bin"), "--calibration", str(cal), "--out",
        str(d / "far.parquet"))
    import polars as pl

    target = pl.read_parquet(d / "far.parquet").filter(pl.col("tdc") < 4)
    assert target["detected"].all()
    assert (target["distance_m"] - 2.0).abs().max() < 0.05
    res = run("calibrate", "delay", str(d / "known8.bin"), "--out", str(cal),
              "--distance-m", "-1", ok=False)
    assert res.exit_code == 2 and "--distance-m must be >= 0" in res.output


def zero_distance(d, name, delay_ns, reflectivity, lux=None, gate_ns=140.0,
                  cycles=50_000):
    """A zero-distance capture of the 8-TDC chip: the return at tau = gate - delay."""
    scene = SCENE.replace('name = "density8"', f'name = "{name}"')
    scene = scene.replace("lux = 2009.247", f"lux = {lux}") if lux else \
        scene.split("[[ambient]]")[0]
    (d / f"{name}.toml").write_text(scene + f"""
[gate]
t_laser_win_ns = {gate_ns}
delay_ns = {delay_ns}
[[targets]]
pixels = [0, 7]
distance_m = 0.001
reflectivity = {reflectivity}
surface = "mirror"
""")
    run("simulate", str(d / f"{name}.toml"), "--cycles", str(cycles), "--out",
        str(d / f"{name}.bin"), "-q")
    return d / f"{name}.bin", json.loads((d / f"{name}.json").read_text())["truth"]


def delay_tolerance_ps(caldir):
    """What the calibration allows: 4 sigma of the density tests' INL statistics at the
    peak (the INL error, RMS over codes, x LSB) and of the peak's position (sigma_ps of
    the fit, from its counts), plus 20 ps for the LSB polynomial's interpolation."""
    meta = json.loads((caldir / "meta.json").read_text())
    lsb = pq.read_table(caldir / "tdc.parquet").column("lsb_ps").to_numpy()
    inl = np.asarray(meta["density"]["inl_error_lsb"]) * lsb
    peak = np.asarray(meta["delay"]["sigma_ps"], np.float64)
    return 4 * np.hypot(inl, peak) + 20


@pytest.mark.parametrize("delay_ns, lux", [
    (71.5, None),   # issue 15: the return near the density test's reset-peak codes
    (63.0, None),   # 12 codes from the capture's own reset peak
    (100.0, None),  # mid-window
    (139.0, None),  # 5 codes from the window's end
    (71.5, 66.975),   # a little ambient light: a reset peak, dimmer than the density tests
    (135.0, 4018.495),  # brighter, near the window's end
])
def test_the_delay_is_found_wherever_the_return_is(capture, lsb_cal, tmp_path, delay_ns,
                                                    lux):
    """A dim zero-distance capture (0.07 detections a pixel a cycle, 5e4 cycles, gate 140
    ns) put the return where the in-situ scale took it for the reset peak: 128 of 128 TDCs
    "scaled from the reset peak", then delays NaN or tens of ns off, and exit 0. The
    return anywhere in the window, with or without ambient light: every TDC's delay within
    what its calibration allows (delay_tolerance_ps)."""
    zbin, truth = zero_distance(tmp_path, "z", delay_ns, 0.0015, lux)
    cal = tmp_path / "cal"
    shutil.copytree(lsb_cal, cal)
    res = run("calibrate", "delay", str(zbin), "--out", str(cal))
    assert "delay on 8 of 8 TDCs" in res.output
    got = pq.read_table(cal / "tdc.parquet").column("delay_ps").to_numpy()
    err_ps = got - truth["delay_ns"] * 1e3
    assert np.all(np.abs(err_ps) < delay_tolerance_ps(cal)), err_ps
    meta = json.loads((cal / "meta.json").read_text())["delay"]
    assert meta["tdcs_with_delay"] == 8 and meta["reasons"] == [""] * 8


@pytest.mark.parametrize("delay_ns, lux, why", [
    (60.6, None, "reset peak"),       # the return 2-3 codes from the reset peak
    (139.7, None, "window's end"),    # the return 1.5 codes from the window's end
    (71.5, 10715.987, "outside the LSB fit's range"),  # 0.8 a cycle, the fit ends at 0.69
    (100.0, None, "no return detected"),  # gate 300 ns: the return is before the window
])
def test_no_delay_anywhere_exits_non_zero_and_keeps_the_calibration(
        capture, lsb_cal, tmp_path, delay_ns, lux, why):
    """Where no TDC can be measured, the command says why and exits non-zero, and the
    calibration directory stays byte for byte as it was."""
    gate = 300.0 if why == "no return detected" else 140.0
    zbin, _ = zero_distance(tmp_path, "z", delay_ns, 0.0015, lux, gate_ns=gate)
    cal = tmp_path / "cal"
    shutil.copytree(lsb_cal, cal)
    before = (cal / "tdc.parquet").read_bytes()
    res = run("calibrate", "delay", str(zbin), "--out", str(cal), ok=False)
    assert res.exit_code == 2
    assert "no TDC got a delay" in res.output and why in res.output
    assert (cal / "tdc.parquet").read_bytes() == before


def test_a_tdc_without_a_delay_is_flagged_with_its_reason(capture, lsb_cal, tmp_path):
    """Some TDCs measured, one flagged by the density test: the reason is in meta.json,
    the count on stderr, and the delay NaN there only."""
    zbin, truth = zero_distance(tmp_path, "z", 100.0, 0.0015)
    cal = tmp_path / "cal"
    shutil.copytree(lsb_cal, cal)
    import pyarrow as pa

    tdc = pq.read_table(cal / "tdc.parquet")
    ok = tdc.column("ok").to_numpy(zero_copy_only=False).copy()
    ok[3] = False  # as a dead TDC would be
    pq.write_table(tdc.set_column(tdc.schema.get_field_index("ok"), "ok", pa.array(ok)),
                   cal / "tdc.parquet")
    res = run("calibrate", "delay", str(zbin), "--out", str(cal))
    assert "delay on 7 of 8 TDCs" in res.output and "flagged by the density test" in res.output
    got = pq.read_table(cal / "tdc.parquet").column("delay_ps").to_numpy()
    assert np.isnan(got[3]) and np.isfinite(np.delete(got, 3)).all()
    reasons = json.loads((cal / "meta.json").read_text())["delay"]["reasons"]
    assert reasons[3] == "flagged by the density test" and reasons.count("") == 7
    # ... and `tcspc range` ranges the others (at zero distance) and not that one, saying so
    res = run("range", str(zbin), "--calibration", str(cal), "--out", str(tmp_path / "r.pq"))
    assert "1 TDC(s) not ranged" in res.output
    import polars as pl

    df = pl.read_parquet(tmp_path / "r.pq").sort("tdc")
    assert df["detected"].to_list() == [True] * 3 + [False] + [True] * 4
    assert df.filter(pl.col("detected"))["distance_m"].abs().max() < 0.05


def test_a_campaign_with_no_calibrated_tdc_exits_non_zero_and_writes_nothing(tmp_path):
    """Four dark captures (no light: every TDC under the density test's hits): the
    campaign says why per TDC and exits non-zero; no calibration directory appears."""
    from pipeline.offline.simulate import simulate_capture
    from stages.models.scene import scene_from_dict

    caps = []
    for i in range(4):
        scene = scene_from_dict({"name": f"dark{i}", "sensor": {"n_pixels": 4}})
        simulate_capture(scene, 2000, tmp_path / f"dark{i}", seed=i)
        caps.append(str(tmp_path / f"dark{i}.bin"))
    r = run("calibrate", "lsb", *caps, "--out", str(tmp_path / "cal"), ok=False)
    assert r.exit_code != 0
    assert "no TDC calibrated" in r.output and "dead or dark" in r.output
    assert not (tmp_path / "cal").exists()


def test_calibrate_plan_from_a_zero_capture(tmp_path):
    """`calibrate plan ZERO.bin --cycles-budget N --out PLAN.json`: the tests to take (the
    levels and the zero's light), cycles within the budget, the expected delay error per
    TDC printed; a missing capture is refused before any work."""
    zbin, _ = zero_distance(tmp_path, "z", 100.0, 0.0015, 500.0, cycles=100_000)
    res = run("calibrate", "plan", str(zbin), "--cycles-budget", "4e6", "--out",
              str(tmp_path / "plan.json"))
    plan = json.loads((tmp_path / "plan.json").read_text())
    assert 4 <= len(plan["tests"]) <= 5
    assert sum(t["cycles"] for t in plan["tests"]) <= 4e6
    assert all(t["light"] > 0 and t["cycles"] > 0 for t in plan["tests"])
    assert "expected delay error from counting" in res.output
    assert len(plan["expected_delay_error_ps"]) == 8
    bad = run("calibrate", "plan", str(tmp_path / "none.bin"), "--cycles-budget", "4e6",
              "--out", str(tmp_path / "p2.json"), ok=False)
    assert bad.exit_code == 2 and "capture not found" in bad.output, bad.output
    assert not (tmp_path / "p2.json").exists()
