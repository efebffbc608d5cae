"""LinoSPAD2 code-density calibration against a published table: synthetic and real."""

from pathlib import Path

import numpy as np
import pytest

from pipeline.io import linospad2 as lio
from pipeline.offline import linospad2_cal as cal
from stages.instruments import linospad2 as lino

DATA = Path(__file__).parents[2] / "data" / "linospad2"  # public files, see tests/data/README.md
DAT = DATA / "test_data_2212b.dat"
CSV = DATA / "TDC_A5_#36_2212b.csv"
needs_data = pytest.mark.skipif(not DAT.exists() or not CSV.exists(),
                                reason=f"the shared LinoSPAD2 sample is not in {DATA}")
WPL = 40


def chain_widths(rng, rows=256):
    w = rng.lognormal(0.0, 0.4, size=(rows, lino.N_FINE))
    w[:, : rng.integers(15, 28)] = 0.0
    return w / w.sum(axis=1, keepdims=True) * lino.CLOCK_PS


def write_daplis_csv(path, table_ps):
    """The published layout: pandas' header and index."""
    lines = ["," + ",".join(str(k) for k in range(lino.N_FINE))]
    lines += [f"{i}," + ",".join(repr(float(v)) for v in row) for i, row in enumerate(table_ps)]
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    """A capture and a 'published' table (another capture, daplis' convention) of the
    same known chains."""
    rng = np.random.default_rng(31)
    truth = chain_widths(rng)
    tmp = tmp_path_factory.mktemp("lino")
    dat = tmp / "capture.dat"
    lino.simulate_words(truth, 60, rng, "2212b", WPL, fill=0.6).astype("<u4").tofile(dat)
    other = lino.simulate_words(truth, 50, rng, "2212b", WPL, fill=0.6)
    counts, _ = lino.fine_histograms(other, "2212b", "pixel", WPL)
    csv = write_daplis_csv(tmp / "TDC_X_#0_2212b.csv", lino.code_density(counts).upper_ps)
    return truth, dat, csv, counts


def test_synthetic_capture_agrees_with_its_published_twin_as_statistics_says(synthetic):
    truth, dat, csv, counts = synthetic
    res = cal.compare(dat, csv, "2212b", words_per_line=WPL, n_null=100, seed=3)
    c = res.comparison
    np.testing.assert_array_equal(c.published_hits, counts.sum(1).astype(np.int64))
    s = cal.summary(res)
    assert s["live"] == 256
    assert 0.7 < s["median_ratio"] < 1.0          # statistics alone: ~0.84
    assert abs(s["median_ratio"] - s["null_median_ratio"]) < 0.12
    assert s["within_2x"] > 0.93
    assert abs(s["mean_diff_ps"]) < 4 * s["mean_diff_se_ps"]
    # the measured times are within the binomial error of the truth (this capture alone)
    f = np.clip(np.cumsum(truth, axis=1) / lino.CLOCK_PS, 0, 1)
    sigma = np.sqrt(f * (1 - f) / res.measured.hits[:, None]) * lino.CLOCK_PS
    inside = (f > 0) & (f < 1)
    z = (res.measured.upper_ps - np.cumsum(truth, axis=1))[inside] / sigma[inside]
    assert 0.85 < np.sqrt(np.mean(z ** 2)) < 1.15


def test_per_tdc_comparison_pools_the_four_pixels(synthetic):
    _, dat, csv, counts = synthetic
    res = cal.compare(dat, csv, "2212b", by="tdc", words_per_line=WPL, n_null=0)
    assert res.measured.counts.shape == (64, 140)
    np.testing.assert_array_equal(res.published_counts, counts.reshape(64, 4, 140).sum(1))
    t = cal.comparison_table(res)
    assert t.column_names[0] == "tdc" and t.num_rows == 64
    assert np.all(np.isnan(t["p_value"].to_numpy()))


def test_a_published_table_in_another_convention_shows_as_an_offset(tmp_path):
    """Had the authors written bin centres, the mean difference would be ~ +w/2 (~8 ps);
    with ~2400 hits a pixel on both sides that is many standard errors, while the right
    convention's mean difference is within a few."""
    rng = np.random.default_rng(8)
    truth = chain_widths(rng)
    dat = tmp_path / "big.dat"
    lino.simulate_words(truth, 400, rng, "2212b", WPL, fill=0.6).astype("<u4").tofile(dat)
    counts = rng.multinomial(np.full(256, 2400), truth / lino.CLOCK_PS)
    summaries = {}
    for conv in ("upper", "centre"):
        csv = write_daplis_csv(tmp_path / f"{conv}.csv",
                               lino.code_density(counts).code_time_ps(conv))
        summaries[conv] = cal.summary(cal.compare(dat, csv, "2212b", words_per_line=WPL,
                                                  n_null=0))
    right, wrong = summaries["upper"], summaries["centre"]
    assert abs(right["mean_diff_ps"]) < 4 * right["mean_diff_se_ps"]
    assert wrong["mean_diff_ps"] > 6.0 and wrong["mean_diff_ps"] > 5 * wrong["mean_diff_se_ps"]
    assert wrong["median_rms_ps"] > right["median_rms_ps"]


def test_comparison_table_columns(synthetic):
    _, dat, csv, _ = synthetic
    t = cal.compare_with_published(dat, csv, "2212b", n_null=0, words_per_line=WPL)
    for name in ("pixel", "tdc", "hits", "rms_ps", "max_ps", "expected_rms_ps",
                 "dead_codes", "published_hits", "ratio", "p_value"):
        assert name in t.column_names
    assert t.num_rows == 256
    assert np.all(t["max_ps"].to_numpy() >= t["rms_ps"].to_numpy())


# ---------------------------------------------------------------------------- real

@needs_data
def test_real_board_agrees_with_its_published_calibration_within_statistics():
    """Bound: both tables are ~400-hit code-density tests (the published one's widths are
    multiples of 2500 ps / N, N ~390), so binomial statistics alone give a per-pixel RMS
    difference of sqrt(mean F(1-F) (1/N + 1/N_pub)) x 2500 ~ 64 ps (median). Under pure
    statistics the median of RMS / expectation is ~0.84 (Monte Carlo), and the median over
    ~250 pixels scatters by a few %: so the median RMS must be below the median expectation
    itself (a systematic disagreement of even ~30 ps would push it over), and below 70 ps
    (3.9 nominal codes) in absolute terms."""
    t = cal.compare_with_published(DAT, CSV, "2212b", n_null=50, seed=0)
    live = np.isfinite(t["rms_ps"].to_numpy())
    rms = t["rms_ps"].to_numpy()[live]
    expected = t["expected_rms_ps"].to_numpy()[live]
    assert live.sum() == 251   # pixels 107, 111, 113, 125, 150 have no hits here or there
    assert np.median(rms) < np.median(expected)
    assert np.median(rms) < 70.0
    assert np.mean(rms / expected < 2) > 0.93
    assert set(np.flatnonzero(~live).tolist()) == {107, 111, 113, 125, 150}
    hits = t["hits"].to_numpy()
    counts, _ = lio.histogram_file(DAT, "2212b")
    np.testing.assert_array_equal(hits, counts.sum(1).astype(np.int64))


@needs_data
def test_real_board_per_tdc_halves_the_disagreement():
    s = cal.summary(cal.compare(DAT, CSV, "2212b", by="tdc", n_null=0))
    assert s["live"] == 64
    assert s["median_rms_ps"] < s["median_expected_rms_ps"] < 40.0


@needs_data
def test_the_published_convention_is_the_upper_edge():
    scan = {r["convention"]: r for r in cal.convention_scan(DAT, CSV, "2212b").to_pylist()}
    assert min(scan, key=lambda k: scan[k]["pooled_rms_ps"]) == "upper"
    assert min(scan, key=lambda k: abs(scan[k]["mean_diff_ps"])) == "upper"
    # lower and centre are off by ~ a mean width (17.9 ps x live share) and half of it
    assert scan["lower"]["mean_diff_ps"] < scan["centre"]["mean_diff_ps"] - 6
    assert scan["centre"]["mean_diff_ps"] < scan["upper"]["mean_diff_ps"] - 6


@needs_data
def test_the_four_pixels_of_a_tdc_share_one_chain_and_tdcs_differ():
    """Each pixel against the other 3 of its TDC is statistics (in both tables); a TDC
    against the next one is not: per-TDC calibration pools 4x the hits legitimately."""
    res = {k: cal.comparison_summary(v)
           for k, v in cal.shared_chains(DAT, CSV, "2212b", n_null=200).items()}
    mine, pub, control = res.values()
    for s in (mine, pub):
        assert abs(s["median_ratio"] - s["null_median_ratio"]) < 0.1
        assert s["p_below_0.01"] <= 8      # ~2.5 expected by chance of ~250
    assert control["median_ratio"] > 1.2 and control["p_below_0.01"] >= 8


@needs_data
@pytest.mark.slow   # matplotlib: ~3-7 s
def test_the_figure_is_written(tmp_path):
    res = cal.compare(DAT, CSV, "2212b", n_null=20)
    out = cal.write_figure(res, tmp_path / "fig.png",
                           by_tdc=cal.compare(DAT, CSV, "2212b", by="tdc", n_null=20))
    assert out.stat().st_size > 20_000 and out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
