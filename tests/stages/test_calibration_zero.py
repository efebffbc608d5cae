"""Issue 33: the zero-distance capture's uniform light as a fifth density test
(:mod:`stages.calibration.zero_test`), on chips with what real chips have
(``REAL_CHIP_RANGES``): noise-free it adds no bias, noisy it lowers the delay's error as
the counting floor (:func:`stages.calibration.floor.tau_floor_s`) says, and ``calibrate
delay`` counts one capture once."""

import numpy as np
import pytest

from benchmarks.calibration_bias import (
    ZERO_PULSE_S,
    ZERO_ROW,
    ZERO_SIGNAL,
    axis_error_ps,
    campaign,
    floor_rows,
    rms,
    use,
    with_zero,
)
from stages.calibration import zero_test
from stages.simulator.chip import REAL_CHIP_RANGES, random_chip
from stages.simulator.expected import expected_hits

T = 80e-9
N = 8
LEVELS = (0.02, 0.05, 0.1, 0.3)
N0, CODE = 0.07, 200


@pytest.fixture(autouse=True)
def _after(monkeypatch):
    from stages import calibration as cal

    for name in ("PHASE_PULL", "OWN_TOP", "CONTINUE_CODES"):
        monkeypatch.setattr(cal, name, getattr(cal, name))  # restored after
    use("after")


def test_return_mask_reaches_the_response_sigmas():
    m = zero_test.return_mask(np.array([200.0, np.nan]), np.array([1.0, 1.0]))
    reach = int(np.ceil(zero_test.ZERO_CLEAR_SIGMAS)) + zero_test.ZERO_CLEAR_CODES
    assert np.flatnonzero(m[0]).tolist() == list(range(200 - reach, 200 + reach + 1))
    assert m[1].all()  # no return located: nothing of it is known to be uniform light


@pytest.mark.parametrize("seed", [1, 6])
def test_zero_capture_widths_are_the_chips_noise_free(seed):
    """Noise-free, the zero capture's widths clear of its return and reset peak are the
    chip's (Coates' correction undoes the return's pile-up below it), and the table with
    them combined reads the delay's code as the table without (no bias added)."""
    chip, _ = random_chip(seed, n_tdc=N, ranges=REAL_CHIP_RANGES)
    lsb, x_t, _ = chip.window_truth(N0, T)
    z = expected_hits(chip, N0, 1e6, T, signal=np.full(N, ZERO_SIGNAL),
                      tau_s=(CODE + 0.5) * lsb, pulse_sigma_s=ZERO_PULSE_S)
    peak = CODE - 20 + np.argmax(z[:, CODE - 20:CODE + 21], axis=1).astype(float)
    mask = zero_test.return_mask(peak, ZERO_PULSE_S / lsb)
    res, var = zero_test.zero_density(z, np.full(N, 1e6), T, mask)
    true = np.diff(chip.boundaries_s(N0), axis=1) / lsb[:, None]
    measured = np.isfinite(var)
    assert (measured & ~mask).sum(axis=1).min() > 300
    assert not (measured & mask).any()
    ratio = np.nansum(np.where(measured, true, np.nan), 1) / np.nansum(
        np.where(measured, res.width_lsb, np.nan), 1)
    err = np.where(measured, res.width_lsb * ratio[:, None] - true, 0.0)
    # codes 0-1 hold the jitter below tau = 0, and the last codes below the reset peak
    # are fitted beside its tail, as in every density test
    mid = (np.arange(512)[None, :] >= 2) & (np.arange(512)[None, :] < x_t[:, None] - 8)
    assert np.abs(err[mid]).max() < 2e-3, np.abs(err[mid]).max()
    assert np.abs(err[:, 2:]).max() < 0.03, np.abs(err[:, 2:]).max()
    best, _, _, tvar = campaign(chip, LEVELS, [1e6] * 4, None)
    new, nvar, used = with_zero(chip, best, tvar, N0, 1e6, CODE)
    assert (used > 300).all()
    before, after = axis_error_ps(chip, best, N0, CODE), axis_error_ps(chip, new, N0, CODE)
    assert rms([after]) < rms([before]) + 1.0, (rms([before]), rms([after]))
    # a zero capture of its return alone (no ambient light) is no density test: unused
    alone = np.round(expected_hits(chip, 1e-5, 1e6, T, signal=np.full(N, ZERO_SIGNAL),
                                   tau_s=(CODE + 0.5) * lsb, pulse_sigma_s=ZERO_PULSE_S))
    with np.errstate(all="raise"):
        r0, v0 = zero_test.zero_density(alone, np.full(N, 1e6), T, mask)
    same, _, none = zero_test.with_test(best, tvar, r0, v0)
    assert not r0.ok.any() and not none.any()
    np.testing.assert_array_equal(same.width_lsb, best.width_lsb)
    finite = np.isfinite(tvar)  # (1e-3: the units renormalised)
    assert np.all(nvar[finite] <= tvar[finite] * (1 + 1e-3))


@pytest.mark.slow
def test_zero_capture_lowers_the_delay_error_as_the_floor_says():
    """Noisy (Poisson draws of the same campaigns, paired): a 2e6-cycle zero capture at
    0.07 counted as a fifth test lowers the delay's RMS error at code 200 by about what the
    floor says (74 -> 64 ps), and the chain stays near its floor (57 s on 2 cores; the
    default suite's check is in tests/pipeline/offline/test_calibration_zero.py)."""
    before, after, floor0, floor1 = [], [], [], []
    for seed in (1, 2, 3):
        chip, knobs = random_chip(seed, n_tdc=N, ranges=REAL_CHIP_RANGES)
        fl = floor_rows(chip, knobs, LEVELS, [1e6] * 4, N0, CODE, 2e6)
        floor0.append(fl["INL table"])
        floor1.append(fl[ZERO_ROW])
        for d in range(2):
            rng = np.random.default_rng([seed, d, 7])
            best, _, _, var = campaign(chip, LEVELS, [1e6] * 4, rng)
            before.append(axis_error_ps(chip, best, N0, CODE))
            after.append(axis_error_ps(chip, with_zero(chip, best, var, N0, 2e6, CODE,
                                                       rng)[0], N0, CODE))
    b, a, f0, f1 = rms(before), rms(after), rms(floor0), rms(floor1)
    assert f1 < 0.9 * f0, (f0, f1)
    assert a < 0.92 * b, (b, a)
    assert 0.75 < a / f1 < 1.25, (a, f1)
