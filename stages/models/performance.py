"""Performance prediction: the probability P of detecting the peak (eq. 2.44-2.48).

``h(TOF') - a_h sqrt(h) > b(TOF') + a_b sqrt(b)`` with ``a_h = sqrt(2) erfinv(P)`` and
``a_b = sqrt(2) erfinv(1 - (1 - P) / (T0/dt - 1))``: the largest P that satisfies it is the
prediction. ``h`` is the expected count at the histogram's peak, ``b`` the expected count
that background alone puts in that bin (with its pile-up). Without gating the peak is the
highest bin of the whole histogram: when that is not the signal (background pile-up at the
window's start wins), the prediction is P = 0, as in the thesis's Figure 2.13.

Table 2.2 is sparse: a blank carries the value from the column to its left (columns 6/7,
4/5 and 3/4 restate values that would need no restating otherwise). So configurations 2-7
each change one parameter of configuration 1, and 8 is the thesis's own system.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np
from scipy.constants import c as C_LIGHT
from scipy.special import ndtri

from stages.models.noise import lux_to_spectral_irradiance, photon_rate_hz
from stages.models.signal import (
    LASER_WAVELENGTH_M,
    PIXEL_PITCH_M,
    photons,
)
from stages.models.tcspc import (
    _intensities,
    first_photon_histogram,
    histogram_from_intensities,
)

#: Photons/s per lux on a 24 um pixel through a 10 nm filter at 405 nm: the one lux
#: conversion (:func:`stages.models.noise.lux_to_spectral_irradiance`, section 2.2.2).
AMBIENT_PHOTONS_PER_LUX = float(photon_rate_hz(lux_to_spectral_irradiance(1.0)))


@dataclass(frozen=True)
class SystemSpec:
    """What Table 2.2 varies, and what it holds fixed. SI units."""

    pulse_energy_j: float = 100e-9
    ambient_lux: float = 100.0
    samples: int = 10_000
    tdc_resolution_s: float = 200e-12
    pde: float = 0.02
    jitter_s: float = 200e-12
    window_s: float = 500e-9        # the ungated window (appendix B: 500 ns)
    gate_s: float = 50e-9           # the gated window (Figure 2.18b)
    reflectivity: float = 1.0       # footnote of section 2.5.2
    wavelength_m: float = LASER_WAVELENGTH_M
    pixel_pitch_m: float = PIXEL_PITCH_M
    dark_count_hz: float = 0.0

    def signal_per_cycle(self, distance_m):
        """M: the footnote's N = N0 * S_pitch / (2 pi x^2) diffuse return, times PDE."""
        x = np.asarray(distance_m, np.float64)
        n0 = photons(self.pulse_energy_j, self.wavelength_m)
        return n0 * self.pixel_pitch_m ** 2 / (2 * np.pi * x * x) * self.reflectivity * self.pde

    @property
    def background_hz(self) -> float:
        """Detected background rate: ambient photons times PDE, plus dark counts."""
        scale = (self.pixel_pitch_m / PIXEL_PITCH_M) ** 2
        return (self.ambient_lux * AMBIENT_PHOTONS_PER_LUX * scale * self.pde
                + self.dark_count_hz)


def _table_2_2() -> tuple[SystemSpec, ...]:
    c1 = SystemSpec()
    return (c1, replace(c1, jitter_s=800e-12), replace(c1, pde=0.08),
            replace(c1, tdc_resolution_s=50e-12), replace(c1, samples=40_000),
            replace(c1, ambient_lux=400.0), replace(c1, pulse_energy_j=400e-9),
            replace(c1, pulse_energy_j=29e-12, samples=40_000, pde=0.013, jitter_s=666e-12))


TABLE_2_2 = _table_2_2()


def alpha_h(p):
    """eq. 2.45: sqrt(2) erfinv(P) = ndtri((1 + P) / 2)."""
    return ndtri((1 + np.asarray(p, np.float64)) / 2)


def alpha_b(p, n_bins):
    """eq. 2.46 on the stable side: sqrt(2) erfinv(1 - q) = -ndtri(q / 2)."""
    q = (1 - np.asarray(p, np.float64)) / (np.asarray(n_bins, np.float64) - 1)
    return -ndtri(q / 2)


def detection_probability(h, b, n_bins, iterations: int = 60):
    """The largest P in [0, 1) satisfying eq. 2.44 (vectorised bisection); 0 if none does.

    >>> round(float(detection_probability(400.0, 100.0, 400)), 3)
    1.0
    >>> float(detection_probability(100.0, 100.0, 400))
    0.0
    """
    h = np.asarray(h, np.float64)
    b = np.asarray(b, np.float64)

    def margin(p):
        return h - alpha_h(p) * np.sqrt(h) - b - alpha_b(p, n_bins) * np.sqrt(b)

    lo = np.zeros(np.broadcast(h, b).shape)
    hi = np.ones_like(lo) - 1e-15
    ok_any = margin(lo) > 0
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        good = margin(mid) > 0
        lo = np.where(good, mid, lo)
        hi = np.where(good, hi, mid)
    return np.where(ok_any, lo, 0.0)


def _expected_counts(spec: SystemSpec, tof_in_window, window_s):
    """Expected counts per bin, and the background-only share of each bin."""
    sigma = spec.jitter_s
    m = spec.signal_per_cycle(tof_in_window[1])
    bg = spec.background_hz
    intens = _intensities(m, tof_in_window[0], sigma, bg, window_s, spec.tdc_resolution_s,
                          0.0)
    log_dl = intens[1]
    h = histogram_from_intensities(*intens)
    counts = spec.samples * h.p
    # the background's share of each bin's first detections: bg dt / dL of the bin
    dl = np.exp(log_dl)
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(dl > 0, bg * spec.tdc_resolution_s / dl, 1.0)
    return counts, counts * share


def _predict_once(spec: SystemSpec, x: np.ndarray, gated: bool,
                  offset_bins: float) -> dict[str, np.ndarray]:
    tof = 2 * x / C_LIGHT
    window = spec.gate_s if gated else spec.window_s
    t_in = (np.full_like(tof, window / 2) if gated else tof) + offset_bins * spec.tdc_resolution_s
    counts, noise = _expected_counts(spec, (t_in, x), window)
    n_bins = counts.shape[-1]
    peak = np.argmax(counts, axis=-1)
    rows = np.arange(x.size)
    h, b = counts[rows, peak], noise[rows, peak]
    centre = (peak + 0.5) * spec.tdc_resolution_s
    on_signal = np.abs(centre - t_in) <= 3 * spec.jitter_s + spec.tdc_resolution_s
    inside = t_in < window
    p = np.where(on_signal & inside, detection_probability(h, b, n_bins), 0.0)
    return {"p_detect": p, "peak_count": h, "noise_count": b,
            "on_signal": on_signal.astype(np.float64)}


def predict(spec: SystemSpec, distance_m, gated: bool = False,
            phases: int = 8) -> dict[str, np.ndarray]:
    """P of detecting the peak against distance, with the count figures behind it.

    Without gating the window opens at the laser pulse (TOF = 2 x / c inside a window of
    ``spec.window_s``); with gating a window of ``spec.gate_s`` is centred on the TOF.
    Where the pulse falls on the TDC's bin grid is unknown, so every figure is averaged
    over ``phases`` evenly spaced sub-bin offsets (``phases=1`` shows the raw ripple).
    """
    x = np.atleast_1d(np.asarray(distance_m, np.float64))
    runs = [_predict_once(spec, x, gated, k / phases) for k in range(phases)]
    out = {k: np.mean([r[k] for r in runs], axis=0) for k in runs[0]}
    out["on_signal"] = out["on_signal"] > 0.5
    out["distance_m"] = x
    out["m_signal"] = spec.signal_per_cycle(x)
    return out


def table_2_2_rows(distance_m) -> list[dict]:
    """Every configuration of Table 2.2 against distance, gated and not, as rows."""
    rows = []
    for i, spec in enumerate(TABLE_2_2, start=1):
        for gated in (False, True):
            r = predict(spec, distance_m, gated)
            for k in range(r["distance_m"].size):
                rows.append({"config": i, "gated": gated,
                             **{f: (float(v[k]) if v.dtype != bool else bool(v[k]))
                                for f, v in r.items()},
                             **{f"spec_{k2}": v2 for k2, v2 in asdict(spec).items()}})
    return rows


def moving_target_histogram(spec: SystemSpec, distance_m, velocity_m_s,
                            sample_rate_hz=1e6, window_s=None, samples=None):
    """Expected histogram of a target whose range changes at ``velocity_m_s`` (Figure 2.16).

    Sample i sees TOF ``2 (d + v i / f) / c``: the round trip, so the spread over a capture
    is twice the distance travelled over c (the thesis's section 2.6 states the one-way
    distance). Positive velocity is receding (TOF grows). Returns (edges_s, counts).
    """
    n = int(samples or spec.samples)
    window = window_s or spec.gate_s
    t = np.arange(n) / sample_rate_hz
    tof = 2 * (distance_m + velocity_m_s * t) / C_LIGHT
    t_in = tof - 2 * distance_m / C_LIGHT + window / 2   # gate centred on the first sample
    m = float(spec.signal_per_cycle(distance_m))
    h = first_photon_histogram(m, t_in, spec.jitter_s, spec.background_hz, window,
                               spec.tdc_resolution_s)
    return h.edges_s, h.p.sum(axis=0)


def measure_detection(spec: SystemSpec, distance_m, gated: bool = False, runs: int = 200,
                      rng: np.random.Generator | int = 0, tolerance_lsb: float = 2.0
                      ) -> np.ndarray:
    """P measured the way section 2.5.3 measured it, on histograms drawn from the model.

    At each distance, ``runs`` range detections of ``spec.samples`` cycles, each with its
    own sub-bin phase: the peak is the histogram's highest bin, and a detection counts when
    the peak's centre lies within ``tolerance_lsb`` LSB of the true time (the thesis's
    +/- 2 LSB). Returns the fraction per distance, to set beside :func:`predict`.
    """
    rng = np.random.default_rng(rng)
    x = np.atleast_1d(np.asarray(distance_m, np.float64))
    window = spec.gate_s if gated else spec.window_s
    b = spec.tdc_resolution_s
    out = np.empty(x.size)
    for i, xi in enumerate(x):
        tof = 2 * xi / C_LIGHT
        t_in = (window / 2 if gated else tof) + rng.uniform(0, 1, runs) * b
        if not gated and tof >= window:
            out[i] = 0.0
            continue
        m = float(spec.signal_per_cycle(xi))
        intens = _intensities(m, t_in, spec.jitter_s, spec.background_hz, window, b, 0.0)
        h = histogram_from_intensities(*intens)
        p = np.concatenate([h.p, h.p_none[:, None]], axis=1)
        counts = rng.multinomial(spec.samples, p / p.sum(axis=1, keepdims=True))[:, :-1]
        peak = np.argmax(counts, axis=1)
        out[i] = float(np.mean(np.abs((peak + 0.5) * b - t_in) <= tolerance_lsb * b))
    return out
