"""Calibration, online LSB tracking: each TDC's LSB measured from an ordinary range
capture's uniform background (its returns masked), against what the calibration expects.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.calibration.density import INL_RMS_FACTOR, density_test, implausible_reset_peak
from stages.calibration.timescale import light_level


def signal_codes(hits: np.ndarray, dilate: int = 8, z: float = 6.0) -> np.ndarray:
    """(n_tdc, 512) mask of codes that hold more than uniform background: a range
    capture's returns (counts above a running median by ``z`` Poisson sigmas), widened by
    ``dilate`` codes on each side."""
    from scipy.ndimage import maximum_filter1d, median_filter

    h = np.asarray(hits, np.float64)
    base = median_filter(h, size=(1, 41), mode="nearest")
    peak = h > base + z * np.sqrt(np.maximum(base, 1.0))
    return maximum_filter1d(peak, size=2 * dilate + 1, axis=1)


#: The online LSB estimate of a TDC is not trusted when its own statistical error (the
#: reset peak's place over the background's widths: LSB x sqrt(1/6) / sqrt(hits)) exceeds
#: this, or when it lies further than ``TRACK_MAX_REL`` from the calibration's LSB at the
#: light (the density tests' LSBs span a few per cent over their light levels: a quarter
#: is a misplaced reset peak, never a drift).
TRACK_MAX_SIGMA_PS = 10.0
TRACK_MAX_REL = 0.25


@dataclass(frozen=True)
class Tracking:
    """The LSB measured from a range capture's background, against a calibration."""

    lsb_s: np.ndarray          #: measured now (NaN where the background is too thin)
    expected_s: np.ndarray     #: the calibration's LSB at this capture's light (eq. 5.1)
    light: float               #: detections per pixel per cycle of this capture
    hits: np.ndarray
    #: the estimate's own statistical error (NaN where not measured)
    sigma_s: np.ndarray | None = None
    #: per TDC why its estimate cannot be trusted ("" where it can, or was not measured)
    why: tuple = ()

    @property
    def flagged(self) -> np.ndarray:
        """TDCs whose estimate was measured but cannot be trusted (``why`` says why)."""
        n = int(np.asarray(self.lsb_s).size)
        return np.array([bool(w) for w in self.why] if self.why else [False] * n, bool)

    @property
    def drift_ps(self) -> np.ndarray:
        """Measured minus expected; NaN where not measured or not trusted (``flagged``)."""
        return np.where(self.flagged, np.nan, (self.lsb_s - self.expected_s) * 1e12)


def track_lsb(hits: np.ndarray, cycles: np.ndarray, window_s: float,
              expected_lsb_s: np.ndarray, min_hits: int = 1000,
              artifacts: np.ndarray | None = None) -> Tracking:
    """Measure each TDC's LSB from the uniform background of an ordinary range capture
    (its signal peaks masked) and compare it with what the calibration expects.
    ``artifacts``: the artifact words by code, where counted (see :func:`density_test`).
    A TDC's estimate is flagged (``why``, left out of ``drift_ps``) when its reset peak is
    not where the light ends (:func:`implausible_reset_peak`), its own error exceeds
    ``TRACK_MAX_SIGMA_PS``, or it is ``TRACK_MAX_REL`` or more from the expected LSB."""
    h = np.asarray(hits, np.float64)
    res = density_test(h, cycles, window_s, min_hits, exclude=signal_codes(h),
                       artifacts=artifacts)
    light = light_level(h, cycles)
    lsb = np.where(res.ok, res.lsb_s, np.nan)
    expected = np.broadcast_to(np.asarray(expected_lsb_s, np.float64), lsb.shape)
    sigma = lsb * INL_RMS_FACTOR / np.sqrt(np.maximum(res.hits, 1.0))
    why = implausible_reset_peak(h, res)
    for t in np.flatnonzero(np.isfinite(lsb) & (why == "")):
        ps, exp_ps = lsb[t] * 1e12, expected[t] * 1e12
        if sigma[t] * 1e12 > TRACK_MAX_SIGMA_PS:
            why[t] = (f"LSB {ps:.0f} +- {sigma[t] * 1e12:.0f} ps: uncertain beyond "
                      f"{TRACK_MAX_SIGMA_PS:g} ps")
        elif np.isfinite(exp_ps) and abs(ps / exp_ps - 1) >= TRACK_MAX_REL:
            why[t] = (f"LSB {ps:.0f} ps against {exp_ps:.0f} ps expected: implausible, not "
                      "a drift")
    return Tracking(lsb, np.asarray(expected_lsb_s), light, res.hits, sigma,
                    tuple(why.tolist()))
