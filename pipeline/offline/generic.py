"""Ranging and distance calibration of generic histograms (any instrument's, see
:mod:`pipeline.io.generic`) on the instrument's own uniform bins.

The time of a return is taken on the file's nominal bins, relative to the measurement's
reference channel where it has one (an internal zero-distance path: it removes the laser's
drift between captures). ``tcspc calibrate distance`` fits, per row and per estimator, the
line ``t = (delay + 2 d / c) * nominal / real`` over captures at known distances: the delay
(eq. 5.3 at the target's distance) and, from two or more distances, the real bin width.
Off-axis zones see a flat target along a longer, slanted path, a fixed factor that the
per-row scale takes up.

Pile-up: an instrument that does not report its laser pulses gives no Coates correction.
From three or more distances the calibration models pile-up where the data have it (the
background behind the returns is thinned, :func:`_background_deficit`) with one effective
number of pulses per histogram (the sensor's, the same for every row and capture: the one
whose correction leaves the smallest calibration residuals where the lines can see the
pile-up and do, else the one that makes the background behind the returns equal to the
one before them) and records it; ranging uses it where the file has no cycles, and says
so.
"""

from __future__ import annotations

import csv
import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.constants import c as C_LIGHT

from pipeline.io.atomic import atomic_path
from pipeline.io.generic import Measurement, read_generic
from schemas.errors import CalibrationError, SchemaMismatch
from stages.ranging import ESTIMATORS, Estimate, Histograms, estimate, estimate_returns
from stages.ranging.histograms import coates
from stages.ranging.irf import (
    IRF_ESTIMATORS,
    Response,
    fit_response,
    response_from_counts,
    response_from_returns,
)
from stages.ranging.multi import select_rows
from stages.ranging.multi_irf import PerGroup, merge_rows
from stages.ranging.width import response_from_data, return_fwhm

CALIBRATION_FILE = "distance_calibration.json"
#: the key of a fit made with a Gaussian by an estimator that takes a measured response
#: (its delay differs: each shape puts a return's time elsewhere on the peak)
GAUSSIAN = "/gaussian"
#: cycles of a histogram whose instrument does not report them: so many that the Coates
#: correction is the identity
_NO_PILEUP = 1e12
#: the effective-pulse grid of the pile-up fit, in multiples of the brightest histogram
_CYCLE_GRID = np.geomspace(1.02, 30.0, 24)


@dataclass
class DistanceCalibration:
    """What ``calibrate distance`` fitted: per estimator and row (``tdc``) the delay and the
    real bin width, the residuals; the measured response; the effective pulses."""

    tdc: list[int]
    nominal_bin_ps: float
    fits: dict[str, dict] = field(default_factory=dict)
    response: Response | None = None
    cycles: float | None = None
    pileup: str = "none (the file gives no cycles)"
    #: measurements the truth file names that the histograms file does not have
    missing: list[str] = field(default_factory=list)
    measurements: list[str] = field(default_factory=list)
    distances_m: list[float] = field(default_factory=list)
    path: str = ""
    #: the calibration rows' own returns aligned and averaged (their response, tail
    #: included): the model of a found return when several are searched (a reference
    #: channel's tail is another optical path's)
    returns_response: Response | None = None
    #: whether its measurements had a reference channel: every time is then relative to
    #: the reference's return, and a file ranged with it must have one too (None: unknown)
    reference: bool | None = None

    def save(self, out: str | Path) -> Path:
        doc = {"kind": "distance", "tdc": self.tdc, "nominal_bin_ps": self.nominal_bin_ps,
               "reference": self.reference,
               "fits": self.fits, "cycles": self.cycles, "pileup": self.pileup,
               "measurements": self.measurements, "distances_m": self.distances_m,
               "response": _response_doc(self.response),
               "returns_response": _response_doc(self.returns_response)}
        with atomic_path(out) as tmp:
            tmp.mkdir()
            (tmp / CALIBRATION_FILE).write_text(json.dumps(doc, indent=1, allow_nan=True))
        return Path(out)

    @classmethod
    def load(cls, path: str | Path) -> DistanceCalibration:
        f = Path(path) / CALIBRATION_FILE
        if not f.is_file():
            raise CalibrationError(f"{path}: no {CALIBRATION_FILE} (made by `tcspc calibrate "
                                   "distance`)")
        doc = json.loads(f.read_text())
        response = _response_of(doc.get("response"))
        reference = doc.get("reference")
        if reference is None and response is not None:  # (made before the key was kept)
            reference = response.source.startswith("reference channel")
        return cls(doc["tdc"], doc["nominal_bin_ps"], doc["fits"],
                   response, doc.get("cycles"),
                   doc.get("pileup", ""), doc.get("measurements", []),
                   doc.get("distances_m", []), str(path),
                   returns_response=_response_of(doc.get("returns_response")),
                   reference=reference)

    def check_layout(self, m: Measurement, path) -> None:
        """Refuse a measurement the calibration's times do not apply to: one whose rows it
        did not fit, or with a reference channel where its measurements had none (or the
        reverse: a time relative to the reference's return is ~0.2 m off the TMF8820's
        time after its pulse)."""
        extra = sorted(set(m.tdc[~m.reference].tolist()) - set(self.tdc))
        if extra:
            raise CalibrationError(f"{path}: measurement {m.name}: rows {_span(extra)} have "
                                   f"no calibration in {self.path} (it fitted rows "
                                   f"{_span(self.tdc)})")
        has = bool(np.any(m.reference))
        if self.reference is not None and has != self.reference:
            raise CalibrationError(
                f"{path}: measurement {m.name} has {'a' if has else 'no'} reference channel, "
                f"{self.path} was fitted on measurements {'with' if self.reference else 'without'}"
                " one (times are measured from the reference's return when there is one): "
                "calibrate on files of the same layout")

    def preferred(self, estimator: str) -> str:
        """The fit ``range`` uses for ``estimator`` when no response is asked for: for
        matched and ml, the measured response or the Gaussian of its FWHM, whichever left
        the smaller calibration residuals (a reference channel's far tail need not be a
        zone's; the calibration, not the user, tells)."""
        alt = self.fits.get(estimator + GAUSSIAN)
        if alt is not None and estimator in self.fits and np.isfinite(alt["rms_mm"]) and (
                not np.isfinite(self.fits[estimator]["rms_mm"])
                or alt["rms_mm"] < self.fits[estimator]["rms_mm"]):
            return estimator + GAUSSIAN
        return estimator

    def row_fit(self, estimator: str, tdc) -> tuple[np.ndarray, np.ndarray]:
        """(delay_s, bin scale real/nominal) per requested row; NaN where not calibrated."""
        if estimator not in self.fits:
            raise CalibrationError(f"{self.path}: no fit for estimator {estimator!r} "
                                   f"(has {sorted(self.fits)})")
        fit = self.fits[estimator]
        where = {t: i for i, t in enumerate(self.tdc)}
        idx = [where.get(int(t), -1) for t in tdc]
        delay = np.array([fit["delay_ps"][i] if i >= 0 else np.nan for i in idx], float)
        width = np.array([fit["bin_width_ps"][i] if i >= 0 else np.nan for i in idx], float)
        return np.asarray(delay, float) * 1e-12, np.asarray(width, float) / self.nominal_bin_ps

    def row_sigma_m(self, estimator: str, tdc, d_m) -> np.ndarray:
        """The calibration's own standard deviation (m) of a distance ``d_m`` ranged on row
        ``tdc``: its line t = a + b x (d = c/2 (t - a) / b) from the calibration times'
        sigmas; 0 for a calibration made before it was kept (the fit's sigma alone)."""
        cov = self.fits[estimator].get("line_cov")
        if cov is None:
            return np.zeros(np.shape(d_m))
        where = {t: i for i, t in enumerate(self.tdc)}
        idx = np.array([where.get(int(t), -1) for t in tdc], np.int64)

        def col(name, unit):
            v = np.asarray(cov[name], float) * unit
            return np.where(idx >= 0, v[np.maximum(idx, 0)], np.nan)

        var_a, cov_ab, var_b = col("a_ps2", 1e-24), col("ab_ps", 1e-12), col("b", 1.0)
        b = 1.0 / (self.row_fit(estimator, tdc)[1])
        d = np.asarray(d_m, float)
        k = C_LIGHT / 2 / b  # d = k (t - a): dd/da = -k, dd/db = -d / b
        var = k ** 2 * var_a + (d / b) ** 2 * var_b + 2 * k * d / b * cov_ab
        return np.sqrt(np.clip(np.nan_to_num(var), 0.0, None))


def _response_doc(r: Response | None) -> dict | None:
    if r is None:
        return None
    return {"source": r.source, "bin_ps": r.bin_s * 1e12, "density": r.density.tolist(),
            **({} if r.error is None else {"error": r.error.tolist()})}


def _response_of(doc: dict | None) -> Response | None:
    if doc is None:
        return None
    err = doc.get("error")
    return Response(np.asarray(doc["density"]), doc["bin_ps"] * 1e-12, doc["source"],
                    None if err is None else np.asarray(err))


@dataclass(frozen=True)
class Times:
    """Return times of a measurement's ranged rows (not its reference)."""

    tdc: np.ndarray
    est: Estimate
    t_s: np.ndarray          #: after the reference channel's return, or after bin 0
    response: str            #: which instrument response was used
    pileup: str              #: how pile-up was handled
    bright: np.ndarray       #: rows with more counts than the effective pulses (raised)


def _cycles(m: Measurement, cycles: float | None) -> tuple[np.ndarray, str, np.ndarray]:
    total = m.counts.sum(axis=1)
    given = np.isfinite(m.cycles)
    bright = np.zeros(total.size, bool)
    if given.all():
        return m.cycles, "Coates, with the file's cycles", bright
    if cycles is not None:
        # a histogram holds no more first photons than pulses: a brighter one than the
        # fitted count raises its own to its total (and is counted in the note)
        bright = ~given & (total >= cycles)
        cyc = np.where(given, m.cycles, np.maximum(cycles, total * 1.001))
        return cyc, (f"Coates, with {cycles:.4g} effective pulses fitted by calibrate "
                     "distance"), bright
    return (np.where(given, m.cycles, np.maximum(total, 1.0) * _NO_PILEUP),
            "none: the file gives no cycles", bright)


def _histograms(m: Measurement, cyc: np.ndarray, rows=slice(None)) -> Histograms:
    """The rows ``rows`` of ``m`` on its nominal bins, with the cycles ``cyc``."""
    counts = m.counts[rows]
    n = counts.shape[1]
    edges = m.bin_width_s * np.arange(n + 1, dtype=np.float64)
    return Histograms(counts, np.broadcast_to(edges, (counts.shape[0], n + 1)).copy(),
                      np.asarray(cyc)[rows], np.ones(counts.shape, bool))


def measurement_times(m: Measurement, estimator: str = "ml", p_fa: float = 1e-3,
                      response: Response | None = None, sigma_s: float | None = None,
                      cycles: float | None = None, max_returns: int = 1,
                      returns_response: Response | None = None) -> Times:
    """The return time of every non-reference row of ``m``.

    ``matched`` and ``ml`` use a measured response (the measurement's own reference
    channel, else ``response``) unless ``sigma_s`` asks for a Gaussian; the other
    estimators use a Gaussian of ``sigma_s`` (default: the response's sigma, else one bin).
    With ``max_returns`` > 1, up to so many returns a row
    (:func:`stages.ranging.multi.estimate_returns` with ``returns_response``, the found
    returns' model): ``Times.tdc`` then names each row's pixel.
    """
    return measurements_times([m], estimator, p_fa, response, sigma_s, cycles, max_returns,
                              returns_response)[0]


#: the most rows a batch of measurements whose further returns are searched together (the
#: search's fits hold ~25 shifts x bins x 8 bytes a row in each of a few arrays)
BATCH_ROWS = 2048


@dataclass
class _First:
    """A measurement's single-return estimate of its non-reference rows, before its
    further returns are searched."""

    m: Measurement
    cyc: np.ndarray
    pileup: str
    bright: np.ndarray
    used: str
    single: object           #: its single-return estimator, a function of Histograms
    est: Estimate            #: of the rows ``~m.reference``
    origin: float
    sigma: float = float("nan")  #: the Gaussian's sigma (a measured response's FWHM's)


def _first(m: Measurement, estimator, p_fa, response, sigma_s, cycles) -> _First:
    cyc, pileup, bright = _cycles(m, cycles)
    h = _histograms(m, cyc)
    ref = np.flatnonzero(m.reference)
    if ref.size:
        r = ref[0]
        response = response_from_counts(m.counts[r], m.bin_width_s,
                                        f"the reference channel (row {m.tdc[r]}) of each "
                                        "measurement",
                                        cyc[r] if np.isfinite(m.cycles[r]) or cycles is not None
                                        else None)
    if estimator in IRF_ESTIMATORS and response is not None and sigma_s is None:
        def single(hh):
            return fit_response(hh, response, estimator, p_fa)
        used = response.source
        sigma = response.sigma_s
    else:
        how = "given"
        if sigma_s is None and response is None:
            # measured on the returns (one bin was taken: ml's 2-sigma coverage 0.59-0.84
            # on a response 2.3 bins wide, issue 34.5)
            sigma, how = response_from_data(h)
            sigma = max(sigma, m.bin_width_s / np.sqrt(12.0))
        else:
            sigma = sigma_s or response.sigma_s

        def single(hh):
            return estimate(hh, sigma, estimator, p_fa)
        used = f"Gaussian, sigma {sigma * 1e12:.1f} ps" + ("" if how == "given" else
                                                            f" ({how})")
    est = single(h)
    if used.startswith("Gaussian"):  # the return's measured width, not the response's:
        # a merged pair of surfaces is then wider than one (issue 34.5; a measured
        # response's tail would widen its second moment, so there the response's is kept)
        est = dataclasses.replace(est, fwhm_s=return_fwhm(h, est.t_s, sigma))
    origin = 0.0
    if ref.size:
        origin = est.t_s[ref[0]] if est.detected[ref[0]] else np.nan
    keep = ~m.reference
    return _First(m, cyc, pileup, bright, used, single, select_rows(est, keep), origin,
                  sigma)


def measurements_times(ms: list[Measurement], estimator: str = "ml", p_fa: float = 1e-3,
                       response: Response | None = None, sigma_s: float | None = None,
                       cycles: float | None = None, max_returns: int = 1,
                       returns_response: Response | None = None) -> list[Times]:
    """:func:`measurement_times` of each of ``ms``. Their further returns (``max_returns``
    > 1) are searched in batches of measurements with the same bins (up to
    :data:`BATCH_ROWS` rows), each row with its own measurement's cycles, single-return
    estimator and reference: the same results as one measurement at a time, the search's
    Python paid once a batch."""
    firsts = [_first(m, estimator, p_fa, response, sigma_s, cycles) for m in ms]
    if max_returns == 1:
        return [Times(f.m.tdc[~f.m.reference], f.est, f.est.t_s - f.origin, f.used,
                      f.pileup, f.bright[~f.m.reference]) for f in firsts]
    out: list[Times | None] = [None] * len(firsts)
    if returns_response is None:  # a Gaussian response (--irf-ps, --delay-ps): its masks
        for i, f in enumerate(firsts):
            r = np.flatnonzero(~f.m.reference)
            found = estimate_returns(_histograms(f.m, f.cyc, r), f.sigma, estimator, p_fa,
                                     max_returns)
            out[i] = Times(f.m.tdc[r][found.pixel], found, found.t_s - f.origin, f.used,
                           f.pileup, f.bright[r][found.pixel])
        return out
    for batch in _batches(firsts):
        fs = [firsts[i] for i in batch]
        rows = [np.flatnonzero(~f.m.reference) for f in fs]
        hs = [_histograms(f.m, f.cyc, r) for f, r in zip(fs, rows, strict=True)]
        h = Histograms(*(np.concatenate([getattr(x, a) for x in hs])
                         for a in ("counts", "edges_s", "cycles", "valid")))
        group = np.repeat(np.arange(len(fs)), [r.size for r in rows])
        first = merge_rows([(np.flatnonzero(group == j), f.est) for j, f in enumerate(fs)],
                        group.size)
        found = estimate_returns(h, returns_response.sigma_s, estimator, p_fa, max_returns,
                                 response=returns_response, first=first,
                                 single=PerGroup(group, [f.single for f in fs]))
        start = np.cumsum([0] + [r.size for r in rows])
        for j, (i, f, r) in enumerate(zip(batch, fs, rows, strict=True)):
            mine = (found.pixel >= start[j]) & (found.pixel < start[j + 1])
            sub = select_rows(found, mine)
            sub = dataclasses.replace(sub, pixel=sub.pixel - start[j])
            out[i] = Times(f.m.tdc[r][sub.pixel], sub, sub.t_s - f.origin, f.used,
                           f.pileup, f.bright[r][sub.pixel])
    return out


def _batches(firsts: list[_First]) -> list[list[int]]:
    """Indices of ``firsts`` in batches of measurements with the same bins (their count
    and width), of up to :data:`BATCH_ROWS` rows (a measurement is never split)."""
    out, open_ = [], {}
    for i, f in enumerate(firsts):
        key = (f.m.counts.shape[1], f.m.bin_width_s)
        n = int((~f.m.reference).sum())
        b = open_.get(key)
        if b is None or b[1] + n > BATCH_ROWS:
            b = open_[key] = [[], 0]
            out.append(b[0])
        b[0].append(i)
        b[1] += n
    return out


def _span(rows) -> str:
    """Row numbers, short: ``0-8`` for a run, else the list."""
    rows = sorted(int(r) for r in rows)
    if len(rows) > 2 and rows == list(range(rows[0], rows[-1] + 1)):
        return f"{rows[0]}-{rows[-1]}"
    return ", ".join(map(str, rows))


def read_truth(path: str | Path) -> dict[tuple[str, int | None], float]:
    """truth.csv: ``measurement,distance_m`` and optionally ``tdc`` (a row's own distance)."""
    with open(path, newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows or not {"measurement", "distance_m"} <= set(rows[0]):
        raise CalibrationError(f"{path}: needs the columns measurement,distance_m")
    out = {}
    for i, r in enumerate(rows, start=2):
        try:
            d = float(r["distance_m"])
        except ValueError:
            raise CalibrationError(f"{path}: line {i}: distance_m {r['distance_m']!r} is not "
                                   "a number") from None
        if not np.isfinite(d) or d < 0:
            raise CalibrationError(f"{path}: line {i}: distance_m must be >= 0, found {d}")
        tdc = r.get("tdc")
        out[(r["measurement"], int(tdc) if tdc not in (None, "") else None)] = d
    return out


def _fit_line(x, t, sd=None):
    """t = a + b x over the finite points: (a, b, residuals in t units, the covariance of
    (a, b) as [var a, cov ab, var b]); b = 1 when the points hold one distance. The
    covariance is that of the unweighted fit given each time's standard deviation ``sd``
    (the estimator's sigma; NaN where not given)."""
    ok = np.isfinite(t) & np.isfinite(x)
    if ok.sum() == 0:
        return np.nan, np.nan, np.full(t.shape, np.nan), [np.nan] * 3
    var = (np.full(t.shape, np.nan) if sd is None else np.asarray(sd, float) ** 2)[ok]
    if np.unique(x[ok]).size >= 2:
        b, a = np.polyfit(x[ok], t[ok], 1)
        # (X'X)^-1 X' diag(var) X (X'X)^-1 of the least-squares line
        X = np.stack([np.ones(ok.sum()), x[ok]], axis=1)
        g = np.linalg.solve(X.T @ X, X.T)
        cov = (g * var) @ g.T
        cov = [cov[0, 0], cov[0, 1], cov[1, 1]]
    else:
        a, b = float(np.mean(t[ok] - x[ok])), 1.0
        cov = [float(np.sum(var)) / ok.sum() ** 2, 0.0, 0.0]
    return a, b, np.where(ok, t - a - b * x, np.nan), [float(c) for c in cov]


def _fit_rows(times: list[Times], dist: np.ndarray):
    """Per row: delay (s), scale (real/nominal), residuals (m) over the measurements, and
    the covariance of the line t = a + b x (s^2, s, 1) from the times' sigmas."""
    t = np.stack([np.where(tm.est.detected, tm.t_s, np.nan) for tm in times])
    sd = np.stack([np.asarray(tm.est.sigma_s, float) for tm in times])
    x = 2 * dist / C_LIGHT
    delay, scale, res, cov = [], [], [], []
    for j in range(t.shape[1]):
        a, b, r, c = _fit_line(x[:, j], t[:, j], sd[:, j])
        delay.append(a / b)
        scale.append(1.0 / b)
        res.append(r / b * C_LIGHT / 2)
        cov.append(c)
    return np.array(delay), np.array(scale), np.array(res).T, np.array(cov)


def _rms(res) -> float:
    r = np.asarray(res, float)
    return float(np.sqrt(np.nanmean(r ** 2))) if np.isfinite(r).any() else float("nan")


def calibrate_distance(path: str | Path, truth_csv: str | Path,
                       estimators=ESTIMATORS, p_fa: float = 1e-3,
                       fit_pileup: bool = True) -> DistanceCalibration:
    """Fit delay and bin width per row from the measurements of ``path`` that ``truth_csv``
    names; see the module's docstring (``fit_pileup=False``: no effective pulse count,
    for comparison). Raises CalibrationError when nothing can be fitted."""
    truth = read_truth(truth_csv)
    names = {k[0] for k in truth}
    meas = [m for m in read_generic(path) if m.name in names]
    if not meas:
        raise CalibrationError(f"{truth_csv}: names no measurement of {path}")
    # (a truth row naming no measurement of the file was skipped silently: counted, named)
    missing = sorted(names - {m.name for m in meas})
    tdc = meas[0].tdc[~meas[0].reference]
    for m in meas:
        if not np.array_equal(m.tdc[~m.reference], tdc):
            raise CalibrationError(f"{path}: measurement {m.name} has rows "
                                   f"{m.tdc[~m.reference].tolist()}, {meas[0].name} "
                                   f"{tdc.tolist()}")
    refs = {bool(np.any(m.reference)) for m in meas}
    if len(refs) > 1:
        raise CalibrationError(f"{path}: some measurements have a reference channel and some "
                               "do not; their times cannot share one calibration")
    dist = np.array([[truth.get((m.name, int(t)), truth.get((m.name, None), np.nan))
                      for t in tdc] for m in meas])
    nominal = meas[0].bin_width_s
    cal = DistanceCalibration([int(t) for t in tdc], nominal * 1e12,
                              measurements=[m.name for m in meas],
                              distances_m=np.nanmedian(dist, axis=1).tolist(),
                              reference=refs.pop())
    order = np.argsort(cal.distances_m)
    mid = meas[order[len(order) // 2]]
    if mid.reference.any():
        r = int(np.flatnonzero(mid.reference)[0])
        source = f"reference channel of {mid.name}"
    else:  # the brightest row at the middle known distance
        r = int(np.argmax(mid.counts.sum(axis=1)))
        source = (f"row {mid.tdc[r]} of {mid.name} at "
                  f"{cal.distances_m[order[len(order) // 2]]:g} m")

    def response(cycles, rows=None, shifts=None):
        """The response of row ``r`` of ``mid``, or of its ``rows``, each pile-up
        corrected, moved ``shifts`` bins earlier, and summed."""
        if rows is None:
            c = mid.cycles[r] if np.isfinite(mid.cycles[r]) else cycles
            return response_from_counts(mid.counts[r], nominal, source, c)
        h = _histograms(mid, _cycles(mid, cycles)[0], rows)
        n = h.counts.shape[1]
        at = (np.arange(n)[None, :] + np.asarray(shifts)[:, None]) % n
        y = np.take_along_axis(h.intensity() * h.cycles[:, None], at, 1).sum(0)
        return response_from_counts(y, nominal, source)

    cal.missing = missing
    cal.response = response(None)
    if any(np.isfinite(m.cycles).any() for m in meas):
        cal.pileup = "Coates, with the file's cycles (none fitted)"
    elif not fit_pileup:
        cal.pileup = "none (not fitted: asked so)"
    elif np.unique(cal.distances_m).size < 3:
        cal.pileup = ("none (the file gives no cycles; an effective pulse count needs >= 3 "
                      "distances to fit)")
    else:
        cal.cycles, cal.pileup = _pileup(meas, dist, cal.response, p_fa)
        if cal.cycles is not None:
            cal.response = response(cal.cycles)  # its shape without the pile-up
    if not mid.reference.any():
        # every row at the middle distance, not its brightest alone: one row of 2 000
        # counts gave a Gaussian width 2 % narrow to 11 % wide, an error in every sigma of
        # the Gaussian estimators with this calibration (fast's 2-sigma coverage 0.929 to
        # 0.971 by the draw, issue 34)
        tm = measurement_times(mid, "ml", p_fa, cal.response, cal.response.sigma_s,
                               cal.cycles)
        pos = np.asarray(tm.est.t_s, float) / nominal
        ok = np.flatnonzero(np.asarray(tm.est.detected) & np.isfinite(pos))
        if ok.size > 1:
            source = (f"{ok.size} rows of {mid.name} at "
                      f"{cal.distances_m[order[len(order) // 2]]:g} m, aligned to a bin "
                      "on their times and summed")
            shifts = np.rint(pos[ok] - np.median(pos[ok])).astype(np.int64)
            cal.response = response(cal.cycles, ok, shifts)
    cal.returns_response = _returns_response(meas, cal, p_fa)
    runs = [(name, None) for name in estimators] + [
        (name + GAUSSIAN, cal.response.sigma_s) for name in estimators
        if name in IRF_ESTIMATORS]
    for key, sigma in runs:
        name = key.removesuffix(GAUSSIAN)
        times = [measurement_times(m, name, p_fa, cal.response, sigma, cal.cycles)
                 for m in meas]
        delay, scale, res, cov = _fit_rows(times, dist)
        cal.fits[key] = {
            "delay_ps": (delay * 1e12).tolist(), "bin_width_ps": (scale * nominal * 1e12)
            .tolist(), "residual_mm": (res * 1e3).tolist(), "rms_mm": _rms(res) * 1e3,
            # the line t = a + b x's covariance per row from the times' sigmas: ranging
            # adds it to each distance's sigma (issue 34.5: without it ml and fast covered
            # 0.87 of the errors with a calibration of 4 targets of 2 000 counts)
            "line_cov": {"a_ps2": (cov[:, 0] * 1e24).tolist(),
                         "ab_ps": (cov[:, 1] * 1e12).tolist(), "b": cov[:, 2].tolist()},
            "n_distances": int(np.unique(np.asarray(cal.distances_m)).size),
            "response": times[0].response}
    if not any(np.isfinite(f["delay_ps"]).any() for f in cal.fits.values()):
        raise CalibrationError(f"{path}: no return detected in the calibration measurements")
    return cal


def _returns_response(meas: list[Measurement], cal: DistanceCalibration,
                      p_fa: float) -> Response | None:
    """The calibration rows' own response: every detected return of the calibration
    measurements (a single target each, at a known distance), aligned on ml's time (the
    Gaussian of the response's FWHM) and averaged (:func:`response_from_returns`)."""
    hs, ts = [], []
    for m in meas:
        cyc = _cycles(m, cal.cycles)[0]
        tm = measurement_times(m, "ml", p_fa, cal.response, cal.response.sigma_s, cal.cycles)
        hs.append(_histograms(m, cyc, np.flatnonzero(~m.reference)))
        ts.append(np.where(tm.est.detected, tm.est.t_s, np.nan))
    if not np.isfinite(np.concatenate(ts)).any():
        return None
    h = Histograms(*(np.concatenate([getattr(x, f) for x in hs])
                     for f in ("counts", "edges_s", "cycles", "valid")))
    n = int(np.isfinite(np.concatenate(ts)).sum())
    return response_from_returns(h, np.concatenate(ts),
                                 f"the calibration's {n} returns, aligned and averaged")


def _pileup(meas, dist, response, p_fa) -> tuple[float | None, str]:
    """Whether pile-up is modelled, and with what effective pulse count: (count or None,
    what was modelled and why). The data decide: only where the background behind the
    returns is thinned (:func:`_background_deficit`, p < :data:`PILEUP_ALPHA`). The count
    is then the calibration lines' (:func:`_fit_cycles`) where they can see it and do:
    the background's count (:func:`_deficit_cycles`) would bend them beyond their noise
    (the returns' signals differ with distance), and the lines' own count lowers their
    residuals, both F tests at PILEUP_ALPHA. Else it is the background's: targets of one
    strength all move alike, which the delay takes up, and a count the lines chose there
    was noise (1.7e4 for 2e5 pulses, F test p = 0.004: the search over the count makes
    that test too lenient)."""
    p = _background_deficit(meas, response)
    if not p < PILEUP_ALPHA:
        return None, (f"none (the background behind the returns is not below the one "
                      f"before them: p = {p:.2g}, not < {PILEUP_ALPHA:g})")
    why = (f"modelled: the background behind the returns is below the one before them, "
           f"p = {p:.2g} < {PILEUP_ALPHA:g}")
    best, res0, best_rms, p_f = _fit_cycles(meas, dist, response, p_fa)
    n, dof = int(np.isfinite(res0).sum()), _dof(res0, dist)
    lines = (f"residual RMS {_rms(res0) * 1e3:.3f} -> {best_rms * 1e3:.3f} mm"
             + (f" at {best:.4g}" if best else "") + f", F test p = {p_f:.2g} on {n} "
             "residuals")
    count = _deficit_cycles(meas, response)
    p_bend, bend = 0.0, ""
    if count is not None:
        res = _residuals(meas, dist, response, p_fa, count)
        # against their noise: the residuals at the lines' own best count
        p_bend = _f_test(float(np.hypot(_rms(res - res0), best_rms)), best_rms, n, dof)
        bend = (f"that count bends them by {_rms(res - res0) * 1e3:.3f} mm RMS against "
                f"their {best_rms * 1e3:.3f} mm noise, F test p = {p_bend:.2g}; ")
    if p_f < PILEUP_ALPHA and p_bend < PILEUP_ALPHA:
        return best, (f"Coates with {best:.4g} effective pulses per histogram, fitted on "
                      f"the calibration lines ({bend}{lines} < {PILEUP_ALPHA:g}); {why}")
    if count is None:
        return None, (f"none (the background behind the returns is below the one before "
                      f"them, p = {p:.2g}, but no effective pulse count up to 10^6 times "
                      f"the brightest histogram brings it up to that one: {lines})")
    return count, (f"Coates with {count:.4g} effective pulses per histogram, the count "
                   f"whose correction brings the background behind the returns up to the "
                   f"one before them (the calibration lines do not fix it: {bend}{lines}); "
                   f"{why}")


def _residuals(meas, dist, response, p_fa, cycles=None) -> np.ndarray:
    """ml's calibration lines' residuals (m) with the Coates correction of ``cycles``."""
    return _fit_rows([measurement_times(m, "ml", p_fa, response, cycles=cycles)
                      for m in meas], dist)[2]


def _dof(res, dist) -> int:
    """Residuals left free by every row's line and one count."""
    return int(np.isfinite(res).sum()) - 2 * dist.shape[1] - 1


def _fit_cycles(meas, dist, response, p_fa):
    """The effective pulses per histogram whose Coates correction leaves the smallest
    residuals of ml's calibration lines: (count or None where no count does better than
    none, the residuals without it, the RMS with it, the F test's p of the one added
    parameter against the two of every row's line)."""
    from scipy.optimize import minimize_scalar

    top = max(float(m.counts.sum(axis=1).max()) for m in meas)

    def rms(log_k):
        return _rms(_residuals(meas, dist, response, p_fa, float(np.exp(log_k)) * top))

    grid = np.log(_CYCLE_GRID)
    scores = np.array([rms(x) for x in grid])
    res0 = _residuals(meas, dist, response, p_fa)
    best, best_rms = None, _rms(res0)
    i = int(np.nanargmin(scores))
    if scores[i] < best_rms:  # refined between the grid's neighbours (a smooth minimum)
        lo, hi = grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)]
        r = minimize_scalar(rms, bounds=(lo, hi), method="bounded",
                            options={"xatol": 0.005})
        x, v = (r.x, r.fun) if r.fun < scores[i] else (grid[i], scores[i])
        best, best_rms = float(np.exp(x)) * top, v
    n = int(np.isfinite(res0).sum())
    p = _f_test(_rms(res0), best_rms, n, _dof(res0, dist)) if best else 1.0
    return best, res0, best_rms, p


#: the significance at which a calibration models pile-up (an effective pulse count)
PILEUP_ALPHA = 0.01


def _background_regions(m: Measurement, response: Response):
    """A measurement's rows (reference channel left out) and, per row, its bins behind
    the return (beyond 4 spans of the response after the row's fullest bin) and before
    it (2 spans ahead), and the share of those bins that are behind: (counts, before,
    after, share)."""
    lo, hi = response.span
    c = m.counts[~m.reference].astype(np.float64)
    j = np.arange(c.shape[1])[None, :]
    k = np.argmax(c, axis=1)[:, None]
    before, after = j < k - 2 * lo, j > k + 4 * hi
    return c, before, after, after.sum(1) / np.maximum(before.sum(1) + after.sum(1), 1)


def _background_deficit(meas: list[Measurement], response: Response) -> float:
    """P-value of "no pile-up" from the data themselves: a first-photon histogram's
    background behind a return is thinned by the cycles the return took, so behind the
    returns it is below the one before them (:func:`_background_regions`). Under no
    pile-up and a flat background, a row's counts there split binomially by the bins'
    numbers: the sum over the rows against its mean and variance, one-sided (a normal
    tail; a diffusion tail behind a return only adds counts, which keeps it conservative).
    1 where the rows hold no background to test."""
    from scipy.special import ndtr

    num = mean = var = 0.0
    for m in meas:
        c, before, after, share = _background_regions(m, response)
        nb, na = (c * before).sum(1), (c * after).sum(1)
        tot = nb + na
        num += na.sum()
        mean += (tot * share).sum()
        var += (tot * share * (1 - share)).sum()
    if var <= 0:
        return 1.0
    return float(ndtr((num - mean) / np.sqrt(var)))


def _deficit_cycles(meas: list[Measurement], response: Response) -> float | None:
    """The effective pulses per histogram whose Coates correction makes the background
    behind the returns equal to the one before them (:func:`_background_regions`; the
    rows' corrected counts behind the returns, summed, against their share of the rows'
    corrected background, a root in the count). None: no count between the brightest
    histogram and 10^6 times it closes the gap."""
    from scipy.optimize import brentq

    rows = [_background_regions(m, response) for m in meas]
    top = max(float(r[0].sum(axis=1).max()) for r in rows)

    def gap(log_k):
        n = float(np.exp(log_k)) * top
        out = 0.0
        for c, before, after, share in rows:
            x = coates(c, n) * n
            xb, xa = (x * before).sum(1), (x * after).sum(1)
            out += float((xa - share * (xa + xb)).sum())
        return out

    lo, hi = np.log1p(1e-6), np.log(1e6)
    if not (gap(lo) > 0 > gap(hi)):
        return None
    return float(np.exp(brentq(gap, lo, hi, xtol=1e-4))) * top


def _f_test(rms0: float, rms1: float, n: int, dof: int) -> float:
    """P-value of one added parameter lowering the residuals' RMS from rms0 to rms1 over n
    residuals (dof left with it): F = (RSS0 - RSS1) / (RSS1 / dof) against F(1, dof)."""
    from scipy.stats import f

    if dof < 1 or not (rms1 > 0) or not np.isfinite(rms0):
        return 1.0
    rss0, rss1 = n * rms0 ** 2, n * rms1 ** 2
    return float(f.sf(max(rss0 - rss1, 0.0) / (rss1 / dof), 1, dof))


def range_generic(path: str | Path, calibration: DistanceCalibration | None = None,
                  delay_s: float | None = None, zero: str | Path | None = None,
                  sigma_s: float | None = None, estimator: str = "ml",
                  p_fa: float = 1e-3, shape: str = "auto", max_returns: int | None = None,
                  ) -> tuple[pa.Table, dict[str, str]]:
    """Ranges of every measurement of a generic histograms file: with a calibration, a
    given delay, or a delay measured on a zero-distance file. A row is not detected where
    its distance would be negative (flagged, NaN) or unknown.
    ``shape`` (matched and ml with a calibration): ``"auto"`` the calibration's
    :meth:`~DistanceCalibration.preferred`, ``"measured"`` or ``"gaussian"``.
    ``max_returns``: returns a row (default: :data:`~stages.ranging.multi.MAX_RETURNS`
    with a calibration that holds its returns' measured response, else 1; more than one
    without it is refused). A further return within the response's FWHM of the zero is
    left out (the sensor's own crosstalk, its cover glass) and counted in ``info``."""
    from pipeline.offline.ranging import SIGMA_NOTE, behind_zero, ranges_table
    from stages.ranging.multi import MAX_RETURNS

    cycles = calibration.cycles if calibration is not None else None
    response = calibration.response if calibration is not None else None
    returns_response = calibration.returns_response if calibration is not None else None
    if max_returns is None:
        max_returns = MAX_RETURNS if returns_response is not None or zero is not None else 1
    if max_returns > 1 and calibration is not None and returns_response is None:
        raise CalibrationError(
            f"--max-returns {max_returns}: several returns a row need the returns' measured "
            "response, which a calibration from `tcspc calibrate distance` holds (this one "
            "predates it: calibrate again)")
    crosstalk = 0
    key = estimator
    if calibration is not None:
        if shape not in ("auto", "measured", "gaussian"):
            raise ValueError(f"shape must be auto, measured or gaussian, found {shape!r}")
        key = calibration.preferred(estimator) if shape == "auto" else estimator
        if estimator in IRF_ESTIMATORS and (sigma_s is not None or shape == "gaussian"):
            key = estimator + GAUSSIAN
        if key.endswith(GAUSSIAN) and sigma_s is None:
            sigma_s = response.sigma_s
    zero_delay = None
    if zero is not None:
        z = read_generic(zero)[0]
        zt = measurement_times(z, estimator, p_fa, response, sigma_s, cycles)
        zero_delay = _zero_delays(zt)
        zero_note = ""
        if (max_returns <= 1 and sigma_s is None and response is None
                and not z.reference.any() and np.asarray(zt.est.detected).any()):
            # one return a row: the zero file's returns (its strong, known-distance ones)
            # give the response's width, not the file's own weaker returns: at 100 counts
            # on 1 a bin those measured it 12 % wide and sigma covered 0.98 (issue 34.5).
            # (Several: the zero's returns aligned and averaged, below, time both files;
            # a Gaussian first return beside that model of the found ones resolved none
            # of two surfaces 1.5 widths apart, where the average resolves most.)
            zh = _histograms(z, _cycles(z, cycles)[0], np.flatnonzero(~z.reference))
            s_z, how = response_from_data(zh, np.where(zt.est.detected, zt.est.t_s, np.nan))
            if how.startswith("measured"):
                sigma_s = s_z
                zero_note = f" (measured on the zero-distance file: {how})"
                zt = measurement_times(z, estimator, p_fa, response, sigma_s, cycles)
                zero_delay = _zero_delays(zt)
        if max_returns > 1 and np.asarray(zt.est.detected).any():
            # the zero file's returns, aligned and averaged: the returns' response, tail
            # and all, as a calibration's (issue 34.1)
            zh = _histograms(z, _cycles(z, cycles)[0], np.flatnonzero(~z.reference))
            returns_response = response_from_returns(
                zh, np.where(zt.est.detected, zt.est.t_s, np.nan),
                f"the returns of the zero-distance file {zero}, aligned and averaged")
            if sigma_s is None:  # the same shape times the zero and the file
                response = returns_response
                zt = measurement_times(z, estimator, p_fa, response, None, cycles)
                zero_delay = _zero_delays(zt)
    tables, info = [], {}
    for meas in _row_batches(path):
        for m in meas:
            if calibration is not None:
                calibration.check_layout(m, path)
            elif zero is not None and bool(np.any(m.reference)) != bool(np.any(z.reference)):
                raise CalibrationError(
                    f"{path}: measurement {m.name} has {'a' if m.reference.any() else 'no'} "
                    f"reference channel, the zero-distance file {zero} "
                    f"{'has' if z.reference.any() else 'has not'} (times are measured from "
                    "the reference's return when there is one)")
        times = measurements_times(meas, estimator, p_fa, response, sigma_s, cycles,
                                   max_returns, returns_response)
        for m, tm in zip(meas, times, strict=True):
            scale = np.ones(tm.tdc.size)
            if calibration is not None:
                delay, scale = calibration.row_fit(key, tm.tdc)
            elif zero_delay is not None:
                delay, delay_sd = np.array([zero_delay.get(int(t), (np.nan, np.nan))
                                            for t in tm.tdc]).reshape(-1, 2).T
            else:
                delay = np.full(tm.tdc.size, float(delay_s))
            d = C_LIGHT / 2 * (tm.t_s * scale - delay)
            sig_t = np.asarray(tm.est.sigma_s, float) * scale
            if calibration is not None:  # the calibration line's own, in quadrature
                sig_t = np.hypot(sig_t, calibration.row_sigma_m(key, tm.tdc, d) * 2 / C_LIGHT)
            elif zero_delay is not None:  # the zero row's time's own, in quadrature
                sig_t = np.hypot(sig_t, delay_sd)
            sig = sig_t * C_LIGHT / 2
            # a row without a delay or a finite time is not detected (its flag says why); a
            # return before the zero is flagged as the chip's is (NaN distance, not detected)
            # (sigma on the real time axis, carried with the rows that behind_zero keeps)
            est = dataclasses.replace(tm.est, detected=np.asarray(tm.est.detected, bool)
                                      & np.isfinite(d) & np.isfinite(sig),
                                      sigma_s=sig_t)
            est, d = behind_zero(est, d)
            if max_returns > 1:
                est, d, n_x = _without_crosstalk(est, d)
                crosstalk += n_x
            sig = np.asarray(est.sigma_s, float) * C_LIGHT / 2
            t = ranges_table(m.name, est, d, sig)
            tdc = tm.tdc if est.pixel is None else m.tdc[~m.reference][est.pixel]
            t = t.set_column(t.schema.get_field_index("tdc"), t.schema.field("tdc"),
                             pa.array(tdc, t.schema.field("tdc").type))
            tables.append(t)
            info = {"response": tm.response + (zero_note if zero is not None else "") + (
                " (the measured response's FWHM: its calibration residuals were smaller "
                "than the measured shape's)" if key != estimator
                and key == calibration.preferred(estimator) else ""), "pileup": tm.pileup}
            if tm.bright.any():
                info["bright"] = (f"{int(tm.bright.sum())} row(s) of {m.name} hold more "
                                  "counts than the effective pulses: their own total used "
                                  "instead")
    if max_returns > 1:
        info["returns"] = (f"up to {max_returns} a row, each found one's model "
                           + (f"{returns_response.source} (its tail included)"
                              if returns_response is not None else
                              "the Gaussian response (its tails masked; a real response's "
                              "longer tail may be found as a surface: --zero or a "
                              "calibration measure it)"))
    if crosstalk:
        info["crosstalk"] = (f"{crosstalk} further return(s) within the response's FWHM of "
                             "the zero left out (the sensor's own crosstalk)")
    table = pa.concat_tables(tables)
    meta = {**(table.schema.metadata or {}), b"tcspc.response": info["response"].encode(),
            b"tcspc.pileup": info["pileup"].encode(),
            b"tcspc.returns": info.get("returns", "one a row").encode()}
    if calibration is not None:
        meta[b"tcspc.calibration"] = calibration.path.encode()
    if estimator in SIGMA_NOTE:
        meta[b"tcspc.sigma"] = SIGMA_NOTE[estimator].encode()
    return table.replace_schema_metadata(meta), info


def _zero_delays(zt: Times) -> dict[int, tuple[float, float]]:
    """Each row of a zero-distance file (its tdc): its detected return's time and sigma
    (NaN where none was detected), the delay a row of the ranged file is measured from."""
    det = np.asarray(zt.est.detected, bool)
    return dict(zip(zt.tdc.tolist(), zip(np.where(det, zt.t_s, np.nan).tolist(),
                                         np.where(det, zt.est.sigma_s, np.nan).tolist(),
                                         strict=True), strict=True))


#: count values a batch of rows of a big file holds (x ~64 bytes when ranged: ~0.5 GB)
BATCH_VALUES = 1 << 23


def _row_batches(path):
    """The file's measurements, in batches of rows with at most :data:`BATCH_VALUES`
    count values when it has more; a measurement may then span batches, each part ranged
    alone (the rows are independent, the response measured on each part's returns where
    none is given). A reference row times its measurement's other rows: the reference rows
    are read first (one pass over the file, batch by batch, keeping only them) and each
    part of a measurement is ranged with its measurement's reference, as when read whole.
    Issue 34.7: 10^5 x 4 096 took 14-23 GB read whole. A measurement whose parts differ
    in bins or bin width is refused as it would be read whole (ragged histograms)."""
    import pyarrow.compute as pc

    f = pq.ParquetFile(path)
    md = f.metadata
    names = [md.schema.column(j).path for j in range(md.num_columns)]
    cols = [j for j, n in enumerate(names) if n.split(".")[0] == "counts"]
    values = sum(md.row_group(g).column(j).num_values for g in range(md.num_row_groups)
                 for j in cols)
    if values <= BATCH_VALUES or not md.num_rows:
        yield read_generic(path)
        return
    size = max(1, int(BATCH_VALUES // max(values / md.num_rows, 1)))

    def batches():
        first = 0
        for b in f.iter_batches(batch_size=size):
            t = pa.Table.from_batches([b])
            yield t, np.arange(first, first + t.num_rows)
            first += t.num_rows

    refs = None
    if "reference" in f.schema_arrow.names:
        parts, at = [], []
        for t, rows in batches():
            is_ref = pc.fill_null(t.column("reference"), False)
            if pc.any(is_ref).as_py():
                parts.append(t.filter(is_ref))
                at.append(rows[np.asarray(is_ref.to_numpy(zero_copy_only=False), bool)])
        if parts:
            refs = (pa.concat_tables(parts), np.concatenate(at))
            read_generic(path, *refs)  # (checked here: a reference alone is not ranged)
    seen: dict[str, tuple[int, float]] = {}
    for t, rows in batches():
        if refs is not None:
            rest = ~np.asarray(pc.fill_null(t.column("reference"), False).to_numpy(
                zero_copy_only=False), bool)
            t, rows = t.filter(pa.array(rest)), rows[rest]
            if not t.num_rows:
                continue
            mine = np.asarray(pc.is_in(refs[0].column("measurement"),
                                       value_set=pc.unique(t.column("measurement")))
                              .to_numpy(zero_copy_only=False), bool)
            t = pa.concat_tables([t, refs[0].filter(pa.array(mine))])
            rows = np.concatenate([rows, refs[1][mine]])
        meas = read_generic(path, t, rows)
        for m in meas:
            n, w = seen.setdefault(m.name, (m.counts.shape[1], m.bin_width_s))
            if m.counts.shape[1] != n or abs(m.bin_width_s / w - 1) > 1e-9:
                r = int(rows[np.flatnonzero(
                    np.asarray(t.column("measurement").to_pylist(), object) == m.name)[0]])
                raise SchemaMismatch(
                    f"{path}: row {r}: measurement {m.name!r} has {m.counts.shape[1]} bins "
                    f"of {m.bin_width_s * 1e12:g} ps here and {n} of {w * 1e12:g} ps in "
                    "its earlier rows (ragged histograms)")
        yield meas


def _without_crosstalk(est: Estimate, d):
    """``est`` (and its distances) less the further returns within their FWHM of
    the zero: the sensor's own crosstalk (the TMF8820's cover glass, ~200 counts that a
    weak target 30-40 cm away leaves standing); how many were left out."""
    fwhm_m = np.asarray(est.fwhm_s, float) * C_LIGHT / 2
    x = (np.asarray(est.return_index) > 0) & np.asarray(est.detected, bool) & (d < fwhm_m)
    if not x.any():
        return est, d, 0
    keep = ~x
    return select_rows(est, keep), d[keep], int(x.sum())


def write_ranges(table: pa.Table, out: str | Path) -> None:
    with atomic_path(out) as tmp:
        pq.write_table(table, tmp)
