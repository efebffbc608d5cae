"""More than one surface a pixel (issue 24.4): partially transparent targets in the
simulator (scene ``transmittance``), up to K returns per pixel from the range estimators,
with the truth checked, and the false-alarm rate on background-only histograms."""

from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from scipy import stats

from stages.models.scene import evaluate, load_scene, scene_from_dict
from stages.models.tcspc import first_photon_histogram, layered_histogram
from stages.ranging import Histograms, estimate_returns
from stages.ranging_eval import draw_layered, score_returns, two_surfaces
from stages.simulator.chip import make_chip
from stages.simulator.engines import KIND_PHOTON, FastEngine, Optics, ReferenceEngine

SCENES = Path(__file__).parents[2] / "scenes"
B, SG = 100e-12, 200e-12


def test_a_transparent_target_passes_its_light_each_way():
    """The window scene: pixels 0-63 see the glass and, behind it, the wall with the
    glass's transmittance squared; 64-127 the wall alone; an opaque target hides what
    is behind it (the default)."""
    sm = evaluate(load_scene(SCENES / "window.toml"))
    wall_alone = sm.returns_m[100, 0]
    assert sm.returns_m.shape == (128, 2)
    np.testing.assert_allclose(sm.returns_m[:64, 1], 0.81 * wall_alone, rtol=1e-12)
    np.testing.assert_allclose(sm.returns_distance_m[:64], [[2.0, 5.0]] * 64)
    assert np.isnan(sm.returns_distance_m[64:, 1]).all()
    assert (sm.m_signal == sm.returns_m[:, 0]).all()
    opaque = evaluate(scene_from_dict({"targets": [
        {"pixels": [0, 127], "distance_m": 2.0}, {"pixels": [0, 127], "distance_m": 5.0}]}))
    assert (opaque.returns_m[:, 1] == 0).all() and (opaque.distance_m == 2.0).all()
    with pytest.raises(ValueError, match="transmittance"):
        scene_from_dict({"targets": [{"pixels": [0, 1], "distance_m": 2.0,
                                      "transmittance": 1.5}]})


def test_the_reference_engine_draws_both_surfaces_with_pile_up():
    """Photon by photon, two surfaces in a TDC: the arrival histogram matches the exact
    model's (chi-square), the nearer surface taking its share first (pile-up)."""
    window, reset = 80e-9, 20e-9
    o = Optics(np.array([0.8]), np.array([30e-9]), SG, np.array([2e6]), window, reset,
               extra_m=np.array([[0.6]]), extra_tof_s=np.array([[45e-9]]))
    chip = make_chip(1, 0, inl_scale=0.0, artifact_rate=0.0)
    with pytest.raises(ValueError, match="engine='reference'"):
        FastEngine(chip, o, chip.boundaries_s(0.0))
    eng = ReferenceEngine(chip, o, chip.boundaries_s(0.0))
    rng = np.random.default_rng(3)
    bins = np.arange(0, window + 1e-12, 0.4e-9)
    obs = np.zeros(bins.size - 1)
    for _ in range(4):
        st = eng.draw(rng, 50_000)
        obs += np.histogram(st.t_s[st.kind == KIND_PHOTON], bins=bins)[0]
    h = layered_histogram([0.8, 0.6], [30e-9, 45e-9], SG, 2e6, window, 0.4e-9, reset)
    exp = 200_000 * h.p
    keep = exp > 5
    chi2 = float((((obs - exp) ** 2 / exp)[keep]).sum())
    assert stats.chi2.sf(chi2, keep.sum() - 1) > 0.01
    one = first_photon_histogram(0.8, 30e-9, SG, 2e6, window, 0.4e-9, reset)
    near = slice(int(44e-9 / 0.4e-9), int(46e-9 / 0.4e-9))  # the second surface is there
    assert obs[near].sum() > 10 * 200_000 * one.p[near].sum()


@pytest.mark.parametrize("estimator", ["fast", "ml"])
@pytest.mark.parametrize("scene", ["window", "fence"])
def test_two_surfaces_of_a_scene_are_found_at_their_truth(estimator, scene):
    """Histograms of the scene's model (its transmittance physics) at 200 000 cycles:
    every pixel that sees two surfaces gets two detected returns, each within 4 sigma of
    its truth; a pixel with one surface gets one."""
    sm = evaluate(load_scene(SCENES / f"{scene}.toml"))
    rng = np.random.default_rng(5)
    px = np.arange(0, 128, 4)
    h = draw_layered(rng, sm.returns_m[px], sm.returns_tof_s[px], sm.bg_rate_hz[px],
                         sm.window_s, 65e-12, 200_000, sm.sigma_s)
    est = estimate_returns(h, sm.sigma_s, estimator, 1e-3, 3)
    for i, p in enumerate(px):
        rows = (est.pixel == i) & est.detected
        truth = np.sort(sm.returns_tof_s[p][sm.returns_m[p] > 0])
        got = np.sort(est.t_s[rows])
        assert got.size == truth.size, (p, got, truth)
        sig = est.sigma_s[rows][np.argsort(est.t_s[rows])]
        assert (np.abs(got - truth) < 4 * sig).all(), (p, got - truth, sig)
    # return 0 is the strongest
    for i in range(px.size):
        s = est.signal_counts[(est.pixel == i) & est.detected]
        assert s.size < 2 or s[0] >= s[1:].max()


@pytest.mark.parametrize("estimator", ["fast", "ml"])
def test_two_surfaces_three_widths_apart_the_weaker_with_30_percent(estimator):
    """The issue's goal: 3 instrument widths (FWHM) apart, the weaker with 30 % of the
    counts (300 of 1 000): both detected in >= 95 % of the pixels, each within 2 sigma
    about 95 % of the time (coverage >= 90 % on 200 pixels)."""
    rng = np.random.default_rng(17)
    h, truth = two_surfaces(rng, 200, 3.0, 0.3, 1000, SG, B)
    r = score_returns(estimate_returns(h, SG, estimator, 1e-3, 3), truth)
    assert r["both_detected"] >= 0.95
    assert r["near_cover_2sigma"] >= 0.9 and r["far_cover_2sigma"] >= 0.9


@pytest.mark.parametrize("estimator", ["fast", "ml", "matched"])
@pytest.mark.parametrize("b", [1e-3, 0.3, 30.0])
def test_false_alarms_per_pixel_stay_within_p_fa_with_three_returns(estimator, b):
    """Background-only histograms of 500 bins (seeded): the share of pixels with any
    detected return stays within a binomial 3-sigma bound of p_fa; return k + 1 is only
    searched behind a detected return k, so the union over returns adds nothing here."""
    rng = np.random.default_rng(int(b * 1000) + 3)
    n_hist, p_fa = 600, 0.03
    counts = rng.poisson(b, (n_hist, 500)).astype(float)
    h = Histograms(counts, np.tile(np.arange(501) * B, (n_hist, 1)), np.full(n_hist, 1e9),
                   np.ones_like(counts, bool))
    est = estimate_returns(h, SG, estimator, p_fa, 3)
    any_det = np.zeros(n_hist, bool)
    any_det[est.pixel[est.detected]] = True
    assert any_det.sum() <= n_hist * p_fa + 3 * np.sqrt(n_hist * p_fa * (1 - p_fa))


def test_one_return_has_no_second_beside_its_tails():
    """A strong single return (16 000 counts over 0.3 counts a bin): its Gaussian tails
    past the mask are no second return (they were, against the flat background)."""
    rng = np.random.default_rng(2)
    h, _ = two_surfaces(rng, 100, 5.0, 0.0, 16_000, SG, B, bg_per_bin=0.3)
    est = estimate_returns(h, SG, "ml", 1e-3, 3)
    assert est.detected[est.return_index == 0].all()
    assert not est.detected[est.return_index > 0].any()
    np.testing.assert_array_equal(est.pixel[est.return_index == 0], np.arange(100))


def test_max_returns_one_is_the_single_return_estimate():
    from stages.ranging import estimate

    rng = np.random.default_rng(4)
    h, _ = two_surfaces(rng, 50, 3.0, 0.3, 1000, SG, B)
    one = estimate_returns(h, SG, "fast", 1e-3, 1)
    ref = estimate(h, SG, "fast", 1e-3)
    np.testing.assert_array_equal(one.t_s, ref.t_s)
    np.testing.assert_array_equal(one.detected, ref.detected)
    assert (one.return_index == 0).all() and (one.pixel == np.arange(50)).all()
    with pytest.raises(ValueError, match="max_returns"):
        estimate_returns(h, SG, "fast", 1e-3, 0)


def test_ranges_1_0_files_are_upgraded_on_read(tmp_path):
    from pipeline.io.ranges import read_ranges
    from schemas.core import META_NAME, META_VERSION
    from schemas.errors import SchemaVersionError
    from schemas.outputs import RANGES

    old = pa.table({"measurement": ["m"], "tdc": pa.array([3], pa.uint16()),
                    "distance_m": [1.5], "sigma_m": [0.001], "fwhm_m": [0.07],
                    "signal_counts": [100.0], "background_per_bin": [0.1],
                    "detected": [True], "estimator": ["ml"]})
    pq.write_table(old.replace_schema_metadata({META_NAME: b"ranges", META_VERSION: b"1.0"}),
                   tmp_path / "old.parquet")
    t = read_ranges(tmp_path / "old.parquet")
    assert t.schema.metadata[META_VERSION] == RANGES.version.encode() == b"3.0"
    assert t.schema.field("tdc").type == pa.uint32()
    assert t.column("return_index").to_pylist() == [0] and t.column("flag").to_pylist() == [""]
    assert t.column("distance_m").to_pylist() == [1.5]
    pq.write_table(old.replace_schema_metadata({META_NAME: b"ranges", META_VERSION: b"4.0"}),
                   tmp_path / "new.parquet")
    with pytest.raises(SchemaVersionError, match="4.0"):
        read_ranges(tmp_path / "new.parquet")
