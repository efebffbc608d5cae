"""Issue 33: ``calibrate delay`` counts the zero capture's uniform light as a fifth density
test (``delay_from_state``, :mod:`stages.calibration.zero_test`), once per capture, on a
chip of the zoo with what real chips have (benchmarks/calibration_sigma.py's path: Poisson
draws of expected histograms through ``lsb_from_states`` and ``delay_from_state``)."""

import numpy as np
import pytest

from benchmarks.calibration_sigma import GATE_S, T, capture, chip_of, second_of
from pipeline.offline import calibrate as pc
from stages.calibration_set import Calibration

N = 8
LEVELS = (0.02, 0.05, 0.1, 0.3)


@pytest.fixture(scope="module")
def campaign():
    chip = chip_of(2, N)
    rng = np.random.default_rng([2, 5])
    second = second_of(chip)
    tests = [(capture(chip, n, 1e6, rng), second) for n in LEVELS]
    var: dict = {}
    best, second, fit, *_ = pc.lsb_from_states(tests, T, inl_rms_lsb=2.0, variance=var)
    calib = Calibration(best, second, fit, np.full(N, np.nan), (), None, {},
                        width_var_lsb2=var["width_var"])
    lsb = chip.window_truth(0.07, T)[0]
    zeros = [capture(chip, 0.07, 1e6, rng, np.full(N, 0.02), np.full(N, 200.5) * lsb)
             for _ in range(2)]
    return chip, calib, zeros


def _delay_error_ps(chip, calib):
    truth = GATE_S - 200.5 * chip.window_truth(0.07, T)[0]
    return (calib.delay_s - truth) * 1e12


def test_the_zero_capture_is_counted_once_and_lowers_the_tables_variance(campaign):
    chip, calib, (z1, z2) = campaign
    got = pc.delay_from_state(calib, z1, T, GATE_S, "zero1.bin")
    entry, = got.meta["zero_density"]
    assert entry["capture"] == "zero1.bin" and entry["hits"] == int(z1.hits.sum())
    used = np.asarray(entry["codes_used"])
    assert (used > 300).all(), used
    above = np.isfinite(calib.width_var_lsb2) & np.isfinite(got.width_var_lsb2)
    assert np.median(got.width_var_lsb2[above] / calib.width_var_lsb2[above]) < 0.95
    # the table reaches further: the capture measured codes past its last one
    last = lambda c: np.isfinite(c.density.width_lsb).sum(axis=1)  # noqa: E731
    assert (last(got) >= last(calib)).all()
    # the same capture again, under another name too: not counted twice
    again = pc.delay_from_state(got, z1, T, GATE_S, "copy-of-zero1.bin")
    assert len(again.meta["zero_density"]) == 1
    np.testing.assert_array_equal(again.density.width_lsb, got.density.width_lsb)
    np.testing.assert_allclose(again.delay_s, got.delay_s)
    # another zero capture adds its own counts
    more = pc.delay_from_state(got, z2, T, GATE_S, "zero2.bin")
    assert [e["capture"] for e in more.meta["zero_density"]] == ["zero1.bin", "zero2.bin"]
    # the delay stays a measurement of the chip's (tens of ps on 1e6-cycle tests)
    assert np.sqrt(np.nanmean(_delay_error_ps(chip, got) ** 2)) < 150


def test_without_the_zero_test_the_table_is_the_campaigns(campaign, monkeypatch):
    chip, calib, (z1, _) = campaign
    monkeypatch.setattr(pc, "ZERO_AS_TEST", False)
    got = pc.delay_from_state(calib, z1, T, GATE_S, "zero1.bin")
    assert "zero_density" not in got.meta
    np.testing.assert_array_equal(got.density.width_lsb, calib.density.width_lsb)
