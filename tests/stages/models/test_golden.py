"""The thesis's own numbers, each with the equation it comes from.

Where the thesis's arithmetic does not follow from its inputs, the physics is tested and
the comment says so.
"""

import numpy as np
import pytest
from scipy.constants import c as C_LIGHT

from stages.models import atmosphere as atm
from stages.models import noise, signal
from stages.models.performance import AMBIENT_PHOTONS_PER_LUX


def test_eq_2_23_collimated_photons_at_100_m():
    assert signal.collimated_photons_per_pixel(100.0) == pytest.approx(9.4, abs=0.05)


def test_eq_2_26_diffuse_photons_at_100_m():
    # eq. 2.26 prints ~1.25e-7; S/(2 pi z^2) * 29 pJ * 0.5 / (hc/405 nm) is 2.71e-7.
    assert signal.diffuse_photons_per_pixel(100.0, 0.5) == pytest.approx(2.71e-7, rel=2e-3)


def test_section_2_2_2_ambient_photons():
    # 1.0 W/m^2/nm through a 10 nm filter on a 24 um pixel: 5.76 nW, ~1.17e10 photons/s.
    assert 1.0 * 10 * (24e-6) ** 2 == pytest.approx(5.76e-9)
    assert noise.photon_rate_hz(1.0, 10.0) == pytest.approx(1.17e10, rel=5e-3)
    assert AMBIENT_PHOTONS_PER_LUX * 1e5 == pytest.approx(1.17e10, rel=5e-3)


def test_section_2_3_3_transmission_200_m_at_273_k():
    assert atm.transmission(200.0, temperature_k=273.0) == pytest.approx(0.9914, abs=5e-5)


def test_appendix_g_scale_height_and_column():
    # eq. G.1 with the thesis's constants (k = 1.38e-23, g = 9.81): 7314.5 m
    h = 1.38e-23 * 250 / (28.964 * 1.660e-27 * 9.81)
    assert h == pytest.approx(7314.5, abs=1.0)
    # with CODATA constants the height moves by 0.05 %, the column not at 4 digits
    assert atm.scale_height_m() == pytest.approx(7314.5, rel=1e-3)
    assert atm.column_transmission() == pytest.approx(0.7420, abs=2e-4)
    # eq. G.2 as a product over 1 m slabs equals the integral form
    z = np.arange(1, 96_561)
    prod = np.exp(-np.sum(atm.RAYLEIGH_405_M2 * 1.0 * atm.N0_SEA_LEVEL_M3
                          * np.exp(-z / atm.scale_height_m())))
    assert prod == pytest.approx(atm.column_transmission(), rel=1e-4)


def test_eq_f_5_pressure_at_2000_m():
    assert atm.pressure_pa(2000.0) == pytest.approx(79495, abs=3)


def test_eq_2_42_2_43_lamps():
    # eq. 2.42 prints 2.389 klx; 1.5e6 / (2 pi * 100) = 2387.3 (the print rounds pi)
    assert noise.lamp_illuminance_lux(1.5e6, 10.0, 90.0) == pytest.approx(2389, rel=1e-3)
    assert noise.lamp_illuminance_lux(3200.0, 5.0, 45.0) == pytest.approx(69.6, abs=0.05)


def test_eq_2_37_2_38_solar_irradiance_at_405_nm():
    # W/m^2/um: 1711.4 at the top of the atmosphere, 1269.9 at sea level (eq. 2.40)
    assert noise.solar_irradiance_top() * 1e-6 == pytest.approx(1711.4, rel=2e-4)
    assert noise.solar_irradiance_sea_level() * 1e-6 == pytest.approx(1269.9, rel=5e-4)
    # eq. 2.37 is a normalised spectrum
    lam = np.linspace(50e-9, 100e-6, 2_000_001)
    assert np.trapezoid(noise.planck_normalized_per_m(lam), lam) == pytest.approx(1, rel=1e-3)


def test_eq_3_6_dcr_from_artifact_counts():
    assert noise.dcr_from_counts_hz(298, 80e-9, 1e6) == pytest.approx(3725.0)
    assert noise.dcr_from_counts_hz(6, 80e-9, 1e6) == pytest.approx(75.0)  # after removal


def test_section_2_6_moving_target_tof_is_a_round_trip():
    # 2 ms at 50 m/s moves the target 0.1 m: the TOF changes by 2 * 0.1 / c = 0.667 ns
    # (the thesis quotes the one-way distance).
    from stages.models.performance import SystemSpec, moving_target_histogram

    spec = SystemSpec(samples=2000, tdc_resolution_s=10e-12, jitter_s=5e-12, ambient_lux=0)
    edges, counts = moving_target_histogram(spec, 10.0, 50.0, 1e6, window_s=4e-9)
    t = edges[:-1][counts > counts.max() * 0.5]
    assert t.max() - t.min() == pytest.approx(2 * 0.1 / C_LIGHT, abs=30e-12)


def test_eq_2_20_to_2_22_beam_grows_with_distance():
    a = signal.beam_area_m2(np.array([0.0, 10.0, 100.0]))
    assert a[0] == pytest.approx(np.pi * 2.5e-3 * 1.1e-3)
    assert np.all(np.diff(a) > 0)


def test_appendix_e_regimes_and_specular_geometry():
    assert signal.surface_regime(0.1e-6) == "specular"
    assert signal.surface_regime(2e-6) == "diffuse"
    on = signal.specular_photons_per_pixel(10.0, 0.9, 0.0)
    off = signal.specular_photons_per_pixel(10.0, 0.9, np.radians(5))
    assert on > 0 and off == 0
    assert signal.slope_sigma_rad(1e-6, 2e-6) == pytest.approx(np.arctan(1.0) / np.sqrt(2))


def test_appendix_f_humidity_lowers_the_molecular_mass():
    dry = atm.mean_molecular_mass_u(2000.0, 293.15, 0.0)
    wet = atm.mean_molecular_mass_u(2000.0, 293.15, 1.0)
    assert dry == pytest.approx(0.8 * 28.013 + 0.2 * 31.998)
    assert wet < dry
