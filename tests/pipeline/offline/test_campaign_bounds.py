"""One set of artifact bounds for a whole density-test campaign (issue 15), on small
synthetic histograms: the bounds are the chip's, not the light's (thesis section 3.4: the
artifact comes at a fixed rate per cycle, the valid block grows with the light), so the
brightest test shows them and every test is filtered with them; a TDC whose bounds or
reset peak cannot be trusted is flagged with the reason, never silently wrong."""

from types import SimpleNamespace

import numpy as np

from pipeline.io.caldir import load_calibration
from pipeline.offline.calibrate import checked, write_caldir
from stages import calibration as cal
from stages.artifact import estimate_bounds

N_TDC, CYCLES = 3, 800_000
N_MIN, N_MAX = 20, 150


def joint(rng, block_per_code, artifact_per_code=70.0):
    """(N_TDC, 8, 256) second-stage counts: a DNL-shaped block [N_MIN, N_MAX] spread over
    the P1st values, and the artifact's sparse D2nd codes above N_MAX (at a rate per cycle
    that does not depend on the light)."""
    dnl = np.random.default_rng(7).uniform(0.6, 1.4, (N_TDC, 1, N_MAX - N_MIN + 1))
    j = np.zeros((N_TDC, 8, 256), np.int64)
    j[:, :, N_MIN:N_MAX + 1] = rng.poisson(block_per_code / 8 * dnl,
                                           (N_TDC, 8, N_MAX - N_MIN + 1))
    j[:, 0, N_MAX + 1:] = rng.poisson(artifact_per_code, (N_TDC, 255 - N_MAX))
    return j


def test_the_dimmest_test_alone_is_fooled_the_campaign_is_not():
    """The dimmest test's artifact codes (~70 a code) are nearly as dense as its block
    (~100): alone its bounds run to 255 and nothing says so (what issue 15 found at 0.02
    detections a cycle with the artifact at 2.7e-3 a cycle). The campaign takes each TDC's
    bounds from the test with the densest block per cycle, exact, in any order."""
    rng = np.random.default_rng(1)
    dim, mid, bright = joint(rng, 100.0), joint(rng, 600.0), joint(rng, 3000.0)
    alone = estimate_bounds(dim.sum(axis=1))
    assert alone.n_max.tolist() == [255] * N_TDC and not alone.uncertain.any()  # the trap
    for order in ([dim, mid, bright], [bright, dim, mid]):
        second = cal.campaign_second_stage(order, [CYCLES] * 3)
        assert second.n_min.tolist() == [N_MIN] * N_TDC
        assert second.n_max.tolist() == [N_MAX] * N_TDC
        assert not second.uncertain.any()
    # per cycle, not per test: the dim test over 40x the cycles is no brighter
    second = cal.campaign_second_stage([joint(rng, 4000.0), mid], [40 * CYCLES, CYCLES])
    assert second.n_max.tolist() == [N_MAX] * N_TDC


def density_state(rng, spike_at=None):
    """D1st histograms of a uniform-light test (~200 hits a code up to code 363, the reset
    peak at 363-364); ``spike_at``: TDC 2 also holds an artifact's code as hits there."""
    hits = np.zeros((N_TDC, 512))
    hits[:, :363] = rng.poisson(200.0, (N_TDC, 363))
    hits[:, 363], hits[:, 364] = 6000, 1500
    if spike_at is not None:
        hits[2, spike_at] += 20_000
    return SimpleNamespace(hits=hits, cycles=np.full(N_TDC, 1e6), artifacts=None)


def test_uncertain_bounds_and_a_misplaced_reset_peak_are_flagged_with_a_reason(tmp_path):
    """TDC 1's block is too sparse in every test for its edges to be trusted: the campaign
    carries the estimate's reason and the density test flags the TDC with it. TDC 2's
    histogram holds an artifact's code (139) as hits, which the density test takes for
    the reset peak: far from where the light ends (~364), flagged, not used."""
    rng = np.random.default_rng(2)
    tests = [joint(rng, b, 0.0) for b in (8.0, 16.0)]
    for j in tests:
        j[1] = rng.poisson(np.where(j[1] > 0, 0.1, 0.0))  # ~1 count a block code
    second = cal.campaign_second_stage(tests, [CYCLES, CYCLES])
    assert second.uncertain.tolist() == [False, True, False]
    state = density_state(rng, spike_at=139)
    res = cal.density_test(state.hits, state.cycles, 80e-9)
    assert res.ok.all() and abs(res.x_t[2] - 139) < 2  # fooled by the spike alone
    out = checked(state, res, second)
    assert out.ok.tolist() == [True, False, False]
    assert out.reasons[0] == ""
    assert out.reasons[1].startswith("artifact bounds uncertain: ") \
        and "edges" in out.reasons[1]
    assert "light ends at code 365: not where the window ends" in out.reasons[2]
    assert np.isnan(out.lsb_s[1:]).all() and np.isfinite(out.lsb_s[0])
    # the reasons are the calibration's: saved, loaded, and one per TDC
    calib = load_calibration(write_caldir(tmp_path / "cal", out, second, []))
    assert calib.ok.tolist() == [True, False, False] and calib.reasons == out.reasons


def test_a_tdc_flagged_in_one_test_keeps_an_lsb_fit_on_the_others():
    """Five levels, TDC 0 flagged in the dimmest (NaN there): its cubic is fitted on the
    four it has (exact for a cubic truth), its spline reads the truth between them, and
    below its own levels it has no LSB (flagged) rather than an extrapolation. Three
    levels give a quadratic, two nothing."""
    levels = np.array([0.02, 0.06, 0.15, 0.3, 0.6])

    def truth(n):
        return 200 + 30 * n - 10 * n ** 2 + 5 * n ** 3

    y = np.vstack([truth(levels), truth(levels) + 1.0])
    y[0, 0] = np.nan
    fit = cal.fit_lsb(levels, y)
    assert np.isfinite(fit.coef).all()
    np.testing.assert_allclose(fit.cubic_ps(levels)[0], truth(levels), atol=1e-9)
    assert abs(fit.lsb_ps(0.1)[0] - truth(0.1)) < 0.01  # ps: the spline, between its levels
    assert abs(fit.lsb_ps(0.1)[1] - truth(0.1) - 1.0) < 0.01
    below = fit.lsb_ps(0.03)
    assert np.isnan(below[0]) and np.isfinite(below[1])  # TDC 0 was never measured there
    y[0, 1] = np.nan  # three levels left: a quadratic through them
    coef = cal.fit_lsb(levels, y).coef[0]
    assert np.isfinite(coef[:3]).all() and coef[3] == 0.0
    y[0, 2] = np.nan  # two: no fit, the TDC is flagged by the campaign
    assert np.isnan(cal.fit_lsb(levels, y).coef[0]).all()
