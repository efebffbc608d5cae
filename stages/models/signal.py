"""Signal photons per pixel per pulse: collimation (eq. 2.19-2.23), diffuse targets
(eq. 2.25-2.26), and the surface-roughness regimes of appendices D-E.

Domains of validity (stated, and checked where a scene asks for them):

- collimated beam on a mirror (eq. 2.21-2.23): the whole beam returns; valid while the beam
  footprint is the only loss (no lens, uniform power across the ellipse).
- diffuse target (eq. 2.25): the pulse energy returns spread uniformly over a hemisphere
  (2 pi sr), the thesis's worst case; valid for rough surfaces, sigma_h / lambda > 1
  (appendix E), and far enough that the beam is smaller than the target.
- specular spike: sigma_h / lambda < 1 (appendix E); the reflection stays collimated and
  reaches the sensor only at normal incidence (within the beam divergence).
"""

from __future__ import annotations

import numpy as np
from scipy.constants import c as C_LIGHT
from scipy.constants import h as H_PLANCK

#: Table 2.1: the thesis's laser.
LASER_WAVELENGTH_M = 405e-9
LASER_ENERGY_J = 29e-12
BEAM_MAJOR_M, BEAM_MINOR_M = 2.5e-3, 1.1e-3
DIV_MAJOR_RAD, DIV_MINOR_RAD = 0.1e-3, 0.25e-3
PIXEL_PITCH_M = 24e-6


def photon_energy_j(wavelength_m=LASER_WAVELENGTH_M):
    """Energy of one photon, h c / lambda."""
    return H_PLANCK * C_LIGHT / np.asarray(wavelength_m, np.float64)


def photons(energy_j, wavelength_m=LASER_WAVELENGTH_M):
    """Number of photons in an optical energy (eq. 2.2 without the PDE)."""
    return np.asarray(energy_j, np.float64) / photon_energy_j(wavelength_m)


def beam_area_m2(distance_m, beam_major_m=BEAM_MAJOR_M, beam_minor_m=BEAM_MINOR_M,
                 div_major_rad=DIV_MAJOR_RAD, div_minor_rad=DIV_MINOR_RAD):
    """Beam footprint at ``distance_m``, eq. 2.21-2.22 as printed.

    ``d = 2 z tan(theta)`` per axis, area ``pi (d1 + d01)(d2 + d02)``. The thesis calls
    d01 = 2.5 mm and d02 = 1.1 mm semi-axes and takes theta as the divergence that widens
    each semi-axis by 2 z tan(theta); read as 1/e^2 diameters and half-angles the area would
    be 4x smaller. Eq. 2.22 is followed so eq. 2.23's N0 ~ 9.4 at 100 m is reproduced.
    """
    z = np.asarray(distance_m, np.float64)
    d1 = 2 * z * np.tan(div_major_rad)
    d2 = 2 * z * np.tan(div_minor_rad)
    return np.pi * (d1 + beam_major_m) * (d2 + beam_minor_m)


def collimated_photons_per_pixel(distance_m, energy_j=LASER_ENERGY_J,
                                 wavelength_m=LASER_WAVELENGTH_M,
                                 pixel_pitch_m=PIXEL_PITCH_M, **beam):
    """Photons on one pixel from a mirror at ``distance_m`` (eq. 2.23), per pulse.

    >>> round(float(collimated_photons_per_pixel(100.0)), 1)  # eq. 2.23: ~9.4
    9.4
    """
    return pixel_pitch_m ** 2 / beam_area_m2(distance_m, **beam) * photons(energy_j,
                                                                           wavelength_m)


def diffuse_photons_per_pixel(distance_m, reflectivity=1.0, energy_j=LASER_ENERGY_J,
                              wavelength_m=LASER_WAVELENGTH_M, pixel_pitch_m=PIXEL_PITCH_M):
    """Photons on one pixel from a diffuse target (eq. 2.25-2.26), per pulse.

    ``E = S_pitch / (2 pi z^2) * Q_p * R_t``. With the thesis's values (100 m, R = 50 %) this
    gives 2.7e-7 photons; eq. 2.26 prints 1.25e-7, which does not follow from its inputs.

    >>> f"{float(diffuse_photons_per_pixel(100.0, 0.5)):.2e}"
    '2.71e-07'
    """
    z = np.asarray(distance_m, np.float64)
    energy = pixel_pitch_m ** 2 / (2 * np.pi * z * z) * energy_j * np.asarray(reflectivity)
    return photons(energy, wavelength_m)


def slope_sigma_rad(sigma_h_m, correlation_m):
    """Facet-slope spread from height roughness and correlation length, eq. D.4."""
    return np.arctan(2 * np.asarray(sigma_h_m) / np.asarray(correlation_m)) / np.sqrt(2)


def surface_regime(sigma_h_m, wavelength_m=LASER_WAVELENGTH_M) -> str:
    """Which reflection the thesis keeps for a surface (appendix E).

    ``"specular"`` (ideal spike only) for sigma_h / lambda < 1, else ``"diffuse"``.
    """
    return "specular" if float(sigma_h_m) / float(wavelength_m) < 1 else "diffuse"


def specular_photons_per_pixel(distance_m, reflectance, incidence_rad=0.0,
                               energy_j=LASER_ENERGY_J, wavelength_m=LASER_WAVELENGTH_M,
                               pixel_pitch_m=PIXEL_PITCH_M, **beam):
    """Photons on one pixel from a smooth (specular-spike) target, eq. E.7.

    The reflected beam stays collimated (``L_r = R0 L_i``), travelling ``2 z`` out and
    back; it comes back to a sensor beside the laser only when the incidence angle is
    within the beam's divergence (else no photon arrives, section 2.3.2).
    """
    inc = np.abs(np.asarray(incidence_rad, np.float64))
    back = inc <= max(DIV_MAJOR_RAD, DIV_MINOR_RAD) if not beam else inc <= max(
        beam.get("div_major_rad", DIV_MAJOR_RAD), beam.get("div_minor_rad", DIV_MINOR_RAD))
    n = collimated_photons_per_pixel(2 * np.asarray(distance_m, np.float64), energy_j,
                                     wavelength_m, pixel_pitch_m, **beam)
    return np.where(back, n * np.asarray(reflectance, np.float64), 0.0)


def signal_detections_per_cycle(photons_per_pixel, pde=0.25, fill_factor=0.049,
                                transmission=1.0):
    """M of eq. 2.2: photons on the pixel times fill factor, PDE and path transmission."""
    return (np.asarray(photons_per_pixel, np.float64) * fill_factor * pde
            * np.asarray(transmission, np.float64))
