"""One calibration as one immutable object, and the time axis it gives a measurement.

A :class:`Calibration` holds everything a calibration directory holds (docs/design.md
"Outputs"): the second stage's bounds, the density test (code widths, DNL, INL, the LSB at
its light), the LSB against light (eq. 5.1's cubic with its scaling), the delay (eq. 5.3)
with a reason for every TDC without one, the instrument response, and the provenance
(``meta``: captures and their SHA-256, dates, software version). It is loaded once, with
validation, by ``pipeline.io.caldir.load_calibration`` and saved there too; everything
else takes the object.

:func:`time_axis` is the calibrated time axis of one measurement: the density test's code
boundaries scaled to the measurement's light. Both the delay measurement and the range
stage use it (it lived beside the range stage, which made the calibration and ranging
drivers import each other).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from schemas.constants import N_CODES
from stages import calibration as cal
from stages.artifact import ArtifactBounds

#: How far the light may be from a single density test's before its LSB is a guess.
SINGLE_TEST_LIGHT_TOLERANCE = 0.02


@dataclass(frozen=True)
class Calibration:
    """A calibration, per TDC (arrays of length ``n_tdc``), read-only."""

    density: cal.DensityResult
    second: cal.SecondStage
    lsb_fit: cal.LsbFit | None  #: None: one density test (its LSB at its light only)
    delay_s: np.ndarray         #: eq. 5.3, NaN where there is none
    delay_reasons: tuple        #: why a TDC has no delay ("" where it has one)
    irf_sigma_s: float | None   #: the instrument response measured at zero distance
    meta: dict                  #: meta.json: provenance, the density test's light, ...
    path: str = ""              #: where it was loaded from ("" for one not saved yet)
    #: (n_tdc, 512) variance (LSB^2) of every code width, the table's counting noise
    #: (issue 33.3, :mod:`stages.calibration.uncertainty`); None for a calibration made
    #: before it (its ranges' sigma is then the fit's alone)
    width_var_lsb2: np.ndarray | None = None
    #: what depends on the calibration only (its TDC ranges, boundaries, splines), built on
    #: first use: a live range stage reads them for every measurement
    _cache: dict = dataclasses.field(default_factory=dict, init=False, repr=False,
                                     compare=False)

    def __post_init__(self):
        n = self.density.n_tdc
        for name in ("n_min", "n_max", "n_th", "pdm"):
            if np.asarray(getattr(self.second, name)).shape != (n,):
                raise ValueError(f"calibration: second-stage {name} is not one per TDC ({n})")
        delay = np.array(self.delay_s, np.float64, copy=True)
        if delay.shape != (n,):
            raise ValueError(f"calibration: {delay.shape[0] if delay.ndim else 0} delays for "
                             f"{n} TDCs")
        delay.setflags(write=False)
        object.__setattr__(self, "delay_s", delay)
        reasons = tuple(self.delay_reasons) or tuple(
            "" if np.isfinite(d) else "no delay measurement" for d in delay)
        if len(reasons) != n:
            raise ValueError(f"calibration: {len(reasons)} delay reasons for {n} TDCs")
        object.__setattr__(self, "delay_reasons", reasons)

    @property
    def n_tdc(self) -> int:
        return self.density.n_tdc

    @property
    def ok(self) -> np.ndarray:
        return np.asarray(self.density.ok, bool)

    @property
    def reasons(self) -> tuple:
        """Per TDC, why the density test flagged it ("" where ok, or none recorded): its
        artifact bounds uncertain, a misplaced reset peak, dead or dark, ..."""
        return self.density.reasons

    @property
    def bounds(self) -> ArtifactBounds:
        return ArtifactBounds(self.second.n_min, self.second.n_max,
                              source=f"calibration:{self.path}" if self.path else "calibration")

    @property
    def has_delay(self) -> bool:
        return bool(np.isfinite(self.delay_s).any())

    @property
    def density_light(self) -> float:
        """Detections per pixel per cycle of the density test the INL comes from."""
        return float(self.meta.get("density", {}).get("detections_per_pixel_per_cycle",
                                                      np.nan))

    def lsb_s(self, light: float) -> tuple[np.ndarray, str]:
        """Per-TDC LSB (s) at a light level (eq. 5.1), and a note ("" when the calibration
        covers that light): outside the LSB fit's range the cubic extrapolates, and a
        single density test gives its own light's LSB only. The caller says the note where
        its user sees it (the command's output, a stage's counters)."""
        fit = self.lsb_fit
        if fit is None:
            n_cal = self.density_light
            note = "" if not abs(light - n_cal) > SINGLE_TEST_LIGHT_TOLERANCE else (
                f"one density test at {n_cal:.3g} detections per pixel per cycle, used at "
                f"{light:.3g}: the LSB changes with light (up to 40 ps, section 5.1); run "
                "`tcspc calibrate lsb` over this range")
            return np.asarray(self.density.lsb_s, np.float64), note
        lo, hi = fit.n_range
        note = "" if fit.in_range(light) else (
            f"light level {light:.3g} detections per pixel per cycle is outside the LSB "
            f"fit's range [{lo:.3g}, {hi:.3g}]")
        return fit.lsb_ps(light) * 1e-12, note

    def _memo(self, key, make):
        if key not in self._cache:
            self._cache[key] = make()
        return self._cache[key]

    @property
    def code_bounds(self) -> np.ndarray:
        """:func:`stages.calibration.code_bounds` of the density test, built once."""
        return self._memo("code_bounds", lambda: cal.code_bounds(self.density))

    def scale_splines(self, window_s: float) -> cal.ScaleSplines | None:
        """:func:`stages.calibration.scale_splines` at a window, built once (None without
        an LSB fit through its points)."""
        fit = self.lsb_fit
        if fit is None or fit.levels is None:
            return None
        return self._memo(("scale_splines", float(window_s)),
                          lambda: cal.scale_splines(self.density, fit, window_s))

    def scale_refs(self, window_s: float, light: float, source=None):
        """:func:`stages.calibration.scale_refs` at a light: where the axis's scale is
        the density tests' interpolated, the tests' x_T and weights its error comes from
        (for :mod:`stages.calibration.uncertainty`); rows whose scale came from the
        capture's own reset peak (``source``, a :class:`TimeAxis`'s) weigh NaN (their
        x_T is the one reference). None where nothing is interpolated."""
        refs = cal.scale_refs(self.density, self.lsb_fit, window_s, light,
                              self.scale_splines(window_s))
        if refs is None or source is None:
            return refs
        codes, weights, codes_var = refs
        situ = np.asarray(source, dtype=object) == "reset peak"
        return codes, np.where(situ[:, None], np.nan, weights), codes_var

    def scale_slope(self, window_s: float, light: float) -> np.ndarray:
        """(n_tdc,) d ln(scale) / dn at a light (eq. 5.1's n): how far the axis's scale
        moves per unit of the light it is read at (a central difference on
        :func:`stages.calibration.scale_at_light`, kept inside the LSB fit's levels);
        0 without an LSB fit (one density test: its own scale at any light)."""
        fit = self.lsb_fit
        if fit is None:
            return np.zeros(self.n_tdc)
        h = max(1e-4, 0.01 * float(light))
        lo, hi = fit.n_range
        a, b = float(light) - h, float(light) + h
        if fit.in_range(light):  # (the spline is not read across the levels' ends)
            a, b = max(a, lo), min(b, hi)

        def scale(n):
            return cal.scale_at_light(self.density, self.lsb_s(n)[0], window_s, fit, n,
                                      self.scale_splines(window_s), self.code_bounds)

        with np.errstate(divide="ignore", invalid="ignore"):
            return (np.log(scale(b)) - np.log(scale(a))) / (b - a)

    def rows(self, start: int, stop: int) -> Calibration:
        """The calibration of TDCs ``start..stop-1`` (a worker's TDC range; the same
        object for the same range, so what it builds is kept)."""
        if stop > self.n_tdc:
            raise ValueError(f"{self.path or 'calibration'}: calibrates {self.n_tdc} TDCs, "
                             f"the data reach TDC {stop - 1}")
        return self._memo(("rows", int(start), int(stop)), lambda: self._rows(start, stop))

    def _rows(self, start: int, stop: int) -> Calibration:
        sl = slice(start, stop)
        fit = self.lsb_fit
        if fit is not None:
            fit = cal.LsbFit(fit.coef[sl], fit.x_mean, fit.x_scale, fit.n_range,
                             np.asarray(fit.residual_ps)[sl] if np.ndim(fit.residual_ps) == 2
                             else fit.residual_ps, fit.levels,
                             None if fit.sigma_ps is None else np.asarray(fit.sigma_ps)[sl])
        return dataclasses.replace(
            self, density=cal.density_rows(self.density, sl),
            second=cal.SecondStage(*(np.asarray(getattr(self.second, f))[sl]
                                     for f in ("n_min", "n_max", "n_th", "pdm")),
                                   tuple(self.second.reasons[sl])),
            lsb_fit=fit, delay_s=self.delay_s[sl], delay_reasons=self.delay_reasons[sl],
            width_var_lsb2=None if self.width_var_lsb2 is None else self.width_var_lsb2[sl])

    def with_delay(self, delay_s: np.ndarray, reasons, irf_sigma_s: float,
                   delay_meta: dict) -> Calibration:
        """This calibration with a delay measurement (``delay_meta`` goes to meta.json)."""
        return dataclasses.replace(self, delay_s=delay_s, delay_reasons=tuple(reasons),
                                   irf_sigma_s=irf_sigma_s,
                                   meta={**self.meta, "delay": {**delay_meta,
                                                                "reasons": list(reasons),
                                                                "irf_sigma_s": irf_sigma_s}})


@dataclass(frozen=True)
class TimeAxis:
    """The calibrated time axis of one measurement, per TDC."""

    tau_edges_s: np.ndarray  #: (n_tdc, 513) code boundaries in tau
    x_t: np.ndarray          #: where tau = T falls on the code axis (bounded by the light)
    scale: np.ndarray        #: seconds per unit of the density test's code boundaries
    source: np.ndarray       #: per TDC "reset peak" or "lsb polynomial[: why not]"
    note: str                #: what the caller should tell its user ("" when nothing)


def time_axis(calibration: Calibration, hits: np.ndarray, cycles: np.ndarray,
              window_s: float, in_situ: bool = False,
              returns: np.ndarray | None = None,
              beyond: np.ndarray | None = None) -> TimeAxis:
    """The calibrated time axis of a measurement's histograms (rows: the calibration's TDCs;
    take :meth:`Calibration.rows` first for a worker's range).

    The code boundaries are the density test's (INL); their scale at this measurement's
    light comes from the LSB polynomial (eq. 5.1) read where the window's end falls
    (:func:`stages.calibration.scale_at_light`), or, with ``in_situ``, from the
    measurement's own reset peak, looked for where its uniform light ends and trusted only
    where the density test measured those codes and no return (``returns``: each TDC's
    return code, NaN for none) lies close to it (:func:`stages.calibration.scale_in_situ`).
    x_T is then bounded by where the uniform light ends, where the light shows a step
    there (:func:`stages.calibration.light_end`): a calibration whose LSB is off for this
    light would otherwise leave the reset peak inside the searched codes, where it wins as
    a false target; without ambient light there is no step, the last populated code is a
    return's tail, and bounding x_T there would mask the return itself. ``beyond``: TDCs
    whose reset peak may sit on any code the campaign measured (``scale_in_situ``).
    """
    hits = np.asarray(hits)
    if hits.shape[0] != calibration.n_tdc:
        raise ValueError(f"{calibration.path or 'calibration'}: calibrates "
                         f"{calibration.n_tdc} TDCs, the histograms have {hits.shape[0]}")
    density = calibration.density
    light = cal.light_level(hits, cycles)
    bounds = calibration.code_bounds
    lsb, note = calibration.lsb_s(light)
    scale = cal.scale_at_light(density, lsb, window_s, calibration.lsb_fit, light,
                               calibration.scale_splines(window_s), bounds)
    source = np.full(hits.shape[0], "lsb polynomial", dtype=object)
    if in_situ:
        own, ok, why = cal.scale_in_situ(hits, cycles, density, window_s, returns=returns,
                                         beyond=beyond)
        scale = np.where(ok, own, scale)
        source = np.where(ok, "reset peak", "lsb polynomial: " + why.astype(str)).astype(
            object)
    tau_edges = bounds * scale[:, None]
    x_t = _x_t(tau_edges, window_s)
    top, step = cal.light_end(hits)
    x_t = np.where(step, np.minimum(x_t, top), x_t)
    return TimeAxis(tau_edges, x_t, scale, source, note)


def _x_t(tau_edges: np.ndarray, window_s: float) -> np.ndarray:
    """Where tau = T falls (fractional code), per TDC."""
    k = np.clip((tau_edges <= window_s).sum(axis=1) - 1, 0, N_CODES - 1)
    r = np.arange(tau_edges.shape[0])
    return k + (window_s - tau_edges[r, k]) / (tau_edges[r, k + 1] - tau_edges[r, k])
