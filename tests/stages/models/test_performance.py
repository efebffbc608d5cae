from dataclasses import replace

import numpy as np
import pytest
from scipy.special import erfinv

from stages.models.performance import (
    TABLE_2_2,
    alpha_b,
    alpha_h,
    detection_probability,
    predict,
    table_2_2_rows,
)

D = np.linspace(1, 50, 50)


def mean_p(spec, gated=False):
    return float(np.mean(predict(spec, D, gated)["p_detect"]))


def test_alphas_are_eq_2_45_2_46():
    p = np.array([0.1, 0.5, 0.9, 0.99])
    np.testing.assert_allclose(alpha_h(p), np.sqrt(2) * erfinv(p), rtol=1e-12)
    np.testing.assert_allclose(alpha_b(p, 400), np.sqrt(2) * erfinv(1 - (1 - p) / 399),
                               rtol=1e-9)
    assert np.isfinite(alpha_b(1 - 1e-14, 400))  # the stable form does not overflow


def test_detection_probability_solves_eq_2_44():
    h, b, n = 200.0, 50.0, 400
    p = detection_probability(h, b, n)
    margin = lambda q: h - alpha_h(q) * np.sqrt(h) - b - alpha_b(q, n) * np.sqrt(b)  # noqa: E731
    assert margin(p - 1e-9) > 0 > margin(min(p + 1e-6, 1 - 1e-15))
    assert detection_probability(10.0, 50.0, 400) == 0.0


def test_table_2_2_reading():
    c = TABLE_2_2
    assert [s.jitter_s for s in c] == pytest.approx([200e-12, 800e-12] + [200e-12] * 5
                                                    + [666e-12])
    assert c[7].pulse_energy_j == pytest.approx(29e-12) and c[7].pde == 0.013
    assert c[4].samples == 40_000 and c[5].samples == 10_000 and c[7].samples == 40_000
    assert c[3].tdc_resolution_s == pytest.approx(50e-12)
    assert c[5].ambient_lux == 400 and c[6].ambient_lux == 100


@pytest.mark.parametrize("field, lo, hi, direction", [
    ("samples", 10_000, 40_000, +1),
    ("pulse_energy_j", 100e-9, 400e-9, +1),
    ("pde", 0.02, 0.08, +1),
    ("jitter_s", 200e-12, 800e-12, -1),
    ("ambient_lux", 100.0, 400.0, -1),
])
def test_trends_of_table_2_2(field, lo, hi, direction):
    """P rises with samples, pulse energy and PDE, falls with jitter and ambient light."""
    base = TABLE_2_2[0]
    a = mean_p(replace(base, **{field: lo}))
    b = mean_p(replace(base, **{field: hi}))
    assert (b - a) * direction > 0.02, (field, a, b)


def test_configurations_against_configuration_1():
    p = [mean_p(s) for s in TABLE_2_2]
    assert p[1] < p[0] and p[3] < p[0] and p[5] < p[0]   # jitter, finer TDC, ambient
    assert p[2] > p[0] and p[4] > p[0] and p[6] > p[0]   # PDE, samples, energy
    assert p[7] < p[0]                                   # the thesis's own system


def test_gating_helps_at_long_range_with_strong_background():
    spec = replace(TABLE_2_2[0], ambient_lux=3000.0)
    far = np.array([15.0, 20.0, 25.0])
    assert np.all(predict(spec, far, True)["p_detect"]
                  >= predict(spec, far, False)["p_detect"])
    assert mean_p(spec, True) > mean_p(spec, False)


def test_rows_table():
    rows = table_2_2_rows(np.array([1.0, 10.0]))
    assert len(rows) == 8 * 2 * 2
    assert {"config", "gated", "distance_m", "p_detect", "spec_pde"} <= set(rows[0])


def test_configuration_8_edge_is_the_threshold_not_the_peak_search():
    """docs/models.md: configuration 8's P falls from 0.80 to 0 between 0.2 and 0.3 m
    while the highest bin stays on the signal; the signal in the peak bin falls below
    eq. 2.44's background term."""
    x = np.array([0.2, 0.25, 0.3, 0.5, 1.0, 5.0])
    r = predict(TABLE_2_2[7], x, gated=False)
    assert r["on_signal"].all()
    assert r["p_detect"][:3].round(2).tolist() == [0.80, 0.39, 0.0]
    assert (r["p_detect"][3:] == 0).all()
    signal = r["peak_count"] - r["noise_count"]
    assert signal[:3].round(1).tolist() == [8.4, 5.4, 3.7]
    threshold = alpha_b(0.5, 2500) * np.sqrt(r["noise_count"][2])
    assert signal[2] < threshold < signal[0]
