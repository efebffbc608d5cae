"""A chip's measurement ranged with the neighbours (pipeline/offline/spatial.py
``range_state_spatial``): each TDC's codes, on its own calibrated axis less its delay,
mapped onto one axis by the codes' overlap (``common_axis``; docs/ranging.md "On the
chip")."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.offline.spatial import UNPLACED, common_axis


def _overlap_rebin(edges, counts, grid):
    """The same by the definition, code by code: a code's counts times the share of its
    interval each common bin overlaps (a code of no width: all in the bin at its edge)."""
    out = np.zeros(grid.size - 1)
    for k in range(counts.size):
        a, b = edges[k], edges[k + 1]
        if b <= a:
            j = np.searchsorted(grid, a, side="right") - 1
            if 0 <= j < out.size:
                out[j] += counts[k]
            continue
        lo, hi = np.maximum(grid[:-1], a), np.minimum(grid[1:], b)
        out += counts[k] * np.clip(hi - lo, 0, None) / (b - a)
    return out


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.integers(1, 5), st.integers(4, 40),
       st.floats(0.2, 3.0))
def test_common_axis_is_each_codes_overlap(seed, rows, codes, bin_s):
    rng = np.random.default_rng(seed)
    w = rng.uniform(0.3, 1.7, (rows, codes))
    w[rng.random(w.shape) < 0.05] = 0.0                    # a missing code
    edges = np.concatenate([np.zeros((rows, 1)), np.cumsum(w, 1)], 1)
    edges += rng.uniform(-2, 2, (rows, 1))                # each TDC's own delay
    counts = rng.poisson(5.0, (rows, codes)).astype(float)
    valid = np.ones((rows, codes), bool)
    valid[:, :1] = False                                  # code 0 masked, as range masks it
    use = np.ones(rows, bool)
    lo_all = np.max(edges[:, 1])
    hi_all = np.min(edges[:, -1])
    if np.floor((hi_all - lo_all) / bin_s) < 3:
        with pytest.raises(ValueError, match="fewer than 3 bins"):
            common_axis(edges, counts, valid, use, bin_s)
        return
    got, lo = common_axis(edges, counts, valid, use, bin_s)
    assert lo == lo_all
    grid = lo + bin_s * np.arange(got.shape[1] + 1)
    for r in range(rows):
        want = _overlap_rebin(edges[r], np.where(valid[r], counts[r], 0.0), grid)
        np.testing.assert_allclose(got[r], want, rtol=1e-6, atol=1e-6)


def test_a_window_of_split_counts_is_no_more_dispersed_than_poisson():
    """What keeps --p-fa: a window's sum of common bins is whole codes (Poisson) plus a
    share of a code at each end (variance f^2 lambda < f lambda); its mean is the rate
    integrated over the window (a flat rate)."""
    rng = np.random.default_rng(7)
    n, codes = 20_000, 30
    w = rng.uniform(0.6, 1.4, codes)                      # one TDC's INL widths
    edges = np.tile(np.concatenate([[0.0], np.cumsum(w)]), (n, 1))
    rate = 3.0                                            # photons a unit of time
    counts = rng.poisson(rate * w, (n, codes)).astype(float)
    got, lo = common_axis(edges, counts, np.ones((n, codes), bool), np.ones(n, bool), 0.5)
    win = got[:, 10:17].sum(1)                            # 3.5 units, ends inside codes
    assert abs(win.mean() - rate * 3.5) < 4 * np.sqrt(rate * 3.5 / n)
    assert win.var() <= win.mean() * 1.02
    assert win.var() > 0.8 * win.mean()                   # (mostly whole codes)


def test_tdcs_without_a_pixel_get_a_flagged_row(tmp_path, caldir):
    """A geometry of 12 of the chip's 16 TDCs: the other 4 have a row each, not detected,
    flagged; the 12 are ranged to the mirror at 1.5 m."""
    from pipeline.io.caldir import load_calibration
    from pipeline.io.capture import Capture
    from pipeline.io.geometry import load_geometry
    from pipeline.offline.simulate import simulate_capture
    from pipeline.offline.spatial import range_state_spatial
    from stages.histogram import HistogramAccumulator
    from stages.models.scene import scene_from_dict

    sc = scene_from_dict({"name": "m", "sensor": {"n_pixels": 16},
                          "gate": {"t_laser_win_ns": 140.0, "delay_ns": 100.0},
                          "targets": [{"pixels": [0, 15], "distance_m": 1.5,
                                       "reflectivity": 0.0005, "surface": "mirror"}],
                          "ambient": [{"kind": "lux", "lux": 800.0}]})
    simulate_capture(sc, 6000, tmp_path / "cap", seed=2)
    cap = Capture(tmp_path / "cap")
    cal = load_calibration(caldir)
    acc = HistogramAccumulator(16, cal.bounds)
    for first, words in cap.iter_chunks():
        acc.update(words, first)
    g = tmp_path / "g.toml"
    g.write_text('name = "g12"\n[grid]\nrows = 3\ncols = 4\nfov_h_deg = 8.0\n'
                 'fov_v_deg = 6.0\n')
    est, d, s, _ = range_state_spatial(acc.snapshot(), cal, cap.meta.window_ns * 1e-9,
                                       cap.meta.t_laser_win_ns * 1e-9, load_geometry(g))
    first = est.return_index == 0
    assert np.array_equal(est.pixel[first], np.arange(16))
    out = est.pixel >= 12
    assert np.all(est.flag[out] == UNPLACED) and not est.detected[out].any()
    assert np.all(np.isnan(d[out]))
    ok = first & ~out
    assert est.detected[ok].all() and est.estimator == "spatial"
    assert np.all(np.abs(d[ok] - 1.5) < 3 * s[ok]), (d[ok], s[ok])


def test_a_capture_ranged_spatially_needs_a_geometry(tmp_path, caldir):
    """`tcspc range CAPTURE --calibration C --spatial` without --geometry: one line, exit
    2, nothing written."""
    from click.testing import CliRunner

    from pipeline.cli import cli
    from pipeline.offline.simulate import simulate_capture
    from stages.models.scene import scene_from_dict

    simulate_capture(scene_from_dict({"name": "e", "sensor": {"n_pixels": 16}}), 200,
                     tmp_path / "cap", seed=1)
    out = tmp_path / "r.parquet"
    res = CliRunner().invoke(cli, ["range", str(tmp_path / "cap"), "--calibration",
                                   str(caldir), "--spatial", "--out", str(out)])
    assert res.exit_code == 2, res.output
    assert "--spatial needs --geometry" in res.output and not out.exists()


def test_a_geometry_without_the_chips_tdcs(tmp_path, caldir):
    """The range stage refuses at start a geometry with no pixel for the calibration's
    TDCs; a measurement whose TDCs have no pixel has a flagged row each, not an error."""
    from pipeline.io.caldir import load_calibration
    from pipeline.io.geometry import load_geometry
    from pipeline.offline.ranging import RangeCore
    from pipeline.offline.spatial import range_state_spatial
    from schemas.errors import CalibrationError
    from stages.histogram import HistogramAccumulator

    g = tmp_path / "g.toml"
    g.write_text('name = "far"\n[grid]\nrows = 2\ncols = 2\nfov_h_deg = 8.0\n'
                 'fov_v_deg = 6.0\nfirst_tdc = 100\n')
    geom = load_geometry(g)
    cal = load_calibration(caldir)
    with pytest.raises(CalibrationError, match="no pixel for any of the 16 TDCs"):
        RangeCore(cal, spatial=geom)
    acc = HistogramAccumulator(16, cal.bounds)
    acc.update(np.zeros(16 * 100, np.uint32), 0)
    est, d, _, _ = range_state_spatial(acc.snapshot(), cal, 80e-9, 140e-9, geom)
    assert est.pixel.tolist() == list(range(16)) and not est.detected.any()
    assert set(est.flag) == {UNPLACED} and np.all(np.isnan(d))


def test_on_a_zoo_chip_the_sigma_covers_and_empty_pixels_stay_empty(tmp_path, zoo):
    """A chip of the zoo (tests/conftest.py ``zoo``: other LSB, DNL, INL bow, second stage
    and reset peak than the simulator's default chip) on a 3 x 5 grid with TDC 15 without a
    pixel, a depth edge between the top row (1.5 m) and the rest (2.5 m), few photons
    (6000 cycles, reflectivity 0.0005, 800 lux): over 8 captures every placed pixel is
    detected and within 2 of its sigma (calibration's in quadrature) on >= 93 % of them
    (measured: 1.000 over 20 captures, `ml` 0.966; with the estimator's sigma alone, the
    calibration's left out, 0.823: benchmarks/results/spatial_chip_zoo.md), and 4 captures
    without a target give no surface."""
    from pipeline.io.caldir import load_calibration
    from pipeline.io.capture import Capture
    from pipeline.io.geometry import load_geometry
    from pipeline.offline.simulate import simulate_capture
    from pipeline.offline.spatial import range_state_spatial
    from stages.histogram import HistogramAccumulator
    from stages.models.scene import scene_from_dict

    chip, caldir, geom = zoo
    cal, g = load_calibration(caldir), load_geometry(geom)
    truth = np.where(np.arange(16) < 5, 1.5, 2.5)

    def ranged(targets, seed):
        sc = scene_from_dict({"name": "e", "sensor": {"n_pixels": 16},
                              "gate": {"t_laser_win_ns": 140.0, "delay_ns": 100.0},
                              "targets": targets,
                              "ambient": [{"kind": "lux", "lux": 800.0}]})
        simulate_capture(sc, 6000, tmp_path / f"c{seed}", chip=chip, seed=seed)
        cap = Capture(tmp_path / f"c{seed}")
        acc = HistogramAccumulator(16, cal.bounds)
        for first, words in cap.iter_chunks():
            acc.update(words, first)
        est, d, s, _ = range_state_spatial(acc.snapshot(), cal, cap.meta.window_ns * 1e-9,
                                           cap.meta.t_laser_win_ns * 1e-9, g)
        first = (est.return_index == 0) & (est.pixel < 15)
        return est.pixel[first], est.detected[first], d[first], s[first]

    edge = [{"pixels": [0, 4], "distance_m": 1.5, "reflectivity": 0.0005,
             "surface": "mirror"},
            {"pixels": [5, 15], "distance_m": 2.5, "reflectivity": 0.0005,
             "surface": "mirror"}]
    det, within = [], []
    for seed in range(100, 108):
        px, dt, d, s = ranged(edge, seed)
        det.extend(dt)
        within.extend(np.abs(d[dt] - truth[px[dt]]) < 2 * s[dt])
    assert np.mean(det) == 1.0
    assert np.mean(within) >= 0.93, np.mean(within)
    for seed in range(200, 204):
        assert not ranged([], seed)[1].any()
