"""Issue 34's goals from outside (benchmarks/ranging_goals.py): its generator checked
here, the audit itself as a slow test (its coverage checks are in docs/ranging.md), and
the --zero cases it failed (ml's coverage with three returns, the spurious third return)."""

from __future__ import annotations

import numpy as np
import pytest

from benchmarks import ranging_goals as g


def test_the_audits_generator_puts_the_counts_where_it_says():
    """The generator's pulse: its mean counts, centre and width (440 ps FWHM) on 80 ps
    bins, and the flat background, from 4 000 rows."""
    rng = np.random.default_rng(1)
    c = g.histograms(rng, np.full((4000, 1), 2.0), np.full((4000, 1), 1000.0), 0.5)
    assert c.shape == (4000, g.BINS)
    centres = (np.arange(g.BINS) + 0.5) * g.BIN_PS
    m = c.mean(axis=0) - 0.5
    t0 = g.t_of(2.0)
    near = np.abs(centres - t0) < 6 * g.SIGMA_PS
    assert abs(m[near].sum() / 1000.0 - 1) < 0.01
    mean = np.sum(m[near] * centres[near]) / m[near].sum()
    sd = np.sqrt(np.sum(m[near] * (centres[near] - mean) ** 2) / m[near].sum()
                 - g.BIN_PS ** 2 / 12)
    assert abs(mean - t0) < 2.0 and abs(sd / g.SIGMA_PS - 1) < 0.01, (mean - t0, sd)
    assert abs(c[:, ~near].mean() - 0.5) < 0.01


@pytest.mark.slow
def test_issue_34_goals_hold_from_outside():
    """Two surfaces 3 widths apart with every response source, point 2's second surface,
    false alarms within the binomial bound for every estimator and source, and every bad
    input exit 2 in one line (~3 min on the loaded VM)."""
    assert g.main(["--only", "two,point2,null,bad"]) == 0


@pytest.mark.parametrize("fwhm_ps", [200.0, 440.0, 1000.0])
def test_the_response_measured_on_weak_returns_is_not_widened(fwhm_ps, monkeypatch):
    """Issue 34.5: the response's width measured on returns of 100 counts on 1 a bin
    (no --irf-ps): the median of each row's second moment, which clips the background's
    negative fluctuations, came out 12 % wide (440 ps FWHM; 42 % at 1 000 ps) and sigma
    covered 0.977-0.979; pooled and signed it is within 3 %."""
    from stages.ranging import Histograms, response_from_data

    monkeypatch.setattr(g, "SIGMA_PS", fwhm_ps / 2.3548200450309493)
    rng = np.random.default_rng(7)
    n = 1500
    c = g.histograms(rng, rng.uniform(1.5, 8.0, (n, 1)), np.full((n, 1), 100.0), 1.0)
    e = np.arange(g.BINS + 1) * g.BIN_PS * 1e-12
    h = Histograms(c.astype(float), np.broadcast_to(e, (n, g.BINS + 1)).copy(),
                   np.maximum(c.sum(1), 1) * 1e12, np.ones(c.shape, bool))
    sigma, how = response_from_data(h)
    assert how.startswith("measured"), how
    assert abs(sigma * 1e12 / g.SIGMA_PS - 1) < 0.03, (sigma * 1e12, g.SIGMA_PS)


@pytest.fixture(scope="module")
def zero_dir(tmp_path_factory):
    """The audit's zero-distance file (300 rows of 20 000 counts at distance 0)."""
    tmp = tmp_path_factory.mktemp("zero")
    return tmp, g.zero_file(tmp, np.random.default_rng(21), 300)


@pytest.mark.parametrize("signal,bg", [
    (1000.0, 0.1), pytest.param(100.0, 1.0, marks=pytest.mark.slow)])
def test_ml_with_a_zero_file_and_three_returns_covers(zero_dir, signal, bg):
    """Issue 34: with --zero and ml's default three returns, the first return is timed
    with the zero's averaged response; cut 4 bins ahead of its mode (1.7 of the pulse's
    2.3-bin sigma) it timed a return by -1.4 to 0 mm with its place in its bin, and
    2-sigma covered 0.867 at 1 000 counts (bias -0.57 mm, half a sigma) and 0.924 at 100.
    Goal 0.93-0.97, the bias under a fifth of a sigma."""
    tmp, zero = zero_dir
    rng = np.random.default_rng(22)
    n, per = 900, 300
    d = rng.uniform(1.5, 8.0, n)
    f = g.write(tmp / f"cov{signal:g}.parquet",
                g.split(g.histograms(rng, d[:, None], np.full((n, 1), signal), bg), per))
    t, _ = g.rng_range(f, estimator="ml", zero=zero)
    r0 = (t["return_index"] == 0) & t["detected"]
    err = t["distance_m"][r0] - d[g.row_of(t, per)[r0]]
    cov = float(np.mean(np.abs(err / t["sigma_m"][r0]) <= 2))
    assert r0.sum() >= 0.99 * n
    assert 0.93 <= cov <= 0.97, cov
    assert abs(err.mean()) < 0.2 * np.median(t["sigma_m"][r0]), err.mean()


@pytest.mark.parametrize("sep", [pytest.param(3.0, marks=pytest.mark.slow), 1.5])
def test_a_zero_file_finds_two_surfaces_and_no_third(zero_dir, sep):
    """Issue 34: two surfaces (70/30 of 1 000 counts) ranged with --zero and ml's three
    returns: both found in every row, 1.5 widths apart too, and a third return detected
    in no more rows than p_fa 1e-3 allows (the 0.999 quantile of Binomial(300, 1e-3), 3);
    with the response cut 4 bins ahead of its mode, the first's leading tail was left
    standing and called a surface in 7-8 of 300 rows (14 at 1.5 widths)."""
    from scipy.stats import binom

    tmp, zero = zero_dir
    rng = np.random.default_rng(23)
    n = 300
    tol = 0.5 * g.FWHM_PS * 1e-12 * g.C / 2
    d1 = np.full(n, 2.0)
    d2 = d1 + sep * g.FWHM_PS * 1e-12 * g.C / 2
    f = g.write(tmp / f"two{sep}.parquet", {"m": g.histograms(
        rng, np.stack([d1, d2], 1), np.tile([700.0, 300.0], (n, 1)), 0.1)})
    t, _ = g.rng_range(f, estimator="ml", max_returns=3, zero=zero)
    both = g.found(t, d1, tol) & g.found(t, d2, tol)
    third = int((t["detected"] & (t["return_index"] >= 2)).sum())
    assert both.mean() >= 0.95, both.mean()
    assert third <= binom.ppf(0.999, n, 1e-3), third


def test_a_weak_zero_files_own_error_is_in_sigma(tmp_path):
    """A zero-distance file of returns no stronger than the ranged ones (1 000 counts
    each): each distance is a difference of two times of the same spread, and its sigma
    holds the zero row's too (without it, 2-sigma covered ~0.84)."""
    rng = np.random.default_rng(24)
    n, per = 900, 300
    zero = g.write(tmp_path / "zero.parquet", {"z": g.histograms(
        rng, np.zeros((per, 1)), np.full((per, 1), 1000.0), 0.1)})
    d = rng.uniform(1.5, 8.0, n)
    f = g.write(tmp_path / "r.parquet",
                g.split(g.histograms(rng, d[:, None], np.full((n, 1), 1000.0), 0.1), per))
    t, _ = g.rng_range(f, estimator="fast", zero=zero, max_returns=1)
    r0 = t["detected"]
    err = t["distance_m"][r0] - d[g.row_of(t, per)[r0]]
    cov = float(np.mean(np.abs(err / t["sigma_m"][r0]) <= 2))
    assert 0.93 <= cov <= 0.97, cov
