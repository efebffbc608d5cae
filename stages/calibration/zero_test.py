"""The zero-distance capture as one more density test (issue 33).

Away from its return and its reset peak a zero capture holds uniform light, like a density
test at its own light: the widths of the codes there, by Coates' correction (the return's
STARTs leave the cycles at risk below it, as every START does). Its window ends at its own
light's x_T, above the brightest density test's, so it measures the codes the delay sums
over that only the dimmer tests measured otherwise (issue 33: ~25 codes, 57-535 counts a
code). The counting floor (:func:`stages.calibration.floor.tau_floor_s`) of the issue's
captures falls from ~74 to ~68 ps RMS with a 1e6-cycle zero capture at 0.07 counted so.

:func:`zero_density` measures the widths (the return masked by :func:`return_mask`, the
reset peak as a density test leaves it); :func:`with_test` combines them with a table and
its variance by inverse variance, as the density tests' widths are combined
(:func:`stages.calibration.density.fill_from`), and the table goes on over the codes beyond
its last one that the capture measured.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from schemas.constants import N_CODES
from stages.calibration.density import DensityResult, density_test, width_variance

#: The return's reach each side of its code, in instrument-response sigmas, plus
#: ``ZERO_CLEAR_CODES`` codes (the peak's code is whole-code, its tail): masked.
ZERO_CLEAR_SIGMAS, ZERO_CLEAR_CODES = 6.0, 2
#: Codes both must have measured to bring the capture's widths to the table's units.
MIN_COMMON = 32
#: Hits clear of the return a TDC's zero capture needs to count as a density test.
MIN_UNIFORM_HITS = 1000


def return_mask(returns, sigma_codes) -> np.ndarray:
    """(n_tdc, 512) bool: the codes within ``ZERO_CLEAR_SIGMAS`` response sigmas
    (``sigma_codes``, per TDC or one) plus ``ZERO_CLEAR_CODES`` of each TDC's return code
    (``returns``, NaN: no return located, every code masked: its light is not known to be
    uniform anywhere)."""
    r = np.asarray(returns, np.float64)
    s = np.broadcast_to(np.asarray(sigma_codes, np.float64), r.shape)
    reach = np.ceil(ZERO_CLEAR_SIGMAS * np.where(np.isfinite(s), s, 2.0)) + ZERO_CLEAR_CODES
    k = np.arange(N_CODES)[None, :]
    near = np.abs(k - r[:, None]) <= reach[:, None]
    return np.where(np.isfinite(r)[:, None], near, True)


def zero_density(hits, cycles, window_s: float, exclude, artifacts=None
                 ) -> tuple[DensityResult, np.ndarray]:
    """A zero capture's code widths as a density test's (:func:`density_test` with the
    return ``exclude`` d) and their variance (:func:`width_variance`, NaN on the excluded
    codes: the phase mean stands there, nothing measured)."""
    h = np.asarray(hits, np.float64)
    exclude = np.asarray(exclude, bool)
    # a TDC with little uniform light clear of its return (a zero capture without ambient
    # light holds its return alone) is not a density test: left out, as a dark TDC
    lit = np.where(exclude, 0.0, h).sum(axis=1) >= MIN_UNIFORM_HITS
    h = np.where(lit[:, None], h, 0.0)
    res = density_test(h, cycles, window_s, exclude=exclude, artifacts=artifacts)
    var = width_variance(h, cycles, res, artifacts)
    return res, np.where(exclude, np.nan, var)


def with_test(density: DensityResult, width_var, res: DensityResult, var
              ) -> tuple[DensityResult, np.ndarray, np.ndarray]:
    """``density`` (a calibration's table) and its width variance ``width_var`` with the
    widths ``res`` measured (variance ``var``, NaN where it measured none) combined in:
    each code the inverse-variance mean of the two, the capture's first brought to the
    table's units by the ratio of their widths summed over the codes both measured; past
    the table's last code, the capture's own widths as far as it measured without a gap.
    The units stay the table's (its boundary at its own x_T is x_T). Returns the result,
    its variance and per TDC the codes the capture added to (0 where it did not: a TDC
    either flagged, or with under ``MIN_COMMON`` codes in common)."""
    w0 = np.asarray(density.width_lsb, np.float64)
    v0 = np.asarray(width_var, np.float64)
    wz = np.asarray(res.width_lsb, np.float64)
    vz = np.asarray(var, np.float64)
    w, v = w0.copy(), v0.copy()
    used = np.zeros(density.n_tdc, np.int64)
    mz = np.isfinite(wz) & np.isfinite(vz) & (vz > 0)
    m0 = np.isfinite(w0) & np.isfinite(v0) & (v0 > 0)
    k = np.arange(N_CODES)
    for t in np.flatnonzero(np.asarray(density.ok, bool) & np.asarray(res.ok, bool)):
        common = mz[t] & m0[t]
        if common.sum() < MIN_COMMON:
            continue
        ratio = w0[t, common].sum() / wz[t, common].sum()
        a, va = wz[t] * ratio, vz[t] * ratio ** 2
        both = common
        w[t, both] = (w0[t, both] / v0[t, both] + a[both] / va[both]) / (
            1 / v0[t, both] + 1 / va[both])
        v[t, both] = 1 / (1 / v0[t, both] + 1 / va[both])
        # past the table's last code: the capture's widths while it measured them
        last = int(np.flatnonzero(np.isfinite(w0[t]))[-1]) if np.isfinite(w0[t]).any() else -1
        gap = np.flatnonzero((k > last) & ~mz[t])
        stop = int(gap[0]) if gap.size else N_CODES
        more = (k > last) & (k < stop)
        w[t, more], v[t, more] = a[more], va[more]
        # the table's units: its boundary at its own x_T stays x_T
        b = np.concatenate([[0.0], np.cumsum(np.where(np.isfinite(w[t]), w[t], 0.0))])
        x = float(density.x_t[t])
        j = int(np.clip(np.floor(x), 0, N_CODES - 1))
        at = b[j] + (x - j) * (b[j + 1] - b[j])
        if np.isfinite(at) and at > 0:
            w[t] *= x / at
            v[t] *= (x / at) ** 2
        used[t] = int((both | more).sum())
    bound = np.concatenate([np.zeros((w.shape[0], 1)),
                            np.cumsum(np.where(np.isfinite(w), w, 0.0), axis=1)], axis=1)
    inl = np.where(np.isfinite(w), bound[:, :N_CODES] - k[None, :], np.nan)
    changed = used > 0
    out = dataclasses.replace(
        density,
        width_lsb=np.where(changed[:, None], w, w0),
        dnl_lsb=np.where(changed[:, None], w - 1.0, density.dnl_lsb),
        inl_lsb=np.where(changed[:, None], inl, density.inl_lsb))
    return out, np.where(changed[:, None], v, v0), used
