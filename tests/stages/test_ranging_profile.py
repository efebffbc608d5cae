"""The per-pixel detection under a background that is not flat in time (a batch of rows
on one bin axis): background alone under e^-t, e^-3t and a ramp to 4x holds p_fa, a flat
batch is ranged exactly as before, a return under a falling background is still found.
Histograms from a generator of their own (1 024 bins of 80 ps, a pulse of 440 ps FWHM)."""

from __future__ import annotations

import importlib
from unittest import mock

import numpy as np
import pytest
from scipy.special import ndtr
from scipy.stats import binom

import stages.ranging.detection as det
from stages.ranging import Histograms, estimate

# (the package's ``fast`` is the function)
fast_mod = importlib.import_module("stages.ranging.fast")

N, BIN, FWHM = 1024, 80e-12, 440e-12
SIG = FWHM / (2 * np.sqrt(2 * np.log(2)))
J = np.arange(N)
SHAPES = {"flat": np.ones(N), "e^-t": np.exp(-J / N), "e^-3t": np.exp(-3 * J / N),
          "ramp to 4x": 1 + 3 * J / N}
P_FA = 1e-3


def batch(rng, n, b, shape, s=0.0, t0=None):
    """n rows of b background photons (Poisson, the profile ``shape``) and a pulse of s
    photons at ``t0`` (seconds, one a row), on one bin axis, without pile-up."""
    e = np.arange(N + 1) * BIN
    mu = np.broadcast_to(b * shape / shape.sum(), (n, N)).copy()
    if np.any(s):
        pulse = np.diff(ndtr((e[None, :] - np.asarray(t0)[:, None]) / SIG), axis=1)
        mu += np.asarray(s, np.float64)[:, None] * pulse
    c = rng.poisson(mu).astype(np.float64)
    return Histograms(c, np.broadcast_to(e, (n, N + 1)).copy(), np.full(n, 1e9),
                      np.ones_like(c, bool))


def flat_model():
    """The detection as it was: no profile."""
    return mock.patch.multiple(det, time_profile=lambda h: None), \
        mock.patch.multiple(fast_mod, time_profile=lambda h: None)


@pytest.mark.parametrize("shape", ["e^-t", "e^-3t", "ramp to 4x"])
@pytest.mark.parametrize("b", [50, 200])
def test_background_alone_holds_p_fa(shape, b):
    """Every row background alone: the rows detected by fast, ml and matched at most the
    binomial bound of p_fa (1e-6 of a false failure); the flat model exceeds it at e^-3t,
    200 photons (the test can fail)."""
    n = 2048
    h = batch(np.random.default_rng(b + len(shape)), n, b, SHAPES[shape])
    bound = binom.isf(1e-6, n, P_FA)
    assert det.time_profile(h) is not None or shape != "e^-3t"
    for name in ("fast", "ml", "matched"):
        assert estimate(h, SIG, name, P_FA).detected.sum() <= bound, name
    if shape == "e^-3t" and b == 200:
        a, f = flat_model()
        with a, f:
            assert estimate(h, SIG, "fast", P_FA).detected.sum() > bound


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_flat_batch_unchanged(seed):
    """A flat background, with returns in half the rows: no profile, and every output the
    same to the bit as the flat model's."""
    rng = np.random.default_rng(seed)
    n = 1024
    t0 = rng.uniform(100 * BIN, (N - 100) * BIN, n)
    h = batch(rng, n, (10, 50, 200)[seed - 1], SHAPES["flat"], 20.0 * (J[:n] % 2), t0)
    assert det.time_profile(h) is None
    for name in ("fast", "ml", "matched", "centroid"):
        got = estimate(h, SIG, name, P_FA)
        a, f = flat_model()
        with a, f:
            ref = estimate(h, SIG, name, P_FA)
        for k in ("t_s", "sigma_s", "signal_counts", "background_per_bin", "detected"):
            np.testing.assert_array_equal(getattr(got, k), getattr(ref, k), err_msg=name)


@pytest.mark.parametrize("at", [0.1, 0.5, 0.9])
def test_return_under_falling_background_found(at):
    """A return of 30 photons under 200 background photons falling as e^-3t (5x the late
    rate early on) is detected in nearly every row, early, mid-window or late; the empty
    rows of the same batch hold p_fa."""
    rng = np.random.default_rng(int(at * 10))
    n = 1024
    has = J[:n] % 2 == 1
    t0 = np.full(n, at * N * BIN)
    h = batch(rng, n, 200, SHAPES["e^-3t"], 30.0 * has, t0)
    assert det.time_profile(h) is not None
    bound = binom.isf(1e-6, int((~has).sum()), P_FA)
    for name in ("fast", "ml", "matched"):
        e = estimate(h, SIG, name, P_FA)
        assert e.detected[has].mean() > 0.95, name
        assert e.detected[~has].sum() <= bound, name
        assert np.median(np.abs(e.t_s[has] - t0[has])) < SIG, name


def test_profile_follows_the_background():
    """The profile follows e^-3t within a few per cent of its range; rows with different
    edges (a calibrated chip's) get none."""
    h = batch(np.random.default_rng(7), 2048, 200, SHAPES["e^-3t"])
    s = det.time_profile(h)
    want = SHAPES["e^-3t"] / SHAPES["e^-3t"].mean()
    assert np.abs(s - want)[32:-32].max() < 0.1
    e = h.edges_s.copy()
    e[0] *= 1.0001
    assert det.time_profile(Histograms(h.counts, e, h.cycles, h.valid)) is None


@pytest.mark.parametrize("seed", [1, 2])
def test_piled_up_flat_background_is_flat(seed):
    """First-photon histograms of a flat background with 86 % of the cycles stopped
    (the counts fall in time, the rate a cycle at risk does not): no profile, and the
    rows detected within the binomial bound; with e^-3t the same pile-up is not flat."""
    rng = np.random.default_rng(seed)
    n, cycles = 1024, 500
    for shape, flat in (("flat", True), ("e^-3t", False)):
        p = -np.expm1(-(2.0 / N) * SHAPES[shape] / SHAPES[shape].mean())
        surv = np.concatenate([[1.0], np.cumprod(1 - p)])
        first = rng.multinomial(cycles, np.append(surv[:-1] * p, surv[-1]), size=n)
        c = first[:, :-1].astype(np.float64)
        h = Histograms(c, np.broadcast_to(np.arange(N + 1) * BIN, (n, N + 1)).copy(),
                       np.full(n, float(cycles)), np.ones_like(c, bool))
        assert (det.time_profile(h) is None) == flat, shape
        for name in ("fast", "ml", "matched"):
            assert estimate(h, SIG, name, P_FA).detected.sum() <= binom.isf(1e-6, n, P_FA)


def test_masked_bins_and_falling_background():
    """Rows with their first 40 and last 8 bins masked (a gate) under e^-3t: the profile
    is found on the valid bins and the rows hold p_fa."""
    n = 2048
    h = batch(np.random.default_rng(11), n, 200, SHAPES["e^-3t"])
    valid = np.ones_like(h.valid)
    valid[:, :40] = valid[:, -8:] = False
    h = Histograms(h.counts, h.edges_s, h.cycles, valid)
    assert det.time_profile(h) is not None
    for name in ("fast", "ml", "matched"):
        assert estimate(h, SIG, name, P_FA).detected.sum() <= binom.isf(1e-6, n, P_FA)


@pytest.fixture(scope="module")
def measured():
    """A measured response on the same bins: the pulse, 2 million photons."""
    from stages.ranging.irf import response_from_counts

    rng = np.random.default_rng(5)
    t = rng.normal(50 * BIN, SIG, 2_000_000)
    return response_from_counts(np.histogram(t, bins=np.arange(161) * BIN)[0], BIN,
                                "zero-distance capture")


@pytest.mark.parametrize("name", ["matched", "ml"])
def test_measured_response_holds_p_fa(measured, name):
    """The measured-response estimators' detection takes the profile too: background
    alone under e^-3t at 200 photons within the binomial bound, the flat model far above
    it; a flat batch the same to the bit."""
    from stages.ranging.irf import fit_response

    n = 1024
    h = batch(np.random.default_rng(21), n, 200, SHAPES["e^-3t"])
    bound = binom.isf(1e-6, n, P_FA)
    assert fit_response(h, measured, name, P_FA).detected.sum() <= bound
    irf = importlib.import_module("stages.ranging.irf")
    with mock.patch.object(irf, "time_profile", lambda h: None):
        assert fit_response(h, measured, name, P_FA).detected.sum() > bound
    flat = batch(np.random.default_rng(22), n, 50, SHAPES["flat"])
    got = fit_response(flat, measured, name, P_FA)
    with mock.patch.object(irf, "time_profile", lambda h: None):
        ref = fit_response(flat, measured, name, P_FA)
    for k in ("t_s", "sigma_s", "signal_counts", "background_per_bin", "detected"):
        np.testing.assert_array_equal(getattr(got, k), getattr(ref, k))
