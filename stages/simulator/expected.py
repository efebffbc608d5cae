"""Expected (noise-free) histograms of a density test on a chip: what a capture of
uniform light would hold on average, without the counting noise.

A calibration method tested on these must give the chip's truth: whatever error is left is
the method's bias, not statistics (issue 33). The model is the simulator's: a START is the
first photon of the cycle; one in the reset period is the window's beginning (tau = T, plus
the chip's offset), one in the window is at ``tau = T - t``; every START is blurred by the
TDC's Gaussian jitter (the reset period's by :meth:`Chip.reset_jitter_s`) and falls in the
code whose boundaries (``chip.boundaries_s``) hold it, below code 0 into code 0, beyond
the last boundary into the last code. Artifacts and dark counts are left out.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from schemas.constants import N_CODES
from stages.simulator.chip import Chip

#: Steps of the window's time per LSB in the integral over the STARTs' times.
STEPS_PER_LSB = 40


def expected_density_hits(chip: Chip, light: float, cycles: float, window_s: float = 80e-9,
                          reset_ns: float | None = None) -> np.ndarray:
    """(n_tdc, 512) expected counts of a density test of ``cycles`` cycles at ``light``
    detections per pixel per cycle (eq. 5.1's n: every START, reset peak included, over
    the cycles), the chip's LSB at that light."""
    return expected_hits(chip, light, cycles, window_s, reset_ns=reset_ns)


def expected_hits(chip: Chip, light: float, cycles: float, window_s: float = 80e-9,
                  signal=None, tau_s=None, pulse_sigma_s: float = 0.0,
                  reset_ns: float | None = None) -> np.ndarray:
    """(n_tdc, 512) expected counts of a capture of ``cycles`` cycles: uniform light of
    ``light`` detections per pixel per cycle (as :func:`expected_density_hits`: the
    ambient light alone) and, where ``signal`` (n_tdc,) is given, a return of that many
    signal detections per cycle at ``tau_s`` (n_tdc,), a Gaussian pulse of
    ``pulse_sigma_s`` (the TDC's jitter comes on top), with its pile-up. The chip's LSB is
    the one at the capture's own light (every START over the TDCs and the cycles)."""
    reset_s = (chip.reset_ns if chip.reset_ns is not None
               else (20.0 if reset_ns is None else reset_ns)) * 1e-9
    # the photon rate giving ``light`` STARTs a cycle over the reset period and the window
    rate = -np.log1p(-min(float(light), 1 - 1e-12)) / (reset_s + window_s)
    n = chip.n_tdc
    m = np.zeros(n) if signal is None else np.broadcast_to(np.asarray(signal, float), (n,))
    t0 = np.zeros(n) if tau_s is None else np.broadcast_to(np.asarray(tau_s, float), (n,))
    ps = max(float(pulse_sigma_s), 1e-15)
    lsb = float(np.median(chip.lsb_ps(light))) * 1e-12
    n_steps = int(np.ceil(window_s / lsb * STEPS_PER_LSB))
    t = (np.arange(n_steps) + 0.5) * (window_s / n_steps)   # tau, midpoints over [0, T]
    dt = window_s / n_steps
    reset_mass = -np.expm1(-rate * reset_s)
    # density of the first START at tau (no photon in the reset period nor at higher tau:
    # those come first)
    dens = np.empty((n, n_steps))
    for i in range(n):
        above = (rate * (window_s - t)
                 + m[i] * (ndtr((window_s - t0[i]) / ps) - ndtr((t - t0[i]) / ps)))
        r = rate + m[i] * np.exp(-0.5 * ((t - t0[i]) / ps) ** 2) / (ps * np.sqrt(2 * np.pi))
        dens[i] = np.exp(-rate * reset_s) * r * np.exp(-above) * dt
    n_light = float(np.mean(dens.sum(axis=1) + reset_mass))
    bounds = chip.boundaries_s(n_light)                     # (n_tdc, 513)
    jit = chip.jitter_s(n_light)
    jit_r = chip.reset_jitter_s(n_light)
    out = np.empty((n, N_CODES))
    tau_reset = window_s + chip.reset_offset_ps * 1e-12
    blur = _Blur(N_CODES - 1, t)                             # reused by every TDC
    for i in range(n):  # once per TDC; the inner work is vectorised
        b = bounds[i, 1:N_CODES]                            # the inner boundaries
        cdf = (blur(b, jit[i]) @ dens[i]
               + reset_mass * ndtr((b - tau_reset) / jit_r[i]))
        total = dens[i].sum() + reset_mass
        out[i] = np.diff(np.concatenate([[0.0], cdf, [total]]))
    return np.clip(out, 0.0, None) * float(cycles)


#: Where ndtr is 1.0 and 0.0 to the bit (it is from 8.3 and below -37.7): the jitter's
#: Gaussian is evaluated between these only.
_ONE_ABOVE, _ZERO_BELOW = 9.5, -40.5


class _Blur:
    """``ndtr((b[:, None] - t[None, :]) / jit)`` (the share of a START at ``t`` that the
    jitter puts below each boundary ``b``) for one TDC after another on the same times
    ``t`` (increasing), in one (511, len(t)) array: ndtr is evaluated only where it is
    neither 1.0 nor 0.0 in float64, a band of ~50 jitters (~1,000 of the ~20,000 times)
    a boundary, the rest filled with 1.0 below it and 0.0 above; from one TDC to the next
    only the columns between the two TDCs' bands are written again. The same array to the
    bit, so the counts that follow (and every Poisson draw of them) are the same; the
    full evaluation (511 x ~20,000 ndtr a TDC) took ~0.2 s a TDC."""

    def __init__(self, n_rows: int, t: np.ndarray):
        self.t = t
        self.a = np.zeros((n_rows, t.size))
        self.lo = np.zeros(n_rows, np.int64)  # a row's 1.0s end and its band begins here
        self.hi = np.full(n_rows, t.size, np.int64)  # ... and its 0.0s begin here

    def __call__(self, b: np.ndarray, jit: float) -> np.ndarray:
        t, a = self.t, self.a
        lo = np.searchsorted(t, b - _ONE_ABOVE * jit)       # t[:lo] give 1.0
        hi = np.searchsorted(t, b - _ZERO_BELOW * jit)      # t[hi:] give 0.0
        for k in range(b.size):
            s, e, was_s, was_e = lo[k], hi[k], self.lo[k], self.hi[k]
            if was_s < s:
                a[k, was_s:s] = 1.0
            if e < was_e:
                a[k, e:was_e] = 0.0
            a[k, s:e] = ndtr((b[k] - t[s:e]) / jit)
        self.lo, self.hi = lo, hi
        return a
