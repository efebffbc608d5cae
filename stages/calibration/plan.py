"""Calibration, planning the density tests from the zero-distance capture (issue 33.2).

The delay (eq. 5.3) reads the time of the zero capture's return on the time axis at its
light: ``T B(k_p) / B(x_T0)``, the return at code ``k_p``, the window's end at ``x_T0``. Its
counting error is that of the code widths it sums: ``LSB^2 (sum_{k<k_p} v_k (1 - F)^2 +
sum_{k_p<=k<x_T0} v_k F^2)`` with ``F = k_p / x_T0`` and ``v_k`` the variance of code k's
width (LSB^2): ``1 / sum_i C_i p_i`` over the tests i that measured it, C_i cycles of
``p_i`` hits a code a cycle. A test measures the codes up to ``OWN_CLEAR_LSB`` below its own
window's end, which moves with its light (a brighter test has a larger LSB, its window ends
at a lower code): the codes at the top of a dim zero capture's window are measured only by
tests at its light or dimmer, with few hits a code. Bright tests give most hits a cycle on
the codes below. The plan spends the budget where the variance falls most, a step at a
time, keeping every test the LSB fit needs.

What the zero capture cannot tell is how far the window's end moves with light before the
LSB is measured: :data:`LSB_GROWTH` assumes the thesis's chip (the LSB ~20 % larger at
one detection a cycle than in the dark, eq. 5.1, about linear below 0.3).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from stages.calibration.density import OWN_CLEAR_LSB
from stages.calibration.timescale import RESET_CLEARANCE, light_end, light_level

#: The LSB fit's levels (detections per pixel per cycle, eq. 5.1): the issue's 0.02-0.3.
DEFAULT_LEVELS = (0.02, 0.05, 0.1, 0.3)
#: Relative LSB growth per unit of light assumed before it is measured (see above).
LSB_GROWTH = 0.2
#: Every test keeps at least this share of the budget (its LSB point needs counts too).
MIN_SHARE = 0.05
#: Steps the budget is spent in.
STEPS = 200
#: A return's 8-code sum must exceed the median one by this factor (and 5 sigmas).
RETURN_EXCESS = 1.15
#: Variance (LSB^2) of a code no test measures (the table continues there with the phase
#: pattern, :func:`code_bounds`): a real chip's random DNL, 0.1 LSB.
UNMEASURED_VAR = 0.1 ** 2


@dataclass(frozen=True)
class Plan:
    """Density tests to take, and the delay's counting error they are expected to give."""

    lights: np.ndarray          #: (n_tests,) detections per pixel per cycle (eq. 5.1)
    cycles: np.ndarray          #: (n_tests,) int
    delay_error_ps: np.ndarray  #: (n_tdc,) expected from counting (NaN: no return found)
    zero_light: float
    x_t0: np.ndarray            #: (n_tdc,) where the zero capture's window ends (code)
    return_code: np.ndarray     #: (n_tdc,) the zero capture's return (code; NaN: none)

    def to_json(self) -> dict:
        return {"tests": [{"light": round(float(n), 6), "cycles": int(c)}
                          for n, c in zip(self.lights, self.cycles, strict=True)],
                "zero_light": round(self.zero_light, 6),
                "expected_delay_error_ps": [None if not np.isfinite(e) else round(float(e), 2)
                                            for e in self.delay_error_ps]}


def zero_geometry(hits: np.ndarray, cycles) -> tuple[float, np.ndarray, np.ndarray]:
    """From a zero-distance capture: its light (eq. 5.1), every TDC's window end (the code
    of the reset peak's highest count, at the top of the populated codes, plus a half) and
    its return's code: the highest count within the 8 codes whose sum stands out most,
    ``RESET_CLEARANCE`` codes or more below the window's end; NaN where no 8-code sum
    exceeds the median one by ``RETURN_EXCESS`` and 5 Poisson sigmas (8 codes: a whole
    DNL period, whose widths sum to about 8 LSB whatever the pattern)."""
    h = np.asarray(hits, np.float64)
    top, _ = light_end(h)
    n_tdc = h.shape[0]
    x_t0 = np.full(n_tdc, np.nan)
    peak = np.full(n_tdc, np.nan)
    for t in range(n_tdc):  # once per TDC
        lo = max(int(top[t]) - 8, 0)
        if top[t] > 0:
            x_t0[t] = lo + int(np.argmax(h[t, lo:int(top[t])])) + 0.5
        end = int(top[t]) - RESET_CLEARANCE
        if end < 40:
            continue
        s8 = np.convolve(h[t, :end], np.ones(8), mode="valid")   # s8[i]: codes i..i+7
        base = np.median(s8)
        i = int(np.argmax(s8))
        if s8[i] > RETURN_EXCESS * base + 5 * np.sqrt(max(base, 1.0)):
            peak[t] = i + int(np.argmax(h[t, i:i + 8]))
    return light_level(h, cycles), x_t0, peak


def plan_tests(hits: np.ndarray, cycles, budget: float, window_s: float = 80e-9,
               levels=DEFAULT_LEVELS, window_share: float = 0.8,
               zero_as_test: bool = True) -> Plan:
    """The density tests to take within ``budget`` cycles, planned from a zero-distance
    capture's histograms (``hits`` (n_tdc, 512), ``cycles``): the LSB fit's ``levels``, and
    a test at the zero capture's light (its window ends where the zero's does) where its
    cycles lower the variance, the cycles spent where the delay's counting variance falls
    most (module text).
    ``window_share``: the share of a density test's STARTs in the window (the rest is the
    reset peak; 0.8 for a 20 ns reset period before an 80 ns window).
    ``zero_as_test``: the zero capture's own counts measure the codes clear of its return
    and reset peak (``calibrate delay`` counts them, :mod:`.zero_test`), and the plan
    counts them too."""
    from stages.calibration.zero_test import return_mask

    n0, x_t0, k_p = zero_geometry(hits, cycles)
    x_t0 = np.where(np.isfinite(x_t0), x_t0, np.nanmedian(x_t0))
    lights = np.unique(np.round(np.concatenate([np.asarray(levels, np.float64), [n0]]), 6))
    lights = lights[lights > 0]
    x0 = np.nanmedian(x_t0)
    # each test's last measured code: its window's end moved by its light
    last = x_t0[None, :] * (1 - LSB_GROWTH * (lights[:, None] - n0)) - OWN_CLEAR_LSB
    p = lights * window_share / max(x0, 1.0)          # hits a code a cycle
    codes = np.arange(hits.shape[1])
    measured = codes[None, None, :] < np.floor(last)[:, :, None]   # (test, tdc, code)
    inside = codes[None, :] < x_t0[:, None]
    f = np.where(np.isfinite(k_p), k_p / x_t0, np.nan)
    weight = np.where(codes[None, :] < np.nan_to_num(k_p)[:, None], (1 - f[:, None]) ** 2,
                      f[:, None] ** 2) * inside                    # (tdc, code)

    own = np.zeros(weight.shape)
    if zero_as_test:  # its hits a code (a response sigma of ~1 code assumed for the mask)
        clear = (codes[None, :] < np.floor(x_t0 - OWN_CLEAR_LSB)[:, None]) & ~return_mask(
            k_p, 1.0)
        own = np.where(clear, np.asarray(hits, np.float64), 0.0)

    def variance(c):  # per TDC, in LSB^2
        info = np.einsum("i,itk->tk", c * p, measured) + own
        with np.errstate(divide="ignore", invalid="ignore"):
            v = np.where(weight > 0, weight * np.where(info > 0, 1 / info, UNMEASURED_VAR),
                         0.0)
        return v.sum(axis=1)

    n_tests = lights.size
    # the LSB fit's levels keep their share; the test at the zero's light gets cycles only
    # where they lower the variance (a code measured with few counts is worse than one
    # continued by the phase pattern)
    is_level = np.isin(np.round(lights, 6), np.round(np.asarray(levels, np.float64), 6))
    c = np.where(is_level, MIN_SHARE * budget, 0.0)
    if c.sum() > budget:
        c = np.where(is_level, budget / is_level.sum(), 0.0)
    step = max((budget - c.sum()) / STEPS, 0.0)
    for _ in range(STEPS if step > 0 else 0):  # greedy: convex in the cycles
        base = np.nanmean(np.where(np.isfinite(variance(c)), variance(c), 1e300))
        gains = []
        for i in range(n_tests):
            d = c.copy()
            d[i] += step
            v = variance(d)
            gains.append(base - np.nanmean(np.where(np.isfinite(v), v, 1e300)))
        c[int(np.argmax(gains))] += step
    keep = is_level | (c > 0)
    lights, c, measured = lights[keep], c[keep], measured[keep]
    p = p[keep]
    cyc = np.floor(c).astype(np.int64)
    lsb_ps = window_s / np.maximum(x_t0, 1.0) * 1e12  # the window over the code span
    err = np.sqrt(variance(cyc.astype(np.float64))) * lsb_ps
    err = np.where(np.isfinite(k_p), err, np.nan)
    return Plan(lights, cyc, err, n0, x_t0, k_p)
