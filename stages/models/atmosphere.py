"""Rayleigh attenuation at 405 nm (eq. 2.27-2.36, appendices F-G).

Valid where Rayleigh scattering dominates (clear air, visible/near-UV light; no aerosols,
fog or absorption lines) and, for the altitude forms, in an isothermal exponential
atmosphere of the given temperature.
"""

from __future__ import annotations

import numpy as np
from scipy.constants import g as G_EARTH
from scipy.constants import k as K_BOLTZMANN
from scipy.constants import physical_constants

ATOMIC_MASS_KG = physical_constants["atomic mass constant"][0]
#: Rayleigh cross section at 405 nm, 1.6e-26 cm^2 (appendix G, [36]).
RAYLEIGH_405_M2 = 1.6e-30
#: Sea-level number density used in appendix G: 2.55e19 / cm^3.
N0_SEA_LEVEL_M3 = 2.55e25
P_SEA_LEVEL_PA = 101325.0
M_H2O_U, M_N2_U, M_O2_U = 18.015, 28.013, 31.998


def number_density_m3(pressure_pa=P_SEA_LEVEL_PA, temperature_k=288.15):
    """N = P / (k T), eq. 2.33."""
    return np.asarray(pressure_pa, np.float64) / (K_BOLTZMANN * np.asarray(temperature_k))


def transmission(distance_m, pressure_pa=P_SEA_LEVEL_PA, temperature_k=288.15,
                 cross_section_m2=RAYLEIGH_405_M2):
    """One-way transmission over a horizontal path, eq. 2.34: exp(-sigma L P / (k T)).

    >>> round(float(transmission(200.0, temperature_k=273.0)) * 100, 2)  # section 2.3.3
    99.14
    """
    return np.exp(-cross_section_m2 * np.asarray(distance_m, np.float64)
                  * number_density_m3(pressure_pa, temperature_k))


def pressure_pa(altitude_m):
    """Barometric pressure at altitude, eq. F.5.

    >>> round(float(pressure_pa(2000.0)))  # the thesis: 79495 Pa
    79495
    """
    return P_SEA_LEVEL_PA * (1 - 2.25577e-5 * np.asarray(altitude_m, np.float64)) ** 5.25588


def saturation_vapour_pressure_hpa(temperature_k, pressure_hpa=1013.25):
    """Saturated water-vapour pressure over water, eq. F.2 (T in kelvin here)."""
    tc = np.asarray(temperature_k, np.float64) - 273.15
    return (1.0007 + 3.46e-6 * np.asarray(pressure_hpa)) * 6.1121 * np.exp(
        17.502 * tc / (240.97 + tc))


def mean_molecular_mass_u(altitude_m=0.0, temperature_k=288.15, relative_humidity=0.0):
    """Mean molecular mass of N2/O2 (80/20, appendix F) plus water vapour, in u.

    eq. F.9-F.11 take dry air as 80 % N2 and 20 % O2, which weighs 28.81 u, and water
    18.02 u, giving ``28.81 - 10.80 x`` for a water fraction x; the printed eq. F.11
    (29.6 - 11.6 x) does not follow from those inputs, and eq. F.12 mixes hPa and Pa in
    the ratio. The physics is followed here, with both pressures in hPa.
    """
    p_hpa = pressure_pa(altitude_m) / 100
    x = np.asarray(relative_humidity) * saturation_vapour_pressure_hpa(temperature_k,
                                                                        p_hpa) / p_hpa
    m_dry = 0.8 * M_N2_U + 0.2 * M_O2_U
    return (1 - x) * m_dry + x * M_H2O_U


def scale_height_m(temperature_k=250.0, molecular_mass_u=28.964):
    """H = k T / (m g), eq. G.1.

    >>> round(float(scale_height_m()))  # CODATA k and g; appendix G's 1.38e-23, 9.81: 7314.5
    7318
    """
    return K_BOLTZMANN * np.asarray(temperature_k) / (
        np.asarray(molecular_mass_u) * ATOMIC_MASS_KG * G_EARTH)


def transmission_at_altitude(distance_m, altitude_m, temperature_k=288.15,
                             relative_humidity=0.0, n0_m3=N0_SEA_LEVEL_M3,
                             cross_section_m2=RAYLEIGH_405_M2):
    """Horizontal-path transmission at altitude, eq. 2.35-2.36: density N0 exp(-z / H)."""
    h = scale_height_m(temperature_k, mean_molecular_mass_u(altitude_m, temperature_k,
                                                            relative_humidity))
    n = n0_m3 * np.exp(-np.asarray(altitude_m, np.float64) / h)
    return np.exp(-cross_section_m2 * np.asarray(distance_m, np.float64) * n)


def column_transmission(top_m=96_560.0, temperature_k=250.0, molecular_mass_u=28.964,
                        n0_m3=N0_SEA_LEVEL_M3, cross_section_m2=RAYLEIGH_405_M2):
    """Vertical transmission from the top of the atmosphere to sea level, eq. G.2.

    The product of eq. G.2 over 1 m slabs is the exponential of the column integral,
    ``sigma N0 H (1 - exp(-top / H))`` (its exponent as printed lacks g; H = kT/(mg) is
    used). 74.20 % with the thesis's values.

    >>> round(float(column_transmission()) * 100, 1)
    74.2
    """
    h = scale_height_m(temperature_k, molecular_mass_u)
    return np.exp(-cross_section_m2 * n0_m3 * h * (1 - np.exp(-top_m / h)))
