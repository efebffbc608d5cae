"""The calibration as one object: loaded once with validation, saved in one place."""

import json

import numpy as np
import pytest

from pipeline.io.caldir import load_calibration, save_calibration
from pipeline.offline.calibrate import write_caldir
from schemas.errors import CalibrationError
from stages import calibration as cal
from stages.calibration_set import Calibration, time_axis

N = 4


def density(n=N, light=0.3):
    rng = np.random.default_rng(0)
    width = 1 + rng.uniform(-0.3, 0.3, (n, 512))
    inl = np.cumsum(width - 1, axis=1) - (width - 1)
    return cal.DensityResult(np.full(n, 205e-12), np.full(n, 390.3), width, width - 1, inl,
                             np.full(n, 1e6), np.full(n, light), np.ones(n, bool),
                             np.full(n, 0.05))


def second(n=N):
    return cal.SecondStage(np.full(n, 20), np.full(n, 150), np.full(n, 40), np.full(n, 90))


def test_a_saved_calibration_loads_back_value_for_value(tmp_path):
    fit = cal.LsbFit(np.tile([205.0, 3.0, -1.0, 0.5], (N, 1)), 0.3, 0.2, (0.05, 0.6),
                     np.zeros((N, 5)))
    write_caldir(tmp_path / "c", density(), second(), [], lsb_fit=fit)
    c = load_calibration(tmp_path / "c")
    assert c.n_tdc == N and not c.has_delay
    assert c.delay_reasons == ("no delay measurement",) * N
    np.testing.assert_array_equal(c.density.inl_lsb, density().inl_lsb)
    np.testing.assert_array_equal(c.lsb_fit.coef, fit.coef)
    assert c.bounds.n_min.tolist() == [20] * N and c.bounds.source.startswith("calibration:")
    d = np.array([100e-9, np.nan, 101e-9, 99e-9])
    c2 = c.with_delay(d, ["", "no return detected", "", ""], 180e-12, {"capture": "z.bin"})
    save_calibration(c2, tmp_path / "c")
    c3 = load_calibration(tmp_path / "c")
    np.testing.assert_allclose(c3.delay_s, d, rtol=1e-12)
    assert c3.delay_reasons[1] == "no return detected" and c3.irf_sigma_s == 180e-12
    meta = json.loads((tmp_path / "c" / "meta.json").read_text())
    assert meta["delay"]["capture"] == "z.bin" and meta["lsb_poly_x"]["n_range"] == [0.05, 0.6]


def test_the_lsb_at_a_light_says_when_it_is_a_guess(tmp_path):
    write_caldir(tmp_path / "c", density(), second(), [])
    c = load_calibration(tmp_path / "c")
    lsb, note = c.lsb_s(0.3)
    assert note == "" and np.allclose(lsb, 205e-12)
    _, note = c.lsb_s(0.6)
    assert "one density test at 0.3" in note


def test_rows_and_time_axis(tmp_path):
    write_caldir(tmp_path / "c", density(), second(), [])
    c = load_calibration(tmp_path / "c").rows(1, 3)
    assert c.n_tdc == 2 and c.delay_s.shape == (2,)
    hits = np.zeros((2, 512))
    hits[:, 100:380] = 5
    axis = time_axis(c, hits, np.full(2, 1e5), 80e-9)
    assert axis.tau_edges_s.shape == (2, 513) and np.all(np.diff(axis.tau_edges_s) > 0)
    with pytest.raises(ValueError, match="calibrates 4 TDCs"):
        load_calibration(tmp_path / "c").rows(2, 6)


def test_a_damaged_directory_is_refused(tmp_path):
    write_caldir(tmp_path / "c", density(), second(), [])
    (tmp_path / "c" / "meta.json").write_text("{not json")
    with pytest.raises(CalibrationError, match="not valid JSON"):
        load_calibration(tmp_path / "c")
    write_caldir(tmp_path / "d", density(), second(), [])
    (tmp_path / "d" / "inl.parquet").unlink()
    with pytest.raises(CalibrationError, match="no inl.parquet"):
        load_calibration(tmp_path / "d")
    with pytest.raises(CalibrationError, match="not a calibration directory"):
        load_calibration(tmp_path / "nothing")


def test_the_object_is_read_only(tmp_path):
    write_caldir(tmp_path / "c", density(), second(), [])
    c = load_calibration(tmp_path / "c")
    with pytest.raises(ValueError):
        c.delay_s[0] = 1.0
    with pytest.raises(AttributeError):
        c.path = "elsewhere"
    assert isinstance(c, Calibration)


def test_a_reader_never_mixes_two_versions_while_current_is_swapped(tmp_path):
    """#39.1: ``current`` swapped between two chips (4 and 6 TDCs, different light) while
    loads run: every load is one whole version, named by its own directory and identity."""
    import shutil
    import threading

    from pipeline.io.atomic import point_link

    chips = {}
    for name, n, light in (("a", 4, 0.3), ("b", 6, 0.5)):
        write_caldir(tmp_path / "versions" / name, density(n, light), second(n), [])
        chips[name] = load_calibration(tmp_path / "versions" / name)
    ids = {c.meta["calibration_id"]: (c.n_tdc, c.density_light) for c in chips.values()}
    assert len(ids) == 2  # two contents, two identities
    shutil.copytree(tmp_path / "versions" / "a", tmp_path / "copy")
    assert load_calibration(tmp_path / "copy").meta["calibration_id"] == \
        chips["a"].meta["calibration_id"]  # the identity is the content, not the place
    current = tmp_path / "current"
    point_link(current, tmp_path / "versions" / "a")
    stop, swaps = threading.Event(), [0]

    def publisher():
        while not stop.is_set():
            point_link(current, tmp_path / "versions" / "ab"[swaps[0] % 2])
            swaps[0] += 1

    t = threading.Thread(target=publisher)
    t.start()
    seen = set()
    try:
        for _ in range(150):
            c = load_calibration(current)
            assert ids[c.meta["calibration_id"]] == (c.n_tdc, c.density_light)
            assert c.density.inl_lsb.shape == (c.n_tdc, 512)
            assert c.path == str((tmp_path / "versions" / ("a" if c.n_tdc == 4 else "b"))
                                 .resolve())
            seen.add(c.n_tdc)
    finally:
        stop.set()
        t.join()
    assert seen == {4, 6} and swaps[0] > 150
