"""The counting floor of the delay (issue 33): the Cramér-Rao bound on a code's time from a
campaign's expected counts (:mod:`stages.calibration.floor`), checked against the binomial
rule of thumb and against Monte Carlo draws of the efficient estimator it bounds."""

import numpy as np

from stages.calibration.floor import tau_floor_s
from stages.calibration.reset_peak import at_risk_by_code
from stages.simulator.chip import REAL_CHIP_RANGES, random_chip
from stages.simulator.expected import expected_density_hits

T = 80e-9
N = 2


def _test(chip, light, cycles):
    return (expected_density_hits(chip, light, cycles, T), np.full(chip.n_tdc, float(cycles)),
            chip.window_truth(light, T)[1])


def _widths(chip, light=0.05):
    return np.diff(chip.boundaries_s(light), axis=1)


def test_without_pile_up_the_floor_is_the_binomial_share():
    """A dim test: the share F of the window below the code is binomial over its N hits,
    so the time's error is T' sqrt(F (1 - F) / N), T' the time up to x_T0."""
    chip, _ = random_chip(2, n_tdc=N, ranges=REAL_CHIP_RANGES)
    test = _test(chip, 0.002, 2e7)
    w = _widths(chip, 0.002)
    x0 = np.floor(test[2]) - 4
    got = tau_floor_s([test], w, 200, x0, T)
    for t in range(N):
        top = int(x0[t])
        f = w[t, :200].sum() / w[t, :top].sum()
        hits = test[0][t, :top].sum()
        want = T * top / test[2][t] * np.sqrt(f * (1 - f) / hits)  # T' ~ T top / x_T
        assert abs(got[t] / want - 1) < 0.03, (got, want)


def test_the_floor_is_what_the_efficient_estimator_reaches():
    """One bright test (0.3, pile-up): the share of Coates' corrected counts below the code,
    over 150 Poisson draws, errs by the floor (its RMS within 15 %; the floor is a bound
    the estimator reaches, not a guess)."""
    chip, _ = random_chip(2, n_tdc=N, ranges=REAL_CHIP_RANGES)
    h, c, x_t = _test(chip, 0.3, 1e6)
    w = _widths(chip, 0.3)
    x0 = np.floor(x_t) - 4
    floor = tau_floor_s([(h, c, x_t)], w, 200, x0, T)
    rng = np.random.default_rng(3)
    truth = np.array([T * w[t, :200].sum() / w[t, :int(x0[t])].sum() for t in range(N)])
    err = []
    for _ in range(150):
        d = rng.poisson(h).astype(np.float64)
        u = -np.log1p(-d / at_risk_by_code(d, c))
        err.append([T * u[t, :200].sum() / u[t, :int(x0[t])].sum() for t in range(N)] - truth)
    sd = np.sqrt(np.mean(np.square(err), axis=0))
    assert np.all(np.abs(sd / floor - 1) < 0.15), (sd, floor)


def test_more_tests_lower_it_and_an_unmeasured_code_needs_a_prior():
    chip, _ = random_chip(2, n_tdc=N, ranges=REAL_CHIP_RANGES)
    w = _widths(chip, 0.05)
    tests = [_test(chip, n, 1e6) for n in (0.05, 0.3)]
    x0 = chip.window_truth(0.05, T)[1] - 3.5  # the 0.05 test measures all of it
    both = tau_floor_s(tests, w, 200, x0, T)
    dim = tau_floor_s(tests[:1], w, 200, x0, T)
    assert np.all(both < dim) and np.all(np.isfinite(both))
    # at 0.02's x_T the top codes are measured by no test: no bound without a prior
    x_far = chip.window_truth(0.02, T)[1]
    assert np.all(np.isinf(tau_floor_s(tests, w, 200, x_far, T)))
    known = tau_floor_s(tests, w, 200, x_far, T, unmeasured_sd=0)
    prior = tau_floor_s(tests, w, 200, x_far, T, unmeasured_sd=0.1)
    assert np.all(np.isfinite(known)) and np.all(prior > known)
    # the codes above the bright test's window known: what is left is lower
    part = tau_floor_s(tests, w, 200, x0, T, known_from=np.floor(tests[1][2] - 2.5))
    assert np.all(part < both)
    # a capture whose codes near a return are left out measures less
    clear = np.broadcast_to(np.abs(np.arange(512) - 200) > 12, tests[0][0].shape)
    masked = tau_floor_s([(*tests[0], clear), tests[1]], w, 200, x0, T)
    assert np.all(masked > both)
