"""Calibration, the LSB against light (eq. 5.1): LSB(n) per TDC from the density tests'
levels, a cubic in n and a spline through the measured points.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from schemas.errors import CalibrationError


@dataclass(frozen=True)
class LsbFit:
    """LSB(n) per TDC (eq. 5.1's n): the measured LSBs at the density tests' light levels,
    interpolated, and the cubic in scaled x = (n - x_mean) / x_scale fitted to them.

    Inside the levels' range the LSB is a cubic spline through the measured points in
    sqrt(n) (:meth:`lsb_ps`): each point is measured to 0.003-0.014 ps (``sigma_ps``,
    zoo chips 3-4), while one cubic over 0.02-0.75 detections a cycle leaves residuals of
    up to ~0.4 ps where the IR drop bends (the simulated chip saturates), and 0.1 ps of
    LSB is ~20 ps of range at mid-window.
    sqrt(n) spreads the flow's levels (roughly geometric) evenly, where the bend is, and a
    spline through them misses the simulated curve by <= 0.03 ps against 0.08 in n
    (benchmarks/range_accuracy.py). Outside the range, and without the points (an old
    calibration), the cubic, as eq. 5.1 has it.
    """

    coef: np.ndarray      #: (n_tdc, 4), c0 + c1 x + c2 x^2 + c3 x^3, in ps
    x_mean: float
    x_scale: float
    n_range: tuple[float, float]
    residual_ps: np.ndarray  #: (n_tdc, n_points)
    levels: np.ndarray | None = None  #: (n_points,) the light levels of the residuals
    #: (n_tdc, n_points) standard error of each measured LSB (ps): its test's reset peak
    #: fit and the test's counted light (:func:`point_sigma_ps`); None where not known
    sigma_ps: np.ndarray | None = None
    #: the spline through the points, built on first use (the fit is read-only)
    _splines: dict = field(default_factory=dict, init=False, repr=False, compare=False)

    def cubic_ps(self, n) -> np.ndarray:
        """eq. 5.1's cubic at ``n``."""
        x = (np.asarray(n, np.float64) - self.x_mean) / self.x_scale
        return self.coef @ np.array([np.ones_like(x), x, x * x, x * x * x])

    def points_ps(self) -> np.ndarray:
        """(n_tdc, n_points) the measured LSBs: the cubic at the levels plus its residuals."""
        return self.cubic_ps(self.levels).reshape(self.coef.shape[0], -1) + np.asarray(
            self.residual_ps).reshape(self.coef.shape[0], -1)

    def lsb_ps(self, n) -> np.ndarray:
        n = np.asarray(n, np.float64)
        lv = None if self.levels is None else np.asarray(self.levels, np.float64)
        if lv is None or lv.size < 3 or n.ndim or not self.in_range(float(n)):
            return self.cubic_ps(n)
        if "lsb" not in self._splines:
            order = np.argsort(lv)
            lv, y = lv[order], self.points_ps()[:, order]
            # None: two tests at one light
            self._splines["lsb"] = RowSplines(lv, y) if np.all(np.diff(lv) > 0) else None
        spline = self._splines["lsb"]
        return self.cubic_ps(n) if spline is None else spline(float(n))

    def in_range(self, n) -> bool:
        lo, hi = self.n_range
        return bool(lo - 1e-12 <= n <= hi + 1e-12)


def _spline_rows(levels: np.ndarray, y: np.ndarray, n: float, coord=np.sqrt) -> np.ndarray:
    """Each row of ``y`` (n_rows, n_levels) read at light ``n`` by a cubic spline in
    ``coord(light)`` (sqrt: the time axis's) through its finite points (``levels``
    ascending). A row lacking a level (a TDC a density test flagged) uses the others: NaN
    (no time axis, flagged) where fewer than 3 remain or ``n`` lies outside the row's own
    levels."""
    return RowSplines(levels, y, coord)(n)


class RowSplines:
    """:func:`_spline_rows`'s splines, built once and read at any light (what depends on
    the calibration only is not rebuilt for every measurement)."""

    def __init__(self, levels: np.ndarray, y: np.ndarray, coord=np.sqrt):
        from scipy.interpolate import CubicSpline

        fin = np.isfinite(y)
        self.n_rows, self.coord, self.parts = y.shape[0], coord, []
        for pattern in np.unique(fin, axis=0):
            rows = np.all(fin == pattern, axis=1)
            lv = levels[pattern]
            if lv.size < 3:
                continue
            self.parts.append((rows, lv, bool(pattern.all()),
                               CubicSpline(coord(lv), y[rows][:, pattern].T, axis=0), pattern))

    def __call__(self, n: float) -> np.ndarray:
        out = np.full(self.n_rows, np.nan)
        for rows, lv, complete, spline, _ in self.parts:
            if not (complete or lv[0] - 1e-12 <= n <= lv[-1] + 1e-12):
                continue
            x = min(max(n, lv[0]), lv[-1])  # (the campaign's range is the caller's check)
            out[rows] = spline(self.coord(x))
        return out

    def weights(self, n: float) -> np.ndarray:
        """(n_rows, n_levels) what each point weighs in the value read at ``n``: a cubic
        spline through given points is linear in them, so ``self(n)`` is
        ``sum_i weights[:, i] y[:, i]`` (0 for a row's missing points; NaN where
        ``self(n)`` is)."""
        from scipy.interpolate import CubicSpline

        out = np.full((self.n_rows, self.parts[0][4].size if self.parts else 0), np.nan)
        for rows, lv, complete, _, pattern in self.parts:
            if not (complete or lv[0] - 1e-12 <= n <= lv[-1] + 1e-12):
                continue
            x = min(max(n, lv[0]), lv[-1])
            w = np.zeros(pattern.size)
            w[pattern] = CubicSpline(self.coord(lv), np.eye(lv.size), axis=0)(self.coord(x))
            out[rows] = w
        return out


def fit_lsb(n: np.ndarray, lsb_ps: np.ndarray) -> LsbFit:
    """Per-TDC cubic fit of LSB against light, on scaled x (well conditioned).

    ``n`` (n_points,) light levels, ``lsb_ps`` (n_tdc, n_points). Needs 4 distinct finite
    levels or more (:func:`stages.ranging.validation.check_levels`); with exactly 4 the
    cubic interpolates (residuals are zero and say nothing).
    """
    from stages.ranging.validation import check_levels

    n = np.asarray(n, np.float64)
    y = np.asarray(lsb_ps, np.float64)
    if n.size < 4:
        raise CalibrationError(f"an LSB-against-light fit needs density tests at >= 4 light "
                               f"levels (a cubic, eq. 5.1); found {n.size}")
    if y.ndim != 2 or y.shape[1] != n.size:
        raise CalibrationError(f"lsb_ps must be (TDCs, {n.size} light levels), found shape "
                               f"{y.shape}")
    if np.isfinite(y).any():  # (no TDC measured at all: the caller says why)
        n = check_levels(n)  # finite, >= 4 distinct: [.1, .1, .3, .3] gave half the LSB
    x_mean = float(n.mean())
    x_scale = float(n.std()) or 1.0
    x = (n - x_mean) / x_scale
    v = np.vander(x, 4, increasing=True)              # (n_points, 4), scaled: well posed
    fin = np.isfinite(y)
    coef = np.full((y.shape[0], 4), np.nan)
    # rows by which levels they have (a TDC a test flagged lacks that level): a cubic
    # through 4 or more, a quadratic through 3, nothing through fewer
    for pattern in np.unique(fin, axis=0):
        rows = np.all(fin == pattern, axis=1)
        m = int(np.unique(n[pattern]).size)  # distinct levels: a repeat adds no degree
        if m < 3:
            continue
        deg = min(m, 4)
        coef[rows] = 0.0
        coef[np.ix_(rows, np.arange(deg))] = np.linalg.lstsq(
            v[pattern][:, :deg], y[rows][:, pattern].T, rcond=None)[0].T
    resid = y - coef @ v.T
    return LsbFit(coef, x_mean, x_scale, (float(n.min()), float(n.max())), resid, n)


def point_sigma_ps(fit: LsbFit, lsb_ps, x_t, x_t_var, light_var) -> np.ndarray:
    """(n_tdc, n_points) standard error (ps) of each density test's measured LSB
    ``T / x_T,i`` (``lsb_ps``, ``x_t``, ``x_t_var``: (n_tdc, n_points) of the tests, in
    ``fit.levels``' order): its x_T's own variance (:func:`.density.x_t_variance`: the
    reset peak fit's counts and the widths under the peak) and its light's, the level
    being the test's counted STARTs (``light_var``, (n_points,), binomial over its
    TDC-cycles) while the LSB it measured is the light's expected one: the LSB's slope
    against light (the spline in sqrt(n), a central difference) times that light's
    error. On zoo chips 3-7 (16 TDCs, four tests at 0.02-0.3) the tests' x_T were off from
    the truth at their expected light by z RMS 0.94 (within 2 sigma 0.966) of their own
    sigma (0.003-0.013 code); the counted light moved x_T by up to 0.019 code more, the
    same for every TDC of a test."""
    lsb = np.asarray(lsb_ps, np.float64)
    lo, hi = fit.n_range
    slope = np.zeros_like(lsb)
    for i, n in enumerate(np.asarray(fit.levels, np.float64)):
        h = max(1e-4, 0.01 * n)
        a, b = max(n - h, lo), min(n + h, hi)
        with np.errstate(invalid="ignore"):
            slope[:, i] = (fit.lsb_ps(b) - fit.lsb_ps(a)) / (b - a)
    with np.errstate(invalid="ignore", divide="ignore"):
        own = lsb * np.sqrt(np.asarray(x_t_var, np.float64)) / np.asarray(x_t, np.float64)
    light = np.nan_to_num(slope) * np.sqrt(np.asarray(light_var, np.float64))[None, :]
    return np.hypot(own, light)
