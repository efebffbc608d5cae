"""Issue 34's goals from outside (benchmarks/ranging_goals.py): its generator checked
here, the audit itself as a slow test (its coverage checks are in docs/ranging.md, two of
them not met and said so)."""

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
