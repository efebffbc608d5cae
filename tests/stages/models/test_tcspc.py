import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from stages.models.tcspc import (
    centroid_sigma,
    crlb_tof,
    detected_power_shape,
    first_photon_histogram,
    log_phi_interval,
    log_phi_intervals,
    niclass_histogram,
    peak_shift,
)

WINDOW, BIN, SIGMA, TOF = 80e-9, 0.2e-9, 0.2e-9, 40e-9


def photon_by_photon(rng, n_cycles, m, tof, sigma, bg, window, bin_s, reset):
    """Independent sampler: every signal photon drawn, the first background arrival drawn
    from its exponential; the first detection after the start of sensitivity wins."""
    start = -reset
    k = rng.poisson(m, n_cycles)
    cyc = np.repeat(np.arange(n_cycles), k)
    t = rng.normal(tof, sigma, cyc.size)
    keep = t >= start
    first_sig = np.full(n_cycles, np.inf)
    np.minimum.at(first_sig, cyc[keep], t[keep])
    first_bg = start + rng.exponential(1 / bg, n_cycles) if bg > 0 else np.inf
    first = np.minimum(first_sig, first_bg)
    n_bins = int(round(window / bin_s))
    idx = np.where(first < 0, n_bins, np.where(first >= window, n_bins + 1,
                                               np.floor(first / bin_s)))
    return np.bincount(idx.astype(np.int64), minlength=n_bins + 2)


@pytest.mark.parametrize("m", [0.01, 0.3, 1.0, 5.0, 10.0])
@pytest.mark.parametrize("sbr", [0.01, 1.0, 100.0])
def test_analytic_pileup_histogram_matches_sampled(m, sbr):
    """Chi-square p > 0.01 at 1e6 cycles (the issue's regimes: M 0.01..10, SBR 0.01..100)."""
    rng = np.random.default_rng(int(m * 1000 + sbr * 7))
    reset = 20e-9
    bg = m / (sbr * WINDOW)  # SBR = signal detections / background detections in the window
    n = 1_000_000
    obs = photon_by_photon(rng, n, m, TOF, SIGMA, bg, WINDOW, BIN, reset)
    h = first_photon_histogram(m, TOF, SIGMA, bg, WINDOW, BIN, reset)
    p = np.concatenate([h.p, [h.p_reset, h.p_none]])
    exp = n * p / p.sum()
    # merge sparse categories (expected < 5) into one, as the chi-square test needs
    small = exp < 5
    obs_m = np.concatenate([obs[~small], [obs[small].sum()]])
    exp_m = np.concatenate([exp[~small], [exp[small].sum()]])
    if exp_m[-1] == 0:
        obs_m, exp_m = obs_m[:-1], exp_m[:-1]
        assert obs[small].sum() == 0
    res = stats.chisquare(obs_m, exp_m)
    assert res.pvalue > 0.01, (m, sbr, res)


def test_probabilities_sum_to_one_and_peak_shifts_early():
    h = first_photon_histogram(2.0, TOF, SIGMA, 1e6, WINDOW, BIN, 10e-9)
    assert h.p.sum() + h.p_reset + h.p_none == pytest.approx(1.0, abs=1e-12)
    centre = np.argmax(h.p) * BIN + BIN / 2
    assert centre < TOF  # pile-up pulls the peak early (eq. 2.6, Figure 2.2)


@pytest.mark.parametrize("case", [
    dict(m=1.0, tof=-40 * SIGMA, bg=1e6),               # pulse 40 sigma before the window
    dict(m=1.0, tof=WINDOW + 40 * SIGMA, bg=1e6),       # 40 sigma after it
    dict(m=10.0, tof=TOF, bg=0.0),                      # saturated pile-up, no background
    dict(m=1.0, tof=TOF, bg=1000 * 1.0 / WINDOW),       # background 1000x the signal
    dict(m=0.0, tof=TOF, bg=1e7),                       # zero signal
    dict(m=0.0, tof=TOF, bg=0.0),                       # nothing at all
    dict(m=1e3, tof=TOF, bg=1e12),                      # exp(-lambda) underflows
])
def test_hard_cases_are_finite_nonnegative_and_normalised(case):
    h = first_photon_histogram(case["m"], case["tof"], SIGMA, case["bg"], WINDOW, BIN, 5e-9)
    for arr in (h.p, h.p_reset, h.p_none):
        assert np.all(np.isfinite(arr)) and np.all(arr >= 0)
    assert np.all(np.isfinite(h.log_p) | (h.log_p == -np.inf))
    total = h.p.sum() + h.p_reset + h.p_none
    assert total <= 1 + 1e-12 and total == pytest.approx(1.0, abs=1e-9)


def test_far_tail_bins_keep_relative_precision():
    # A bin 40..41 sigma into the upper tail holds ~e^-805 of the pulse: far below the
    # smallest double, but its logarithm is exact. Window from the pulse centre, so
    # L(a) = M * (Phi(40) - Phi(0)) ~ M / 2.
    m = 1.0
    h = first_photon_histogram(m, 0.0, 1e-12, 0.0, 80e-12, 1e-12)
    tail = stats.norm.logsf(40.0) + np.log1p(-np.exp(stats.norm.logsf(41.0)
                                                      - stats.norm.logsf(40.0)))
    expected = -m * (0.5 - stats.norm.sf(40.0)) + np.log(m) + tail
    assert h.log_p[40] == pytest.approx(expected, rel=1e-12)
    assert h.p[40] == 0.0 and np.isfinite(h.log_p[40])


def test_broadcasting_over_parameters():
    h = first_photon_histogram(np.array([0.1, 1.0]), np.array([[20e-9], [60e-9]]), SIGMA,
                               1e6, WINDOW, BIN)
    assert h.p.shape == (2, 2, 400)
    single = first_photon_histogram(1.0, 60e-9, SIGMA, 1e6, WINDOW, BIN)
    np.testing.assert_allclose(h.p[1, 1], single.p, rtol=1e-12)


def test_bad_inputs_are_clear_errors():
    with pytest.raises(ValueError, match="m_signal must be finite and >= 0"):
        first_photon_histogram(np.nan, TOF, SIGMA, 0, WINDOW, BIN)
    with pytest.raises(ValueError, match="sigma_s must be finite and > 0"):
        first_photon_histogram(1, TOF, 0.0, 0, WINDOW, BIN)
    with pytest.raises(ValueError, match="bg_rate_hz"):
        first_photon_histogram(1, TOF, SIGMA, np.inf, WINDOW, BIN)


def test_low_intensity_limit_is_niclass():
    """Without pile-up (M, background -> 0) eq. 2.12 reduces to Niclass's eq. 2.7-2.9."""
    n = 1e6
    ours = first_photon_histogram(1e-5, TOF, SIGMA, 1e2, WINDOW, BIN).counts(n)
    theirs = niclass_histogram(n, 1e-5, TOF, SIGMA, 1e2, WINDOW, BIN)
    np.testing.assert_allclose(ours, theirs, rtol=1e-4)


def test_density_integrates_to_the_bin_probabilities():
    t = np.linspace(0, WINDOW, 400_001)
    dens = detected_power_shape(t, 2.0, TOF, SIGMA, 1e7)
    h = first_photon_histogram(2.0, TOF, SIGMA, 1e7, WINDOW, BIN)
    cdf = np.concatenate([[0], np.cumsum((dens[1:] + dens[:-1]) / 2 * np.diff(t))])
    np.testing.assert_allclose(np.diff(cdf[::1000]), h.p, rtol=1e-5, atol=1e-12)


def test_peak_shift_solves_the_derivative_of_eq_2_4():
    m = np.array([0.01, 0.1, 1.0, 5.0])
    x = peak_shift(m)
    np.testing.assert_allclose(x + m / np.sqrt(2 * np.pi) * np.exp(-x * x / 2), 0, atol=1e-12)
    # and it is the maximum of the eq. 2.12 density without background
    t = np.linspace(-5, 5, 200_001)
    for mi, xi in zip(m, x, strict=True):
        assert t[np.argmax(detected_power_shape(t, mi, 0.0, 1.0))] == pytest.approx(xi,
                                                                                  abs=1e-4)
    assert np.all(np.diff(x) < 0)  # more pile-up, earlier peak (Figure 2.2)


def test_crlb_limits():
    base = dict(n_cycles=10_000, tof_s=TOF, sigma_s=SIGMA, window_s=WINDOW, bin_s=1e-12)
    # photon-starving, no background, fine bins: sigma / sqrt(detected signal)
    s = crlb_tof(m_signal=0.01, bg_rate_hz=0.0, **base)
    assert s == pytest.approx(SIGMA / np.sqrt(100), rel=0.01)
    # background only makes it worse; coarser bins make it worse
    assert crlb_tof(m_signal=0.01, bg_rate_hz=1e7, **base) > s
    coarse = dict(base, bin_s=0.4e-9)
    assert crlb_tof(m_signal=0.01, bg_rate_hz=0.0, **coarse) > s
    # saturated pile-up (M = 5) is finite; no signal means no information
    assert np.isfinite(crlb_tof(m_signal=5.0, bg_rate_hz=1e6, **base))
    assert crlb_tof(m_signal=0.0, bg_rate_hz=1e6, **base) == np.inf


def test_crlb_matches_numerical_fisher_information():
    args = dict(m_signal=1.5, sigma_s=SIGMA, bg_rate_hz=2e7, window_s=WINDOW, bin_s=BIN,
                reset_s=10e-9)
    eps = 1e-13
    hp = first_photon_histogram(tof_s=TOF + eps, **args)
    hm = first_photon_histogram(tof_s=TOF - eps, **args)
    h0 = first_photon_histogram(tof_s=TOF, **args)
    p0 = np.concatenate([h0.p, [h0.p_reset, h0.p_none]])
    dp = (np.concatenate([hp.p, [hp.p_reset, hp.p_none]])
          - np.concatenate([hm.p, [hm.p_reset, hm.p_none]])) / (2 * eps)
    info = np.sum(np.where(p0 > 0, dp * dp / np.where(p0 > 0, p0, 1), 0))
    assert crlb_tof(1000, tof_s=TOF, **args) == pytest.approx(1 / np.sqrt(1000 * info),
                                                              rel=1e-4)


@pytest.mark.parametrize("m", [0.05, 1.5, 5.0])
def test_crlb_with_the_amplitude_unknown_matches_the_numerical_2x2_fisher(m):
    """M estimated alongside the time: (I^-1)_tt of the (TOF, M) Fisher information, each
    derivative of the multinomial taken numerically."""
    args = dict(sigma_s=SIGMA, bg_rate_hz=2e7, window_s=WINDOW, bin_s=BIN, reset_s=10e-9)

    def probs(tof, mm):
        h = first_photon_histogram(m_signal=mm, tof_s=tof, **args)
        return np.concatenate([h.p, [h.p_reset, h.p_none]])

    p0 = probs(TOF, m)
    dt = (probs(TOF + 1e-13, m) - probs(TOF - 1e-13, m)) / 2e-13
    dm = (probs(TOF, m * (1 + 1e-6)) - probs(TOF, m * (1 - 1e-6))) / (2e-6 * m)
    w = np.where(p0 > 0, 1 / np.where(p0 > 0, p0, 1), 0)
    fish = np.array([[np.sum(a * b * w) for b in (dt, dm)] for a in (dt, dm)])
    want = np.sqrt(np.linalg.inv(fish)[0, 0] / 1000)
    got = crlb_tof(1000, m, TOF, amplitude_known=False, **args)
    assert got == pytest.approx(want, rel=1e-3)
    known = crlb_tof(1000, m, TOF, **args)
    assert got >= known * (1 - 1e-9)  # a nuisance parameter never helps
    if m >= 5:  # under saturated pile-up the edge's shape gives M away: much larger
        assert got > 1.5 * known


def test_centroid_sigma_eq_2_11_limits():
    # SBR -> infinity and a wide centroid window: sigma_s / sqrt(signal counts)
    s = centroid_sigma(n_cycles=1e4, signal_rate_hz=1e6, sbr=1e12, t0_s=1e-6, bin_s=BIN,
                       sigma_s=SIGMA, n_hw=50)
    assert s == pytest.approx(SIGMA / np.sqrt(1e4 * 1e-6 * 1e6), rel=1e-6)
    worse = centroid_sigma(1e4, 1e6, 0.1, 1e-6, BIN, SIGMA, 50)
    assert worse > s


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-60.0, 60.0, allow_nan=False), min_size=2, max_size=30, unique=True))
def test_log_phi_intervals_are_log_phi_interval_on_consecutive_edges(z):
    """Every edge's log_ndtr once gives the same numbers, to the bit, as each interval
    alone, in both tails (where the log is all that survives) and across the centre."""
    z = np.sort(np.array(z))
    got = log_phi_intervals(z)
    want = log_phi_interval(z[:-1], z[1:])
    np.testing.assert_array_equal(got, want)
    zz = np.stack([z, z + 0.5], 1)          # edges along the first axis, more axes after
    np.testing.assert_array_equal(log_phi_intervals(zz)[:, 1],
                                  log_phi_interval(zz[:-1, 1], zz[1:, 1]))
