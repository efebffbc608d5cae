"""Detection by the scan statistic (issue 34.9), tried from outside: histograms from an
independent generator (1 024 bins of 80 ps, a Gaussian pulse of 440 ps FWHM, S signal
photons, B background photons over the window), the false-alarm rate against a binomial
bound of p_fa, and the detection probability against the plain test "most counts in any
6-bin window" at a threshold measured on background alone."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.special import ndtr

from stages.ranging import Histograms, estimate, numba
from stages.ranging.detection import _detect, scan_bins, scan_pvalue, scan_threshold

N, BIN, FWHM = 1024, 80e-12, 440e-12
SIG = FWHM / (2 * np.sqrt(2 * np.log(2)))


def histograms(rng, n, s, b, cycles=None):
    """n histograms: a pulse of s photons (Poisson) at a uniform time away from the
    ends, b background photons (Poisson) spread over the window; ``cycles`` None is a
    file without cycles (the stand-in: 1e12 x the row's total, as the generic reader)."""
    e = np.arange(N + 1) * BIN
    t0 = rng.uniform(100 * BIN, (N - 100) * BIN, n)
    mu = s * np.diff(ndtr((e[None, :] - t0[:, None]) / SIG), axis=1) + b / N
    c = rng.poisson(mu).astype(np.float64)
    cyc = (np.maximum(c.sum(1), 1) * 1e12 if cycles is None else np.full(n, float(cycles)))
    return Histograms(c, np.broadcast_to(e, (n, N + 1)).copy(), cyc,
                      np.ones_like(c, bool)), t0


def window_max(c, k=6):
    cs = np.concatenate([np.zeros((c.shape[0], 1)), np.cumsum(c, axis=1)], axis=1)
    return (cs[:, k:] - cs[:, :-k]).max(axis=1)


def measured_threshold(rng, b, p_fa=1e-3, n=20_000):
    """The least count of the 6-bin window test whose rate on background alone is at most
    p_fa (measured, as the issue's reference test)."""
    m0 = window_max(histograms(rng, n, 0, b)[0].counts)
    return next(c for c in range(1, 1000) if np.mean(m0 >= c) <= p_fa)


@pytest.mark.parametrize("mu, k, m", [(0.05, 6, 1019), (0.3, 7, 1018), (3.0, 7, 400),
                                      (40.0, 3, 3000), (0.2, 1, 1000)])
def test_scan_bound_holds_and_is_tight(mu, k, m):
    """The scan p-value bounds the simulated probability that background alone reaches
    the threshold in some window, and is within 30 % of it (p_fa 1e-2: measurable)."""
    rng = np.random.default_rng(int(mu * 100) + k)
    n_bins = m + k - 1
    x = rng.poisson(mu / k, (20_000, n_bins))
    sim = window_max(x, k)
    thr = scan_threshold(mu, k, m, 1e-2)
    rate = np.mean(sim >= thr)
    bound = float(scan_pvalue(np.array([thr]), np.array([mu]), k, np.array([m]))[0])
    assert rate <= bound + 3 * np.sqrt(bound / 20_000)
    assert bound <= 1e-2
    # one count lower is above p_fa, and the bound is not loose: the simulated rate is
    # at least 70 % of it where it can be measured
    low = float(scan_pvalue(np.array([thr - 1]), np.array([mu]), k, np.array([m]))[0])
    assert low > 1e-2 or thr - 1 <= 0
    if bound > 2e-3:
        assert rate >= 0.7 * bound - 3 * np.sqrt(bound / 20_000)


@pytest.mark.skipif(numba is None, reason="numba not installed")
def test_compiled_scan_agrees_with_numpy():
    from stages.ranging.detection import _scan_p
    from stages.ranging.fast import _fast_args, _fast_numba

    t = np.arange(0, 60.0)
    for mu, k, m in [(0.01, 7, 1000.0), (3.3, 7, 1000.0), (30.0, 2, 50.0), (900.0, 9, 4000.0)]:
        want = scan_pvalue(t, np.full(t.size, mu), k, np.full(t.size, m))
        got = np.array([_scan_p(x, mu, k, m) for x in t])
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-300)
    rng = np.random.default_rng(3)
    for s, b, cyc in [(10, 50, 1e5), (3, 2, None), (1000, 5000, 3000), (0, 0.5, None)]:
        h, _ = histograms(rng, 1500, s, b, cyc)
        a, _ = _fast_args(h, SIG, 1e-3)
        t_s, peak, _, bg, _, _ = _fast_numba(*a)
        for p_fa in (1e-3, 0.05, 0.5):
            np.testing.assert_array_equal(
                _detect(h, peak, bg, p_fa, t_s, SIG, compiled=True),
                _detect(h, peak, bg, p_fa, t_s, SIG, compiled=False))


@pytest.mark.parametrize("estimator", ["fast", "ml", "matched", "centroid", "gaussfit"])
@pytest.mark.parametrize("b", [0.1, 2.0, 50.0, 1000.0])
@pytest.mark.parametrize("cycles", [None, 1e5])
def test_false_alarms_within_the_binomial_bound(estimator, b, cycles):
    """Background-only histograms of the independent generator at p_fa 0.05 and 1e-3:
    histograms called detected within a 3-sigma binomial bound of p_fa."""
    rng = np.random.default_rng(int(b * 10) + (cycles is None))
    n = 300 if estimator == "gaussfit" else 2000
    h, _ = histograms(rng, n, 0, b, cycles)
    for p_fa in (0.05, 1e-3):
        r = estimate(h, SIG, estimator, p_fa)
        bound = n * p_fa + 3 * np.sqrt(n * p_fa * (1 - p_fa)) + 1
        assert int(np.sum(r.detected)) <= bound, (p_fa, int(np.sum(r.detected)))


@pytest.mark.parametrize("s, b", [(10, 2), (10, 50), (5, 10), (2, 2)])
@pytest.mark.parametrize("estimator", ["fast", "ml"])
def test_detection_probability_against_the_window_test(s, b, estimator):
    """The issue's grid: P_d at p_fa 1e-3 (a detection within 2 FWHM of the truth) of ml
    and fast, cycles given or not, against the 6-bin window test whose threshold is
    measured on background alone with the background known (an oracle the estimators do
    not have: they estimate it from the histogram): within 2.5 points of it on the same
    histograms (measured: -1.2 to +0.8), where the single-bin test was 45-75 points below."""
    rng = np.random.default_rng(s * 100 + b)
    thr = measured_threshold(rng, b)
    for cycles in (None, 1e5):
        h, t0 = histograms(rng, 3000, s, b, cycles)
        ref = np.mean(window_max(h.counts) >= thr)
        r = estimate(h, SIG, estimator, 1e-3)
        pd = np.mean(r.detected & (np.abs(r.t_s - t0) < 2 * FWHM))
        assert pd >= ref - 0.025, (cycles, pd, ref)


def test_window_is_three_sigma():
    assert scan_bins(SIG, BIN) == 7 and scan_bins(0.2e-9, 0.2e-9) == 3
    assert scan_bins(1e-12, 1e-9) == 1


def tailed_response(tail=0.08, bin_s=BIN):
    """A response as measured on a SPAD: a Gaussian core and an exponential tail."""
    from stages.ranging.irf import Response

    x = np.arange(40)
    d = np.exp(-0.5 * ((x - 6) / (SIG / bin_s)) ** 2) + tail * np.where(
        x > 6, np.exp(-(x - 6) / 6.0), 0.0)
    return Response(d, bin_s, "test: gaussian core and tail")


@pytest.mark.parametrize("b", [0.1 * N, 2.0, 20.0 * N])
@pytest.mark.parametrize("cycles", [None, pytest.param(1e6, marks=pytest.mark.slow)])
def test_measured_response_false_alarms_within_the_bound(b, cycles):
    """ml and matched with a measured response (the calibrate-distance path) on
    background-only histograms: within the binomial bound at p_fa 1e-3, 1e-2 and 0.05
    (ml called 21, 422 and 434 of 2 000 at 0.1 counts a bin, issue 34.4; 400 here); the background
    it reports is the gate's (median within 10 % of the truth, where it was 0)."""
    from stages.ranging.irf import fit_response

    rng = np.random.default_rng(int(b) + 5)
    n = 400
    h, _ = histograms(rng, n, 0, b, cycles)
    for est in ("ml", "matched"):
        for p_fa in (1e-3, 1e-2, 0.05):
            r = fit_response(h, tailed_response(), est, p_fa)
            bound = n * p_fa + 3 * np.sqrt(n * p_fa * (1 - p_fa)) + 1
            assert int(np.sum(r.detected)) <= bound, (est, p_fa, int(np.sum(r.detected)))
        if b >= N:
            assert abs(np.median(r.background_per_bin) / (b / N) - 1) < 0.1


def test_measured_response_detects_what_the_gaussian_does():
    """Returns of 10 photons over 0.05 counts a bin: ml with the response measured (the
    generator's, no tail) detects as many as fast with the Gaussian (within 3 points)."""
    from stages.ranging.irf import fit_response

    rng = np.random.default_rng(8)
    h, t0 = histograms(rng, 400, 10, 50, None)
    a = fit_response(h, tailed_response(0.0), "ml", 1e-3)
    g = estimate(h, SIG, "fast", 1e-3)
    assert np.mean(a.detected) >= np.mean(g.detected) - 0.03 > 0.8


def test_a_bin_of_1e12_counts_is_a_return_with_a_sane_sigma():
    """Issue 34.6: every estimator detects a bin of 1e12 counts, in that bin, with a
    sigma below the response's (gaussfit's covariance gave 8.7-252 m)."""
    rng = np.random.default_rng(0)
    e = np.arange(401) * BIN
    c = rng.poisson(1.0, (3, 400)).astype(np.float64)
    c[:, 200] += 1e12
    h = Histograms(c, np.broadcast_to(e, (3, 401)).copy(), c.sum(1) * 1e12,
                   np.ones(c.shape, bool))
    for name in ("fast", "ml", "matched", "centroid", "gaussfit"):
        r = estimate(h, SIG, name, 1e-3)
        assert r.detected.all(), name
        assert np.all(np.abs(r.t_s - 200.5 * BIN) < BIN), name
        assert np.all(r.sigma_s <= SIG), (name, r.sigma_s)


def test_a_return_beyond_the_window_is_not_placed_inside_it_unflagged():
    """Issue 34.6: a return centred 1.5 sigma past the last bin: fast and ml withdraw it
    (outside the window), the others flag it at the window's edge."""
    rng = np.random.default_rng(1)
    e = np.arange(401) * BIN
    t0 = 400 * BIN + 1.5 * SIG
    c = rng.poisson(2000 * np.diff(ndtr((e - t0) / SIG)) + 0.5, (20, 400)).astype(float)
    h = Histograms(c, np.broadcast_to(e, (20, 401)).copy(), c.sum(1) * 1e12,
                   np.ones(c.shape, bool))
    for name in ("fast", "ml", "matched", "centroid", "gaussfit"):
        r = estimate(h, SIG, name, 1e-3)
        assert np.all(~r.detected | (r.flag != "")), name
