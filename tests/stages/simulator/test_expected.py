"""The expected histograms' jitter integral (``stages.simulator.expected._Blur``) is the
dense ``ndtr((b[:, None] - t[None, :]) / jit)`` to the bit: ndtr evaluated in a band of
~50 jitters a boundary, 1.0 and 0.0 written elsewhere, one TDC after another on one
array. Bit-identical, so every Poisson draw of the counts (and each seed-tuned test on
them) is what the dense product gave; it made ``expected_hits`` ~5x faster."""

import numpy as np
from scipy.special import ndtr

from stages.simulator.chip import REAL_CHIP_RANGES, make_chip, random_chip
from stages.simulator.expected import _Blur, expected_hits

T = 80e-9


def _dense_expected(chip, light, cycles, window_s, signal, tau_s, pulse_sigma_s):
    """``expected_hits`` as it was, the jitter's ndtr over every boundary and time."""
    import stages.simulator.expected as ex

    class Dense:
        def __init__(self, n_rows, t):
            self.t = t

        def __call__(self, b, jit):
            return ndtr((b[:, None] - self.t[None, :]) / jit)

    was, ex._Blur = ex._Blur, Dense
    try:
        return ex.expected_hits(chip, light, cycles, window_s, signal=signal, tau_s=tau_s,
                                pulse_sigma_s=pulse_sigma_s)
    finally:
        ex._Blur = was


def test_the_banded_blur_is_the_dense_one_to_the_bit():
    """Boundaries of TDCs one after another on one array (the bands moving both ways,
    a jitter 4x another), the first boundaries below the times' start and the last
    beyond their end."""
    rng = np.random.default_rng(1)
    t = (np.arange(4000) + 0.5) * 2e-12
    blur = _Blur(300, t)
    for shift, jit in ((-50e-12, 3e-12), (40e-12, 12e-12), (-3e-12, 5e-12), (0.0, 0.5e-12)):
        b = np.sort(rng.uniform(-0.1e-9, 8.2e-9, 300)) + shift
        np.testing.assert_array_equal(blur(b, jit), ndtr((b[:, None] - t[None, :]) / jit))


def test_expected_hits_are_the_dense_products_to_the_bit():
    """A zoo chip with a real chip's INL (2 TDCs) and a chip of 4x the jitter: ambient
    light and a return at the window's end."""
    chips = [random_chip(2, n_tdc=2, ranges=REAL_CHIP_RANGES)[0],
             make_chip(2, 7, jitter_fwhm_lsb=4.0)]
    for chip in chips:
        got = expected_hits(chip, 0.035, 2e6, T, signal=0.1, tau_s=79.9e-9,
                            pulse_sigma_s=80e-12)
        want = _dense_expected(chip, 0.035, 2e6, T, 0.1, 79.9e-9, 80e-12)
        np.testing.assert_array_equal(got, want)
