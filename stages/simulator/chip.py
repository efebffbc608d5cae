"""The simulated chip: per-TDC LSB, INL/DNL, jitter, second-stage codes and the artifact.

A TDC measures ``tau = window_end - t_start`` (reversed timing) and outputs the first-stage
code ``k`` with ``B[k] <= tau < B[k+1]``, where ``B[k] = LSB * (k + INL[k])``. The code
counter has 9 bits, so codes wrap at 512.

- LSB: ``lsb0`` (200-205 ps, Table 3.2) plus up to ``lsb_light_ps`` (40 ps) as the chip's
  light grows (IR drop, section 5.1), most in the middle of the array:
  ``lsb = lsb0 + lsb_light_ps * profile(tdc) * (1 - exp(-n / n_sat))`` with n the
  detections per pixel per cycle of the whole chip (eq. 5.1).
- INL: a pattern that repeats every VCO cycle of 8 codes (identical for all TDCs, scaled per
  TDC), a slow bow, and a small random part per code; DNL < 0.6 LSB, |INL| < 3 LSB.
- TDC jitter: Gaussian, 1.2 LSB FWHM (section 3.2).
- Second stage: ``D2nd`` in ``[n_min, n_max]`` encodes the fine position in the VCO cycle,
  starting at ``n_th`` and wrapping at ``n_max``, so that ``n_th`` is the smallest D2nd
  seen with P1st = 0 and ``pdm`` the smallest with P1st = 4 (section 3.2). Eq. 3.4-3.5
  (the two-stage code) are not used by this project, which ranges on D1st only.
- Artifact (section 3.4): spurious STARTs at a few fixed codes with D2nd above n_max, with
  a per-cycle probability constant over the first 60 TDCs, decreasing, then constant.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.words import N_CODES, N_CODES_2ND
from stages.models.tcspc import sigma_from_fwhm

_PATTERN8 = np.array([0.25, -0.1, 0.2, -0.3, 0.15, -0.2, 0.1, -0.1])  # INL per phase, LSB


@dataclass(frozen=True)
class Chip:
    """Per-TDC parameters of one simulated chip (arrays of length n_tdc unless noted)."""

    lsb0_ps: np.ndarray
    lsb_light_ps: float
    light_profile: np.ndarray
    n_sat: float
    inl_lsb: np.ndarray          #: (n_tdc, 513): INL at each code boundary, INL[0] = 0
    jitter_fwhm_lsb: float
    n_min: np.ndarray
    n_max: np.ndarray
    n_th: np.ndarray
    artifact_prob: np.ndarray    #: per cycle
    artifact_codes: np.ndarray   #: (n_art,) codes where the artifact lands

    @property
    def n_tdc(self) -> int:
        return int(self.lsb0_ps.size)

    @property
    def width(self) -> np.ndarray:
        """Second-stage codes per VCO cycle, n_max - n_min + 1."""
        return self.n_max - self.n_min + 1

    def min_d2nd(self, p1st: int) -> np.ndarray:
        """Smallest D2nd a hit with this P1st can have (the wrap at n_max included)."""
        w = self.width
        out = np.empty(self.n_tdc, np.int64)
        for t in range(self.n_tdc):  # once per chip, over 128 TDCs
            # mods floor((p1st + f) * w / 8) for f in [0, 1)
            m = np.arange(p1st * w[t] // 8, -(-(p1st + 1) * w[t] // 8))
            d2 = self.n_th[t] + m
            out[t] = np.where(d2 > self.n_max[t], d2 - w[t], d2).min()
        return out

    @property
    def pdm(self) -> np.ndarray:
        """Smallest D2nd when P1st = 4 (what a density test measures as PDM)."""
        return self.min_d2nd(4)

    def lsb_ps(self, detections_per_pixel_per_cycle: float) -> np.ndarray:
        """LSB of every TDC at a light level (eq. 5.1's n)."""
        n = max(float(detections_per_pixel_per_cycle), 0.0)
        return self.lsb0_ps + self.lsb_light_ps * self.light_profile * -np.expm1(-n / self.n_sat)

    def boundaries_s(self, detections_per_pixel_per_cycle: float) -> np.ndarray:
        """(n_tdc, 513) code boundaries in seconds of tau."""
        lsb = self.lsb_ps(detections_per_pixel_per_cycle)[:, None] * 1e-12
        return lsb * (np.arange(N_CODES + 1)[None, :] + self.inl_lsb)

    def dnl_lsb(self) -> np.ndarray:
        """(n_tdc, 512) DNL of every code."""
        return np.diff(self.inl_lsb, axis=1)

    def jitter_s(self, detections_per_pixel_per_cycle: float) -> np.ndarray:
        return sigma_from_fwhm(self.jitter_fwhm_lsb
                               * self.lsb_ps(detections_per_pixel_per_cycle) * 1e-12)

    def window_truth(self, detections_per_pixel_per_cycle: float, window_s: float):
        """The LSB as the window over the code span, and the INL against it.

        ``x_T`` is where tau = T falls on the code axis; ``lsb = T / x_T``;
        ``inl[k] = B[k] / lsb - k``. This is what a density test measures (the INL bow
        beyond the window is invisible to it).
        """
        b = self.boundaries_s(detections_per_pixel_per_cycle)
        k = np.array([np.searchsorted(row, window_s, side="right") - 1 for row in b])
        rows = np.arange(self.n_tdc)
        x_t = k + (window_s - b[rows, k]) / (b[rows, k + 1] - b[rows, k])
        lsb = window_s / x_t
        inl = b[:, :N_CODES] / lsb[:, None] - np.arange(N_CODES)[None, :]
        return lsb, x_t, inl

    def truth(self, detections_per_pixel_per_cycle: float, window_s: float = 80e-9) -> dict:
        """What a calibration should find, for the capture's sidecar."""
        lsb_w, x_t, inl_w = self.window_truth(detections_per_pixel_per_cycle, window_s)
        return {
            "lsb_window_ps": np.round(lsb_w * 1e12, 6).tolist(),
            "x_t": np.round(x_t, 6).tolist(),
            "inl_window_lsb": np.round(inl_w, 5).tolist(),
            "lsb_ps": np.round(self.lsb_ps(detections_per_pixel_per_cycle), 6).tolist(),
            "lsb0_ps": np.round(self.lsb0_ps, 6).tolist(),
            "lsb_light_ps": self.lsb_light_ps, "n_sat": self.n_sat,
            "light_profile": np.round(self.light_profile, 6).tolist(),
            "inl_lsb": np.round(self.inl_lsb[:, :N_CODES], 5).tolist(),
            "n_min": self.n_min.tolist(), "n_max": self.n_max.tolist(),
            "n_th": self.n_th.tolist(), "pdm": self.pdm.tolist(),
            "artifact_prob": self.artifact_prob.tolist(),
            "artifact_codes": self.artifact_codes.tolist(),
            "jitter_fwhm_lsb": self.jitter_fwhm_lsb,
        }


def make_chip(n_tdc: int = 128, rng: np.random.Generator | int | None = 0, *,
              lsb_range_ps=(200.0, 205.0), lsb_light_ps: float = 40.0, n_sat: float = 0.25,
              inl_scale: float = 1.0, jitter_fwhm_lsb: float = 1.2,
              artifact_rate: float = 2.9e-4, artifact_codes=(41, 169, 297)) -> Chip:
    """A chip with the thesis's characteristics, drawn from ``rng``.

    ``inl_scale = 0`` gives an ideal TDC (uniform codes); ``artifact_rate = 0`` none.

    Examples
    --------
    >>> chip = make_chip(rng=1)
    >>> bool(np.abs(chip.dnl_lsb()).max() < 0.6 and np.abs(chip.inl_lsb).max() < 3)
    True
    """
    rng = np.random.default_rng(rng)
    t = np.arange(n_tdc)
    lsb0 = rng.uniform(*lsb_range_ps, n_tdc)
    profile = 0.5 + 0.5 * np.sin(np.pi * (t + 0.5) / n_tdc)  # most in the middle
    k = np.arange(N_CODES + 1)
    scale = inl_scale * rng.uniform(0.7, 1.0, n_tdc)[:, None]
    periodic = _PATTERN8[k % 8] - _PATTERN8[0]
    bow = 1.2 * np.sin(np.pi * k / N_CODES)[None, :] * rng.uniform(-1, 1, n_tdc)[:, None]
    rand = np.cumsum(rng.normal(0, 0.04, (n_tdc, N_CODES + 1)), axis=1)
    rand -= np.linspace(0, 1, N_CODES + 1)[None, :] * rand[:, -1:]  # pinned at both ends
    inl = scale * (periodic[None, :] + bow + rand)
    inl -= inl[:, :1]
    # keep every code's width positive and the DNL within spec
    dnl = np.clip(np.diff(inl, axis=1), -0.55, 0.55)
    inl = np.concatenate([np.zeros((n_tdc, 1)), np.cumsum(dnl, axis=1)], axis=1)
    n_min = rng.integers(12, 28, n_tdc)
    width = rng.integers(110, 150, n_tdc)
    n_max = n_min + width - 1
    # n_th leaves room for the P1st = 0 eighth below the wrap: then n_th is min D2nd there
    n_th = n_min + rng.integers(0, width - width // 8 - 1)
    prob = np.where(t < 60, 1.0, np.where(t < 100, 1 - 0.8 * (t - 60) / 40, 0.2))
    return Chip(lsb0, lsb_light_ps, profile, n_sat, inl, jitter_fwhm_lsb, n_min, n_max,
                n_th, artifact_rate * prob, np.asarray(artifact_codes, np.int64))


def second_stage(chip: Chip, tdc: np.ndarray, code: np.ndarray, frac: np.ndarray) -> np.ndarray:
    """D2nd of hits: the fine position ((code % 8) + frac) / 8 in the VCO cycle, on the
    second stage's scale from n_th, wrapping at n_max back to n_min."""
    w = chip.width[tdc]
    mod = np.minimum(np.floor(((code % 8) + frac) / 8 * w), w - 1).astype(np.int64)
    d2 = chip.n_th[tdc] + mod
    return np.where(d2 > chip.n_max[tdc], d2 - w, d2)


def artifact_d2nd(chip: Chip, tdc: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """D2nd of artifact words: above n_max (section 3.4)."""
    lo = chip.n_max[tdc] + 1
    return lo + np.floor(rng.random(tdc.size) * (N_CODES_2ND - lo)).astype(np.int64)
