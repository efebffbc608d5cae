"""Range estimators on model histograms: accuracy against the CRLB, honesty of sigma, and
the hard cases."""

import numpy as np
import pytest

from stages.models.tcspc import crlb_tof, first_photon_histogram
from stages.ranging import ESTIMATORS, Histograms, estimate

W, B, SG, RESET = 80e-9, 0.2e-9, 0.2e-9, 20e-9


def draw(rng, m, tof, bg, n_cycles=10_000, extra=None):
    """Multinomial first-photon histograms from the exact model (reset peak removed)."""
    tof = np.atleast_1d(tof)
    h = first_photon_histogram(m, tof, SG, bg, W, B, RESET)
    p = np.concatenate([h.p_reset[:, None], h.p, h.p_none[:, None]], 1)
    if extra is not None:  # a second target: mix its histogram in (two returns)
        p = 0.5 * (p + extra)
    d = np.array([rng.multinomial(n_cycles, pi / pi.sum()) for pi in p])
    counts = d[:, 1:-1].astype(float)
    valid = np.ones_like(counts, bool)
    valid[:, :1] = valid[:, -1:] = False
    edges = np.tile(np.arange(counts.shape[1] + 1) * B, (counts.shape[0], 1))
    return Histograms(counts, edges, np.full(len(tof), n_cycles - d[:, 0], float), valid)


@pytest.mark.parametrize("m, sbr, limit", [(0.01, 1.0, 1.2), (0.1, 10.0, 1.2), (1.0, 1.0, 1.2),
                                           (0.05, 0.1, 1.2), (5.0, 10.0, 1.2)])
def test_ml_is_within_1_2_crlb_and_sigma_is_honest(m, sbr, limit):
    """Against the bound of the problem ML solves: time and M both unknown (under pile-up
    at M = 5 that bound is 1.7x the one that pretends M is known)."""
    _against_the_bound("ml", m, sbr, limit, seed=int(m * 1e3 + sbr))


def _against_the_bound(estimator, m, sbr, limit, seed):
    """300 pixels at random times, 10 000 cycles each: RMSE within ``limit`` CRLB (time and
    M both unknown), 2-sigma coverage about 95 %, every pixel detected."""
    rng = np.random.default_rng(seed)
    tof = rng.uniform(10e-9, 70e-9, 300)
    bg = m / (sbr * W)
    h = draw(rng, m, tof, bg)
    r = estimate(h, SG, estimator)
    err = r.t_s - tof
    crlb = np.median(crlb_tof(10_000, m, tof, SG, bg, W, B, RESET, amplitude_known=False))
    assert np.sqrt(np.mean(err ** 2)) < limit * crlb
    assert 0.90 <= np.mean(np.abs(err) < 2 * r.sigma_s) <= 0.99
    assert np.all(r.detected)
    return r, h


def test_pile_up_biases_the_thesis_baseline_but_not_ml():
    rng = np.random.default_rng(5)
    tof = rng.uniform(10e-9, 70e-9, 100)
    h = draw(rng, 5.0, tof, 5.0 / (10 * W))
    assert np.mean(estimate(h, SG, "gaussfit").t_s - tof) < -100e-12  # pulled early
    assert abs(np.mean(estimate(h, SG, "ml").t_s - tof)) < 2e-12


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_no_signal_is_not_detected_and_raises_nothing(estimator):
    rng = np.random.default_rng(1)
    h = draw(rng, 0.0, np.full(50, 40e-9), 1e6)
    r = estimate(h, SG, estimator)
    assert np.mean(r.detected) <= 0.06 and np.all(np.isfinite(r.t_s))


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_one_count_and_an_empty_histogram(estimator):
    counts = np.zeros((2, 400))
    counts[0, 200] = 1.0
    edges = np.tile(np.arange(401) * B, (2, 1))
    h = Histograms(counts, edges, np.array([100.0, 100.0]), np.ones((2, 400), bool))
    r = estimate(h, SG, estimator)
    assert r.t_s.shape == (2,) and not r.detected[1]


@pytest.mark.parametrize("where", [1.5e-9, 78.5e-9])
def test_peak_at_either_window_edge(where):
    rng = np.random.default_rng(3)
    h = draw(rng, 0.3, np.full(40, where), 1e6)
    r = estimate(h, SG, "ml")
    assert np.median(np.abs(r.t_s - where)) < 50e-12 and r.detected.mean() > 0.9


def test_peak_on_the_reset_peak_is_masked_not_reported():
    """A return inside the masked reset-peak codes cannot be seen: no false distance."""
    rng = np.random.default_rng(4)
    h = draw(rng, 0.3, np.full(40, 0.5e-9), 1e6)  # arrival right at the window's start
    v = h.valid.copy()
    v[:, :8] = False  # the reset peak's codes (arrival order: first bins)
    h = Histograms(h.counts, h.edges_s, h.cycles, v)
    r = estimate(h, SG, "ml")
    assert not np.any(np.abs(r.t_s - 0.5e-9) < 0.3e-9)


def test_two_targets_report_the_stronger():
    rng = np.random.default_rng(6)
    far = first_photon_histogram(0.3, 20e-9, SG, 1e6, W, B, RESET)
    p_far = np.concatenate([[far.p_reset], far.p, [far.p_none]])
    h = draw(rng, 0.05, np.full(30, 50e-9), 1e6, extra=p_far[None, :])  # weak near + strong far
    r = estimate(h, SG, "ml")
    assert np.median(np.abs(r.t_s - 20e-9)) < 50e-12


def test_unknown_estimator():
    h = draw(np.random.default_rng(0), 0.1, np.array([40e-9]), 1e6)
    with pytest.raises(ValueError, match="estimator must be one of"):
        estimate(h, SG, "fft")


@pytest.mark.parametrize("name", ["fast", "ml"])
@pytest.mark.parametrize("m", [1.0, 5.0])
def test_compiled_and_numpy_paths_agree(name, m):
    from stages import ranging

    rng = np.random.default_rng(8)
    h = draw(rng, m, rng.uniform(10e-9, 70e-9, 60), m / W)
    fn = getattr(ranging, name)
    a, b = fn(h, SG, compiled=True), fn(h, SG, compiled=False)
    np.testing.assert_allclose(a.t_s, b.t_s, rtol=0, atol=1e-15)  # 1 fs
    np.testing.assert_array_equal(a.detected, b.detected)


@pytest.mark.parametrize("m, sbr, limit", [(0.01, 1.0, 1.3), (0.1, 10.0, 1.3), (1.0, 1.0, 1.3),
                                            (5.0, 10.0, 1.3), (5.0, 100.0, 1.3),
                                            (5.0, 1.0, 2.0)])
def test_fast_estimator_reaches_the_bound_at_any_pile_up(m, sbr, limit):
    """The issue asks 2x the CRLB at SBR >= 1; the scoring steps after the centroid bring
    it to the ML's 1.0-1.1x, M = 5 included (the centroid alone: 2-6x), with honest sigma.
    At M = 5 and SBR = 1 (five background detections a window) the ML itself is 1.4-1.8x."""
    r, h = _against_the_bound("fast", m, sbr, limit, seed=int(9 + m * 10 + sbr))
    np.testing.assert_allclose(np.median(r.signal_counts / h.cycles), m, rtol=0.05)


def test_gaussian_table_matches_ndtr():
    """The scoring steps' CDF/density table against scipy over +-9.5 sigma."""
    from scipy.special import ndtr

    from stages.ranging import _cdf_pdf_numpy

    z = np.linspace(-9.5, 9.5, 400_001)
    cdf, pdf = _cdf_pdf_numpy(z)
    assert np.max(np.abs(cdf - ndtr(z))) < 3e-9
    assert np.max(np.abs(pdf - np.exp(-0.5 * z * z) / np.sqrt(2 * np.pi))) < 5e-9


# ------------------------------------------------------------ the detection threshold

BACKGROUNDS = [0.0, 1e-3, 0.34, 1.0, 100.0]


def _tail_by_sum(c: int, b: float) -> float:
    """P(X >= c), X ~ Poisson(b), summed term by term from c upwards (an independent
    derivation: no incomplete gamma, no scipy)."""
    import math

    if c <= 0:
        return 1.0
    if b == 0:
        return 0.0

    def pmf(k):
        return math.exp(-b + k * math.log(b) - math.lgamma(k + 1))

    if c <= b:  # the tail is large: one less the lower sum
        return 1.0 - math.fsum(pmf(k) for k in range(c))
    total, k = 0.0, c
    while True:  # terms fall from c > b on
        term = pmf(k)
        total += term
        if term < total * 1e-18:
            return total
        k += 1


@pytest.mark.parametrize("b", BACKGROUNDS + [2.5, 30.0, 5e3])
def test_poisson_tail_matches_an_independent_sum_numpy_and_compiled(b):
    from stages.ranging import _poisson_tail, poisson_tail

    cs = np.unique(np.r_[0:12, np.round(b + np.array([-3, 0, 1, 3, 5, 7]) * np.sqrt(b) + 1)])
    cs = cs[cs >= 0].astype(int)
    want = np.array([_tail_by_sum(int(c), b) for c in cs])
    np.testing.assert_allclose(poisson_tail(cs, b), want, rtol=1e-9, atol=1e-300)
    got = np.array([_poisson_tail(float(c), b) for c in cs])
    # 1 - Q by the continued fraction where the tail is large: absolute 1e-15 there
    np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-14)


def test_compiled_tail_beyond_the_exact_range_is_wilson_hilferty():
    from stages.ranging import TAIL_EXACT_MAX, _poisson_tail, poisson_tail

    b = 3 * TAIL_EXACT_MAX
    cs = np.round(b + np.array([3, 4, 5, 6]) * np.sqrt(b))
    np.testing.assert_allclose([_poisson_tail(c, b) for c in cs], poisson_tail(cs, b),
                               rtol=3e-3)


@pytest.mark.parametrize("b", BACKGROUNDS)
def test_threshold_keeps_the_per_bin_false_alarm_rate(b):
    """Seeded Poisson bins above the threshold: at most p_fa / n_bins of them, within a
    3-sigma binomial bound (p_fa large enough to measure: 0.3 over 3000 bins)."""
    from stages.ranging import detection_threshold

    p_fa, n_bins, n = 0.3, 3000, 10_000_000
    q = p_fa / n_bins
    thr = float(detection_threshold(b, p_fa, n_bins))
    x = np.random.default_rng(int(b * 1000) + 1).poisson(b, n)
    above = int(np.sum(x > thr))
    assert above <= n * q + 3 * np.sqrt(n * q) + 1
    # and the threshold is the smallest that does so (one count lower fails, when b > 0)
    if b > 0 and thr > 0:
        assert _tail_by_sum(int(thr), b) > q


def _background_only(rng, b, n_hist, n_bins=3000, cycles=1e9):
    """Background-only histograms of ``b`` counts a bin (cycles so many that pile-up is
    nil: the at-risk count is the cycles to 1e-6)."""
    counts = rng.poisson(b, (n_hist, n_bins)).astype(float)
    edges = np.tile(np.arange(n_bins + 1) * B, (n_hist, 1))
    return Histograms(counts, edges, np.full(n_hist, cycles), np.ones_like(counts, bool))


@pytest.mark.parametrize("estimator", ["fast", "ml", "matched"])
@pytest.mark.parametrize("b", BACKGROUNDS)
def test_false_alarms_on_background_only_histograms_within_p_fa(estimator, b):
    """The issue's case and its neighbours: background-only gates of 3000 bins; the share
    of histograms called detected stays within a binomial 3-sigma bound of p_fa. Eq. 2.46's
    Gaussian, b + alpha_b sqrt(b) + 0.5, called 72 % of them at 0.34 counts a bin."""
    rng = np.random.default_rng(int(b * 100) + 7)
    n_hist, p_fa = 400, 0.05
    h = _background_only(rng, b, n_hist)
    r = estimate(h, SG, estimator, p_fa)
    bound = n_hist * p_fa + 3 * np.sqrt(n_hist * p_fa * (1 - p_fa))
    assert int(np.sum(r.detected)) <= bound


def test_issue_case_0_34_counts_a_bin_at_p_fa_1e_3():
    from scipy.special import ndtri

    rng = np.random.default_rng(15)
    h = _background_only(rng, 0.34, 1000)
    r = estimate(h, SG, "fast", 1e-3)
    assert int(np.sum(r.detected)) <= 1 + 3 * np.sqrt(1)
    # what the Gaussian threshold did: a count of 4 crosses it; P(X >= 4) a bin over 3000
    old = 0.34 + -ndtri(1e-3 / 2999 / 2) * np.sqrt(0.34) + 0.5
    assert 3 < old < 4 and 3000 * _tail_by_sum(4, 0.34) > 1.0


@pytest.mark.parametrize("b", [1e-3, 0.34, 1.0, 100.0])
def test_signal_below_the_threshold_is_not_detected_above_it_is(b):
    """A flat background of b counts a bin (laid out evenly, so its estimate is b) and a
    return of sigma one bin: not detected when the detection window's most counts are
    below the scan statistic's threshold (for b = 100 an excess of a fraction of the
    background), detected a few counts above it."""
    from stages.ranging.detection import scan_bins, scan_threshold

    n_bins = 3000
    k = scan_bins(SG, B)
    flat = np.zeros(n_bins)
    if b >= 1:
        flat[:] = b
    else:
        flat[::int(round(1 / b))] = 1.0
    thr = scan_threshold(k * b, k, n_bins, 1e-3)
    counts = np.tile(flat, (2, 1))
    excess = np.array([thr - 2 - k * b, thr + 2 + np.sqrt(thr) - k * b])
    shape = np.exp(-0.5 * np.arange(-1, 2) ** 2)
    counts[:, 1500:1503] += np.floor(excess[:, None] * shape / shape.sum())
    counts[:, 1501] += np.floor(excess) - np.floor(excess[:, None] * shape / shape.sum()).sum(1)
    h = Histograms(counts, np.tile(np.arange(n_bins + 1) * B, (2, 1)), np.full(2, 1e9),
                   np.ones_like(counts, bool))
    for estimator in ("fast", "ml", "matched", "centroid"):
        r = estimate(h, SG, estimator, 1e-3)
        assert not r.detected[0] and r.detected[1], estimator


def test_compiled_and_numpy_paths_agree_at_low_background():
    from stages import ranging

    rng = np.random.default_rng(11)
    for b in BACKGROUNDS:
        h = _background_only(rng, b, 200, 400)
        counts = h.counts.copy()
        counts[:100, 200] += rng.integers(0, 12, 100)  # some returns, some not
        h = Histograms(counts, h.edges_s, h.cycles, h.valid)
        a, c = ranging.fast(h, SG, 1e-2, compiled=True), ranging.fast(h, SG, 1e-2,
                                                                       compiled=False)
        np.testing.assert_array_equal(a.detected, c.detected)


def _with_a_dead_code(h: Histograms, k: int) -> Histograms:
    """``h`` with a dead code before bin ``k``: a bin of zero width (no count) inserted at
    the edge between bins ``k - 1`` and ``k``, as a first-stage code that never fires."""
    counts = np.insert(h.counts, k, 0.0, axis=1)
    edges = np.insert(h.edges_s, k, h.edges_s[:, k], axis=1)
    valid = np.insert(h.valid, k, True, axis=1)
    return Histograms(counts, edges, h.cycles, valid)


@pytest.mark.parametrize("estimator", ESTIMATORS)
def test_a_return_centred_on_a_dead_code_is_detected(estimator):
    """Found by the chip zoo (seed 326, dead codes, n_sat 0.47): a return of 4 000 counts
    split by a dead code (125: 2300, 126: 0, 127: 829) was not detected: the estimators'
    peak is the centre of their box, the dead code, and the detection tested its count,
    0. Here 60 returns of ~1 000 counts centred on a dead code, at 1e-3 false alarms."""
    from stages import ranging

    rng = np.random.default_rng(11)
    k = 200
    h = _with_a_dead_code(draw(rng, 0.1, np.full(60, k * B), 0.1 / W), k)
    assert np.all(h.counts[:, k] == 0) and np.all(h.counts[:, k - 1] > 100)
    est = estimate(h, SG, estimator)
    assert est.detected.all(), f"{estimator}: {int((~est.detected).sum())} of 60 missed"
    assert np.all(np.isfinite(est.t_s))
    if estimator != "gaussfit":  # (the thesis's baseline fits raw counts at bin centres:
        # the empty code pulls it, up to 3 sigma here, as pile-up does)
        assert np.all(np.abs(est.t_s - k * B) < 3 * SG)
    if estimator in ("fast", "ml"):  # the compiled and numpy paths test the same bin
        fn = getattr(ranging, estimator)
        np.testing.assert_array_equal(fn(h, SG, compiled=True).detected,
                                      fn(h, SG, compiled=False).detected)
