"""Several returns a pixel with a measured, long-tailed instrument response
(stages/ranging/multi_irf.py): a return's tail is subtracted, not found as a surface; a
second surface inside it is still found; background alone stays within p_fa.

The histograms here are drawn from an exponentially modified Gaussian (a SPAD's
diffusion tail) integrated over each bin with scipy, first photon by first photon
(sequential binomials over the cycles still at risk), not by the code under test."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from stages.ranging import Histograms, estimate_returns
from stages.ranging.irf import Response, response_from_returns

N_BINS, BIN = 128, 100e-12
SIG_BINS, TAU_BINS = 0.7, 6.0          # a 70 ps core, a 600 ps tail
CYCLES = 2_000_000


def _shape(t0_bins):
    """Each pixel's bin-integrated EMG (rows sum to the part inside the window)."""
    e = np.arange(N_BINS + 1)[None, :] - np.asarray(t0_bins)[:, None]
    cdf = stats.exponnorm.cdf(e, TAU_BINS / SIG_BINS, scale=SIG_BINS)
    return np.diff(cdf, axis=1)


def _draw(rng, signals, t0s, bg_per_bin, n_pix):
    """First-photon histograms of returns ``signals`` (counts) at ``t0s`` (bins, each
    (n_pix,)) over a flat background."""
    lam = np.full((n_pix, N_BINS), bg_per_bin / CYCLES)
    for s, t in zip(signals, t0s, strict=True):
        lam += s / CYCLES * _shape(t)
    counts = np.empty((n_pix, N_BINS))
    risk = np.full(n_pix, CYCLES, np.int64)
    for j in range(N_BINS):
        counts[:, j] = rng.binomial(risk, -np.expm1(-lam[:, j]))
        risk -= counts[:, j].astype(np.int64)
    edges = np.tile(np.arange(N_BINS + 1) * BIN, (n_pix, 1))
    return Histograms(counts, edges, np.full(n_pix, float(CYCLES)), np.ones(counts.shape, bool))


@pytest.fixture(scope="module")
def response():
    """The response measured on 300 single returns (each pixel's ml time aligned)."""
    rng = np.random.default_rng(11)
    h = _draw(rng, [50_000], [rng.uniform(20, 40, 300)], 2.0, 300)
    first = estimate_returns(h, SIG_BINS * BIN, "ml", 1e-3, 1)
    return response_from_returns(h, np.where(first.detected, first.t_s, np.nan), "EMG")


def test_a_response_measured_on_the_returns_is_their_shape(response):
    """Averaged over the returns, the EMG's own bins (mode aligned): within 12 % of the mode
    over the core (the alignment by fractions of a bin smooths it a little) and 5 % over the
    tail's first 20 bins; its error at least the floor."""
    truth = _shape(np.array([30.0]))[0]
    k = int(np.argmax(truth))
    d = response.density
    m = response.mode
    core, tail = np.arange(-2, 3), np.arange(3, 20)
    np.testing.assert_allclose(d[m + core] / d[m], truth[k + core] / truth[k], atol=0.12)
    np.testing.assert_allclose(d[m + tail] / d[m], truth[k + tail] / truth[k], atol=0.05)
    assert response.error is not None and (response.error >= 0.2).all()


def test_a_long_tail_is_not_a_surface(response):
    """One return of 20 000 counts with a 600 ps tail, 400 pixels: the Gaussian masks find
    the tail as further returns; the measured response, subtracted tail and all, finds
    none beyond p_fa's share (the first return unchanged where it has no company)."""
    rng = np.random.default_rng(5)
    h = _draw(rng, [20_000], [rng.uniform(20, 40, 400)], 2.0, 400)
    gauss = estimate_returns(h, SIG_BINS * BIN, "ml", 1e-3, 3)
    assert ((gauss.return_index > 0) & gauss.detected).sum() > 200
    first = estimate_returns(h, SIG_BINS * BIN, "ml", 1e-3, 1)
    est = estimate_returns(h, SIG_BINS * BIN, "ml", 1e-3, 3, response=response)
    extra = ((est.return_index > 0) & est.detected).sum()
    assert extra <= stats.binom.ppf(0.999, 400, 1e-3)
    alone = np.bincount(est.pixel[est.detected], minlength=400) <= 1
    row0 = est.return_index == 0
    np.testing.assert_array_equal(est.t_s[row0][alone], first.t_s[alone])


@pytest.mark.parametrize("bg", [0.01, 1.0, 30.0])
def test_background_alone_stays_within_p_fa(response, bg):
    """2 000 background-only pixels at p_fa 1e-2: the share with any detected return is
    what one test allows (the first must fire before a second is searched)."""
    rng = np.random.default_rng(int(bg * 100) + 1)
    n = 2000
    h = _draw(rng, [], [], bg, n)
    est = estimate_returns(h, SIG_BINS * BIN, "ml", 1e-2, 3, response=response)
    pixels = np.unique(est.pixel[est.detected]).size
    assert pixels <= stats.binom.ppf(0.999, n, 1e-2)


@pytest.mark.parametrize("sep_widths, share, total", [(1.5, 0.3, 4000), (3.0, 0.1, 4000),
                                                      (3.0, 0.3, 1000)])
def test_a_second_surface_in_the_first_ones_tail_is_found(response, sep_widths, share, total):
    """Two returns of ``total`` counts, the later one ``share`` of them and ``sep_widths``
    FWHMs of the response behind (1.5: 9 bins, inside the first's tail, which still holds
    a fifth of its height there): both found in 90 % of the pixels, no third, each within
    4 of its sigmas (or 0.3 bin) of where ml times such a return alone."""
    from stages.ranging.irf import _fwhm_bins

    rng = np.random.default_rng(int(sep_widths * 10 + share * 100))
    n = 200
    sep_bins = sep_widths * _fwhm_bins(response)
    t1 = rng.uniform(20, 40, n)
    h = _draw(rng, [total * (1 - share), total * share], [t1, t1 + sep_bins], 1.0, n)
    est = estimate_returns(h, SIG_BINS * BIN, "ml", 1e-3, 3, response=response)
    # where ml puts an EMG return's time, each return drawn alone
    offset = [float(np.median(estimate_returns(
        _draw(np.random.default_rng(1), [total * x], [t], 1.0, n), SIG_BINS * BIN, "ml",
        1e-3, 1).t_s - t * BIN)) for x, t in ((1 - share, t1), (share, t1 + sep_bins))]
    per_pixel = np.bincount(est.pixel[est.detected], minlength=n)
    assert (per_pixel <= 2).all()
    both = 0
    for p in np.flatnonzero(per_pixel == 2):
        rows = (est.pixel == p) & est.detected
        o = np.argsort(est.t_s[rows])
        err = np.abs(est.t_s[rows][o] - (np.array([t1[p], t1[p] + sep_bins]) * BIN + offset))
        both += bool((err < np.maximum(4 * est.sigma_s[rows][o], 0.3 * BIN)).all())
    assert both >= 0.9 * n


def test_a_response_error_is_checked():
    with pytest.raises(ValueError, match="error"):
        Response(np.ones(5), 1e-10, "x", error=np.ones(4))


@settings(max_examples=40, deadline=None)
@given(st.lists(st.lists(st.integers(0, 50_000), min_size=24, max_size=24), min_size=1,
                max_size=4),
       st.sampled_from([None, 0.0, 10.0, 1e7]), st.sampled_from(["ml", "fast", "matched"]),
       st.floats(1e-6, 0.5), st.integers(1, 4))
def test_whatever_it_is_given_every_detected_return_is_finite(response, rows, cycles, est,
                                                              p_fa, k):
    """Any counts (ragged light, saturated bins, cycles missing, zero or fewer than the
    counts), any estimator, p_fa and K: no crash; every detected row has a finite time and
    a positive finite sigma; at most K returns a pixel; a pixel without counts nothing."""
    c = np.asarray(rows, float)
    n = c.shape[0]
    cyc = np.full(n, 1e12 if cycles is None else cycles)
    short = Response(response.density[response.mode - 4:response.mode + 20], BIN, "short",
                     error=response.error[response.mode - 4:response.mode + 20])
    h = Histograms(c, np.tile(np.arange(25) * BIN, (n, 1)), cyc, np.ones(c.shape, bool))
    r = estimate_returns(h, SIG_BINS * BIN, est, p_fa, k, response=short)
    det = np.asarray(r.detected, bool)
    assert np.isfinite(r.t_s[det]).all() and (np.asarray(r.sigma_s)[det] > 0).all()
    assert np.isfinite(np.asarray(r.sigma_s)[det]).all()
    assert np.bincount(r.pixel, minlength=n).max() <= k
    assert not det[np.isin(r.pixel, np.flatnonzero(c.sum(axis=1) == 0))].any()


def _fit_every_bin(y, valid, gain, known, kerr, response, centre):
    """The search's fit as it was written first, over every bin (the weights 0 outside
    the span around ``centre``): the reference of the fit over its window of bins."""
    from stages.ranging import multi_irf as mi

    n_pix, n = y.shape
    rows = np.arange(n_pix)
    lo, hi = response.span
    shifts = centre[:, None] + mi._OFF[None, :]
    models = response.models(shifts.ravel(), n).reshape(n_pix, mi._OFF.size, n)
    kk = np.arange(n)[None, :]
    sel = (valid & (kk >= centre[:, None] - lo) & (kk <= centre[:, None] + hi))[:, None, :]
    r, yy, kn = (y - known)[:, None, :], y[:, None, :], known[:, None, :]
    gg, ke = gain[:, None, :], kerr[:, None, :]
    wts = np.where(sel, 1.0 / mi._variance(yy, kn, ke, gg), 0.0)
    for _ in range(3):
        a, b = mi._solve(models, r, wts)
        fit = np.maximum(a, 0)[..., None] * models + np.maximum(b, 0)[..., None]
        wts = np.where(sel, 1.0 / mi._variance(yy, kn, ke, gg, fit), 0.0)
    chi2 = (wts * (r - fit) ** 2).sum(-1)
    j = np.clip(np.argmin(chi2, axis=1), 1, mi._OFF.size - 2)
    s_m, s_0, s_p = chi2[rows, j - 1], chi2[rows, j], chi2[rows, j + 1]
    curv = s_m - 2 * s_0 + s_p
    frac = np.clip(np.where(curv > 0, 0.5 * (s_m - s_p) / np.where(curv > 0, curv, 1.0),
                            0.0), -1.0, 1.0)
    sigma = np.where(curv > 0, np.sqrt(2.0 / np.where(curv > 0, curv, 1.0)) * mi._STEP, np.inf)
    return (shifts[rows, j] + frac * mi._STEP, np.maximum(a[rows, j], 0.0),
            np.maximum(b[rows, j], 0.0), sigma)


@pytest.mark.parametrize("pad", [0, 72])
def test_the_fit_over_its_window_is_the_fit_over_every_bin(response, pad):
    """The search fits each return on a window of whole 8-bin blocks around it: on 128
    bins (one block of numpy's pairwise sums) the same numbers bit for bit as over every
    bin; on 200 (two blocks, a window may straddle them) within the sums' last bits."""
    from stages.ranging import multi_irf as mi

    rng = np.random.default_rng(3)
    n_pix = 200
    t0 = rng.uniform(-2, N_BINS - 10, n_pix)  # near both edges too
    h = _draw(rng, [20_000, 6_000], [t0, t0 + rng.uniform(3, 12, n_pix)], 2.0, n_pix)
    counts = np.hstack([h.counts, rng.poisson(2.0, (n_pix, pad))])
    h = Histograms(counts, np.broadcast_to(np.arange(N_BINS + pad + 1) * BIN,
                                           (n_pix, N_BINS + pad + 1)).copy(),
                   h.cycles, np.ones(counts.shape, bool))
    y, valid = mi._corrected(h), h.valid
    gain = np.maximum(h.cycles[:, None] / np.maximum(h.at_risk, 1.0), 1.0)
    zero = np.zeros_like(y)
    centre = mi._coarse(y, valid, gain, zero, zero, response)
    first = mi._fit(y, valid, gain, zero, zero, response, centre)
    known, kerr = mi._model(response, first[0], first[1], y.shape[1])
    for args in ((zero, zero, centre), (known, kerr, np.clip(centre + 6, 0, None))):
        got = mi._fit(y, valid, gain, *args[:2], response, args[2])
        want = _fit_every_bin(y, valid, gain, *args[:2], response, args[2])
        for g, w in zip(got, want, strict=True):
            if pad:
                np.testing.assert_allclose(g, w, rtol=1e-11, atol=0)
            else:
                np.testing.assert_array_equal(g, w)
