"""Background: sunlight (eq. 2.37-2.40), lux and lamps (eq. 2.41-2.43), dark counts (eq. 3.6).

Domains: the sun as a 6000 K blackbody at the top of the atmosphere, attenuated by
Rayleigh scattering only (appendix G; real sea-level spectra are lower, section 2.4.1);
lamps as point sources of uniform intensity inside their cone; an ideal band-pass filter.
"""

from __future__ import annotations

import numpy as np
from scipy.constants import c as C_LIGHT
from scipy.constants import h as H_PLANCK
from scipy.constants import k as K_BOLTZMANN

from stages.models.atmosphere import column_transmission
from stages.models.signal import LASER_WAVELENGTH_M, PIXEL_PITCH_M, photon_energy_j

#: Total solar irradiance at the top of the atmosphere: the middle of ACRIM's 1360..1363
#: W/m^2 (section 2.4.1), which gives the thesis's 1711.4 W/m^2/um at 405 nm.
I_TOP_W_M2 = 1361.5
SUN_TEMPERATURE_K = 6000.0
#: Hot pixels of the thesis's chip (1-based 67, 98, 106, 119; section 3.4), 0-based here.
HOT_PIXELS = (66, 97, 105, 118)


def planck_normalized_per_m(wavelength_m, temperature_k=SUN_TEMPERATURE_K):
    """Blackbody spectrum normalised to unit integral over wavelength, eq. 2.37 (per metre).

    The normalising integral is analytic: (k T / h c)^4 pi^4 / 15.
    """
    lam = np.asarray(wavelength_m, np.float64)
    x = H_PLANCK * C_LIGHT / (lam * K_BOLTZMANN * temperature_k)
    norm = (K_BOLTZMANN * temperature_k / (H_PLANCK * C_LIGHT)) ** 4 * np.pi ** 4 / 15
    return lam ** -5 / np.expm1(x) / norm


def solar_irradiance_top(wavelength_m=LASER_WAVELENGTH_M, i_top_w_m2=I_TOP_W_M2):
    """Spectral irradiance at the top of the atmosphere, W/m^2 per metre, eq. 2.38.

    >>> round(float(solar_irradiance_top()) * 1e-6)  # W/m^2/um at 405 nm (eq. 2.38: 1711.4)
    1711
    """
    return planck_normalized_per_m(wavelength_m) * i_top_w_m2


def solar_irradiance_sea_level(wavelength_m=LASER_WAVELENGTH_M, i_top_w_m2=I_TOP_W_M2,
                               transmission=None):
    """eq. 2.39-2.40: the top-of-atmosphere value times the column transmission (74.20 %).

    >>> round(float(solar_irradiance_sea_level()) * 1e-6)  # eq. 2.40: ~1269.9
    1270
    """
    t = column_transmission() if transmission is None else transmission
    return solar_irradiance_top(wavelength_m, i_top_w_m2) * t


def photon_rate_hz(spectral_irradiance_w_m2_nm, bandwidth_nm=10.0,
                   pixel_area_m2=PIXEL_PITCH_M ** 2, wavelength_m=LASER_WAVELENGTH_M):
    """Photons per second on a pixel through an ideal band-pass filter (section 2.2.2).

    >>> f"{float(photon_rate_hz(1.0)):.3g}"  # 1.0 W/m^2/nm, 10 nm, 24 um pixel: 1.17e10
    '1.17e+10'
    """
    power = np.asarray(spectral_irradiance_w_m2_nm) * bandwidth_nm * pixel_area_m2
    return power / photon_energy_j(wavelength_m)


#: Section 2.2.2: daylight of 100 klx is 1.2 W/m^2/nm at 405 nm outside the atmosphere and
#: ~1.0 W/m^2/nm after it; the one lux conversion of the project (scenes, `tcspc model
#: ambient` and the prediction model), per lux at 405 nm.
W_M2_NM_PER_LUX_405 = 1.0 / 1e5


def lux_to_spectral_irradiance(lux, wavelength_m=LASER_WAVELENGTH_M):
    """W/m^2/nm of daylight of ``lux`` at ``wavelength_m``: the thesis's 1.0 W/m^2/nm per
    100 klx at 405 nm (section 2.2.2), carried to another wavelength by the solar spectrum's
    shape (the 6000 K blackbody of eq. 2.37), so that 405 nm gives the thesis's number.

    >>> float(lux_to_spectral_irradiance(1e5))  # W/m^2/nm at 405 nm
    1.0
    >>> f"{float(photon_rate_hz(lux_to_spectral_irradiance(1e5))):.3g}"  # section 2.2.2
    '1.17e+10'
    """
    shape = planck_normalized_per_m(wavelength_m) / planck_normalized_per_m(LASER_WAVELENGTH_M)
    return np.asarray(lux, np.float64) * W_M2_NM_PER_LUX_405 * shape


def lamp_illuminance_lux(luminous_flux_lm, distance_m, half_angle_deg):
    """Illuminance of a lamp spreading its flux over a cone, eq. 2.41.

    >>> round(float(lamp_illuminance_lux(1.5e6, 10.0, 90.0)))  # eq. 2.42: ~2.389 klx
    2387
    >>> round(float(lamp_illuminance_lux(3200.0, 5.0, 45.0)), 1)  # eq. 2.43
    69.6
    """
    omega = 2 * np.pi * (1 - np.cos(np.radians(half_angle_deg)))
    return np.asarray(luminous_flux_lm, np.float64) / (omega * np.asarray(distance_m) ** 2)


def lamp_band_irradiance_w_m2(illuminance_lux, efficacy_lm_per_w=100.0, band_fraction=0.008):
    """Radiant irradiance of a lamp in the filter band (section 2.4.2: 0.8 % in 400-410 nm)."""
    return np.asarray(illuminance_lux, np.float64) / efficacy_lm_per_w * band_fraction


def dcr_from_counts_hz(counts, window_s, cycles):
    """Dark-count rate from counts in a dark capture, eq. 3.6.

    >>> float(dcr_from_counts_hz(298, 80e-9, 1e6))
    3725.0
    """
    return np.asarray(counts, np.float64) / (window_s * np.asarray(cycles, np.float64))


def dark_count_rates_hz(n_pixels=128, dcr_hz=100.0, hot_pixels=HOT_PIXELS,
                        hot_dcr_hz=5000.0):
    """Per-pixel dark-count rates: ~100 Hz (Table 3.1) with the thesis's hot pixels."""
    rates = np.full(n_pixels, float(dcr_hz))
    hot = [p for p in hot_pixels if p < n_pixels]
    rates[hot] = hot_dcr_hz
    return rates
