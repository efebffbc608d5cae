"""Calibration campaigns on captures: density test, LSB against light, delay; and the
calibration directory (DESIGN.md "Outputs") written atomically with its provenance.

A calibration directory holds ``tdc.parquet`` (calibration_tdc), ``inl.parquet``
(calibration_inl) and ``meta.json``: schema version, software version, date, the SHA-256
of every capture it came from, the light level of each density test, and the scaling of
the LSB polynomial's x.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import warnings
from dataclasses import dataclass
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.io.atomic import atomic_path
from pipeline.io.caldir import read_tdc_table
from pipeline.io.capture import Capture
from schemas.errors import CalibrationError
from schemas.outputs import CALIBRATION_INL, CALIBRATION_TDC
from schemas.words import N_CODES
from stages import calibration as cal
from stages.histogram import HistogramAccumulator


def software_version() -> str:
    try:
        return version("tcspc-lidar")
    except PackageNotFoundError:  # pragma: no cover - running from a source tree
        return "unknown"


def sha256(path: Path, chunk: int = 1 << 22) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()


def density_histograms(capture: Capture, progress=None):
    """A uniform-light capture's D1st histograms (artifact words apart, by code) and
    second-stage parameters: two passes, the second stage's bounds first."""
    n_tdc = capture.meta.n_tdc
    ss = cal.SecondStageAccumulator(n_tdc)
    for first, words in capture.iter_chunks():
        ss.update(words, first)
        if progress:
            progress(words.size)
    second = cal.second_stage_params(ss.counts)
    acc = HistogramAccumulator(n_tdc, second.bounds, count_artifacts=True)
    for first, words in capture.iter_chunks():
        acc.update(words, first)
        if progress:
            progress(words.size)
    return acc.snapshot(), second


def refilled(state, res: cal.DensityResult, others: list, window_s: float):
    """``res`` (of histograms ``state``) again, with the codes under its reset peak taking
    the widths that ``others`` (``(state, result)`` pairs of density tests at other light)
    measured there, each weighted against the phase mean by its error."""
    tests = [(r, cal.width_variance(st.hits, st.cycles, r, st.artifacts)) for st, r in others]
    return cal.density_test(state.hits, state.cycles, window_s,
                            fill=cal.fill_from(tests, res), artifacts=state.artifacts)


def density_from_capture(capture: Capture, inl_rms_lsb: float | None = 0.3,
                         progress=None, fill: list | tuple = ()
                         ) -> tuple[cal.DensityResult, cal.SecondStage]:
    """Run a density test on a uniform-light capture (two passes: second stage, then D1st).

    ``fill``: captures of density tests at other light (dimmer: their reset peaks ~10
    codes higher at half the light) that measure the codes under this one's reset peak
    (see :func:`refilled`). Raises CalibrationError when the capture is too small for
    ``inl_rms_lsb`` (None: no check), saying how many cycles are needed.
    """
    state, second = density_histograms(capture, progress)
    window_s = capture.meta.window_ns * 1e-9
    res = cal.density_test(state.hits, state.cycles, window_s, artifacts=state.artifacts)
    if fill:
        others = []
        for c in fill:
            st, _ = density_histograms(c, progress)
            others.append((st, cal.density_test(st.hits, st.cycles, window_s,
                                                artifacts=st.artifacts)))
        res = refilled(state, res, others, window_s)
    if inl_rms_lsb is not None:
        worst = np.nanmax(np.where(res.ok, res.inl_error_lsb, np.nan)) if res.ok.any() else np.inf
        if not np.isfinite(worst) or worst > inl_rms_lsb:
            rate = float(np.nanmedian(np.where(res.ok, res.detections_per_cycle, np.nan))) \
                if res.ok.any() else 0.25
            need = cal.cycles_needed(inl_rms_lsb, starts_per_cycle=max(rate, 1e-6))
            raise CalibrationError(
                f"{capture.bin_path}: {capture.meta.cycles} cycles give an INL error of "
                f"{worst:.2f} LSB RMS; {inl_rms_lsb} LSB needs about {need:,} cycles at this "
                f"light level ({rate:.1%} STARTs per cycle)")
    return res, second


def write_caldir(out: str | Path, density: cal.DensityResult, second: cal.SecondStage,
                 sources: list[Path], lsb_fit: cal.LsbFit | None = None,
                 delay_s: np.ndarray | None = None, extra: dict | None = None) -> Path:
    """Write a calibration directory atomically (a failure leaves the old one in place)."""
    n = density.n_tdc
    lsb_ps = density.lsb_s * 1e12
    if lsb_fit is not None:
        poly = lsb_fit.coef
    else:  # a single density test: a constant polynomial at its LSB
        poly = np.column_stack([lsb_ps, np.zeros((n, 3))])
    tdc = pa.table({
        "tdc": pa.array(np.arange(n), pa.uint16()),
        "lsb_ps": pa.array(lsb_ps),
        "lsb_poly": pa.FixedSizeListArray.from_arrays(pa.array(poly.ravel()), 4),
        "n_min": pa.array(np.maximum(second.n_min, 0), pa.uint16()),
        "n_max": pa.array(np.maximum(second.n_max, 0), pa.uint16()),
        "n_th": pa.array(np.maximum(second.n_th, 0), pa.uint16()),
        "pdm": pa.array(np.maximum(second.pdm, 0), pa.uint16()),
        "delay_ps": pa.array([None] * n if delay_s is None else delay_s * 1e12,
                             pa.float64()),
        "ok": pa.array(density.ok),
    }, schema=CALIBRATION_TDC.schema)
    codes = np.arange(N_CODES)
    inl = pa.table({
        "tdc": pa.array(np.repeat(np.arange(n), N_CODES), pa.uint16()),
        "code": pa.array(np.tile(codes, n), pa.uint16()),
        "width_lsb": pa.array(density.width_lsb.ravel()),
        "dnl_lsb": pa.array(density.dnl_lsb.ravel()),
        "inl_lsb": pa.array(density.inl_lsb.ravel()),
    }, schema=CALIBRATION_INL.schema)
    meta = {
        "schema_version": CALIBRATION_TDC.version, "software": software_version(),
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "sources": [{"path": str(p), "sha256": sha256(Path(p))} for p in sources],
        "density": {"detections_per_pixel_per_cycle": float(
            np.nanmean(density.detections_per_cycle)),
            "x_t": density.x_t.tolist(), "inl_error_lsb": density.inl_error_lsb.tolist(),
            "flagged_tdcs": np.flatnonzero(~density.ok).tolist()},
        **({"lsb_poly_x": {"mean": lsb_fit.x_mean, "scale": lsb_fit.x_scale,
                           "n_range": list(lsb_fit.n_range)},
            "lsb_residual_ps": lsb_fit.residual_ps.tolist()} if lsb_fit else {}),
        **(extra or {}),
    }
    out = Path(out)
    with atomic_path(out) as tmp:
        tmp.mkdir(parents=True)
        pq.write_table(tdc, tmp / "tdc.parquet")
        pq.write_table(inl, tmp / "inl.parquet")
        (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
    return out


def read_density(caldir: str | Path) -> tuple[cal.DensityResult, dict]:
    """The density-test part of a calibration directory, as a DensityResult."""
    caldir = Path(caldir)
    tdc = read_tdc_table(caldir)
    inl = pq.read_table(caldir / "inl.parquet")
    meta = json.loads((caldir / "meta.json").read_text())
    n = tdc.num_rows
    grid = lambda c: inl.column(c).to_numpy().reshape(n, N_CODES)  # noqa: E731
    lsb = tdc.column("lsb_ps").to_numpy() * 1e-12
    ok = tdc.column("ok").to_numpy() if "ok" in tdc.column_names else np.ones(n, bool)
    d = meta.get("density", {})
    res = cal.DensityResult(lsb, np.asarray(d.get("x_t", np.full(n, np.nan))),
                            grid("width_lsb"), grid("dnl_lsb"), grid("inl_lsb"),
                            np.full(n, np.nan),
                            np.full(n, d.get("detections_per_pixel_per_cycle", np.nan)),
                            ok, np.asarray(d.get("inl_error_lsb", np.full(n, np.nan))))
    return res, meta


def read_lsb_fit(caldir: str | Path) -> cal.LsbFit | None:
    """The directory's LSB-against-light fit, or None when it holds one density test."""
    caldir = Path(caldir)
    meta = json.loads((caldir / "meta.json").read_text())
    px = meta.get("lsb_poly_x")
    if px is None:
        return None
    poly = np.stack(read_tdc_table(caldir).column("lsb_poly").to_numpy(zero_copy_only=False))
    return cal.LsbFit(poly, px["mean"], px["scale"], tuple(px["n_range"]),
                      np.asarray(meta.get("lsb_residual_ps", np.empty((poly.shape[0], 0)))))


def lsb_at(caldir: str | Path, n_light: float) -> np.ndarray:
    """Per-TDC LSB (s) at a light level from the directory's polynomial (eq. 5.1); warns
    when the level lies outside the fitted range."""
    caldir = Path(caldir)
    tdc = read_tdc_table(caldir)
    meta = json.loads((caldir / "meta.json").read_text())
    fit = read_lsb_fit(caldir)
    if fit is None:
        n_cal = meta.get("density", {}).get("detections_per_pixel_per_cycle")
        if n_cal is not None and abs(n_light - n_cal) > 0.02:
            warnings.warn(f"{caldir}: one density test at {n_cal:.3g} detections per pixel per "
                          f"cycle, used at {n_light:.3g}: the LSB changes with light (up to "
                          "40 ps, section 5.1); run `tcspc calibrate lsb` over this range",
                          stacklevel=2)
        return tdc.column("lsb_ps").to_numpy() * 1e-12
    lo, hi = fit.n_range
    if not fit.in_range(n_light):
        warnings.warn(f"{caldir}: light level {n_light:.3g} detections per pixel per cycle "
                      f"is outside the LSB fit's range [{lo:.3g}, {hi:.3g}]", stacklevel=2)
    return fit.lsb_ps(n_light) * 1e-12


def lsb_campaign(captures: list, out: str | Path, inl_rms_lsb: float = 0.5,
                 log=None) -> tuple[cal.DensityResult, cal.LsbFit, np.ndarray, np.ndarray]:
    """Density tests at several light levels -> LSB per TDC as a cubic in eq. 5.1's n, INL
    from the test with the smallest statistical error; written to ``out`` atomically.
    ``captures``: capture paths, or objects read like one (a daemon's journal run).

    The codes under that test's own reset peak, which it cannot measure, take the widths
    the other tests measured there (each at another light, so with its reset peak
    elsewhere), weighted against the phase mean by their errors (``density_test(fill=)``).

    Returns the density test kept for the INL, the fit, the light levels and the per-test
    LSBs (ps, TDC x test). Raises CalibrationError when no test reaches ``inl_rms_lsb``.
    """
    results, states = [], []
    for path in captures:
        cap = path if hasattr(path, "iter_chunks") else Capture(path)
        state, second = density_histograms(cap)  # dim tests give an LSB, not an INL
        res = cal.density_test(state.hits, state.cycles, cap.meta.window_ns * 1e-9,
                               artifacts=state.artifacts)
        results.append((cap, res, second))
        states.append(state)
        if log:
            log(f"{cap.bin_path.name}: {np.nanmean(res.detections_per_cycle):.3f} STARTs per "
                f"pixel per cycle, LSB {np.nanmean(res.lsb_s) * 1e12:.2f} ps (mean)")
    n = np.array([np.nanmean(r.detections_per_cycle) for _, r, _ in results])
    lsbs = np.column_stack([r.lsb_s * 1e12 for _, r, _ in results])
    fit = cal.fit_lsb(n, lsbs)
    def worst_inl(r: cal.DensityResult) -> float:  # inf when no TDC was calibrated
        e = r.inl_error_lsb[r.ok]
        return float(np.nanmax(e)) if np.isfinite(e).any() else float("inf")

    i_best = min(range(len(results)), key=lambda i: worst_inl(results[i][1]))
    best = results[i_best]
    others = [(st, r) for i, ((_, r, _), st) in enumerate(zip(results, states, strict=True))
              if i != i_best]
    if others:
        best = (best[0], refilled(states[i_best], best[1], others,
                                  best[0].meta.window_ns * 1e-9), best[2])
        if log:
            log(f"INL from {best[0].bin_path.name}; the codes under its reset peak also "
                f"from the {len(others)} other test(s)")
    worst = worst_inl(best[1])
    if not worst <= inl_rms_lsb:
        raise CalibrationError(f"the best density test ({best[0].bin_path.name}) gives an "
                               f"INL error of {worst:.2f} LSB RMS > {inl_rms_lsb}")
    sources = [p for c, _, _ in results for p in getattr(c, "paths", [c.bin_path])]
    write_caldir(out, best[1], best[2], sources, lsb_fit=fit)
    return best[1], fit, n, lsbs


#: What a delay measurement needs: return counts, and codes between the return and the
#: masked reset peak or window end, in instrument-response sigmas.
DELAY_MIN_COUNTS, DELAY_CLEAR_SIGMAS = 20, 3.0
RESET_MASK = 6  #: codes below x_T masked by the estimators (Histograms.from_codes margin)


def add_delay(capture, caldir: str | Path, log=None) -> np.ndarray:
    """Measure the system delay per TDC on a zero-distance capture (eq. 5.3) and rewrite
    ``caldir`` with it (atomically). Returns the delay in seconds (NaN where none).

    The peak's tau is the range stage's: the pile-up-exact ML on the calibrated time axis
    (so a target at zero distance ranges to zero). The axis's scale at the capture's light
    comes from the LSB polynomial, or from the capture's own reset peak where that is
    trustworthy: found where the polynomial puts it, on codes the density test measured,
    with the return (located first on the polynomial's axis) well clear of it
    (:func:`pipeline.offline.ranging.time_axis`); the source of each TDC's scale, and why the
    reset peak was declined, are recorded. A TDC without a delay gets the reason in
    ``meta.json`` (``delay.reasons``). Raises CalibrationError, leaving ``caldir`` as it
    was, when no TDC got a delay.
    """
    from pipeline.io.caldir import read_bounds
    from pipeline.offline.ranging import time_axis
    from stages.ranging import Histograms, ml

    cap = capture if hasattr(capture, "iter_chunks") else Capture(capture)
    res, meta = read_density(caldir)
    acc = HistogramAccumulator(cap.meta.n_tdc, read_bounds(caldir, cap.meta.n_tdc))
    for first, words in cap.iter_chunks():
        acc.update(words, first)
    state = acc.snapshot()
    light = float(state.hits.sum() / (state.n_tdc * max(state.cycles.max(), 1)))  # eq. 5.1
    window_s = cap.meta.window_ns * 1e-9

    def estimate(tau_edges, x_t, scale):
        irf = cal.histogram_sigma_s(state.hits, res, scale)
        irf = irf[np.isfinite(irf) & (irf > 0)]  # an empty histogram's width is 0
        widths = np.diff(tau_edges, axis=1)
        # the instrument response; 1 LSB where no TDC's peak says (as the range stage)
        sigma = float(np.median(irf)) if irf.size else \
            float(np.nanmedian(widths)) if np.isfinite(widths).any() else 200e-12
        h = Histograms.from_codes(state.hits, tau_edges, state.cycles, window_s, x_t=x_t)
        return ml(h, sigma), sigma

    # the return first on the polynomial's axis, so the reset peak's fit can keep clear of it
    tau_edges, x_t, scale, _ = time_axis(state, caldir, window_s, density=res)
    first, _ = estimate(tau_edges, x_t, scale)
    returns = np.array([np.interp(window_s - t, e, np.arange(e.size, dtype=np.float64))
                        if det and np.isfinite(t) and np.all(np.isfinite(e)) else np.nan
                        for t, e, det in zip(first.t_s, tau_edges, first.detected,
                                             strict=True)])
    tau_edges, x_t, scale, source = time_axis(state, caldir, window_s, in_situ=True,
                                              density=res, returns=returns)
    est, sigma = estimate(tau_edges, x_t, scale)
    d = cal.delay_s(cap.meta.t_laser_win_ns * 1e-9, window_s - est.t_s)
    # where the return sits: a return partly under the reset peak's mask or at the window's
    # end is biased (fit on one flank), one with a handful of counts is no measurement
    lsb = np.nanmedian(np.diff(tau_edges, axis=1), axis=1)
    at = np.array([np.interp(window_s - t, e, np.arange(e.size, dtype=np.float64))
                   if np.isfinite(t) and np.all(np.isfinite(e)) else np.nan
                   for t, e in zip(est.t_s, tau_edges, strict=True)])
    reach = DELAY_CLEAR_SIGMAS * sigma / lsb  # codes the return spreads over, each side
    reasons = np.full(state.n_tdc, "", dtype=object)
    reasons[~np.isfinite(d)] = "no peak position (estimator gave none)"
    reasons[at < 1 + reach] = ("return at the window's end (partly cut off): move the gate "
                               "(T_laser-win) later")
    reasons[at > np.floor(x_t) - RESET_MASK - reach] = (
        "return within reach of the reset peak (partly masked): move the gate "
        "(T_laser-win) earlier")
    reasons[np.asarray(est.signal_counts, np.float64) < DELAY_MIN_COUNTS] = (
        f"under {DELAY_MIN_COUNTS} return counts (a return under the reset peak, or too "
        "dim)")
    reasons[~np.asarray(est.detected, bool)] = "no return detected at the false-alarm rate"
    # the polynomial away from the light it was fitted at is a guess (0.7 ns of delay at
    # 0.8 detections a cycle on a fit over 0.02-0.69): only the capture's reset peak helps
    fit = read_lsb_fit(caldir)
    if fit is not None:
        lo, hi = fit.n_range
        off_fit = "" if fit.in_range(light) else \
            f"light {light:.3g} outside the LSB fit's range [{lo:.3g}, {hi:.3g}]"
    else:
        n_cal = meta.get("density", {}).get("detections_per_pixel_per_cycle", light)
        off_fit = "" if abs(light - n_cal) <= 0.02 else \
            f"one density test at {n_cal:.3g} detections a cycle, the capture at {light:.3g}"
    if off_fit:
        guess = (source != "reset peak") & (reasons == "")
        reasons[guess] = [f"{off_fit}, and the capture's own reset peak not usable "
                          f"({str(src).split(': ', 1)[-1]}): run `tcspc calibrate lsb` "
                          "over this light" for src in source[guess]]
    reasons[state.hits.sum(axis=1) == 0] = "no hits in the capture"
    reasons[~np.asarray(res.ok, bool)] = "flagged by the density test"
    d = np.where(reasons == "", d, np.nan)
    if not np.isfinite(d).any():
        counts = {r: int(np.sum(reasons == r)) for r in sorted(set(reasons.tolist()))}
        raise CalibrationError(f"{cap.bin_path}: no TDC got a delay ({counts}); {caldir} "
                               "is left as it was")
    if log:
        log(f"return found on the polynomial's axis on {int(np.isfinite(returns).sum())} of "
            f"{state.n_tdc} TDCs; time axis from the capture's reset peak on "
            f"{int(np.sum(source == 'reset peak'))}")
    tdc = read_tdc_table(caldir)
    second = cal.SecondStage(*(tdc.column(c).to_numpy().astype(np.int64)
                               for c in ("n_min", "n_max", "n_th", "pdm")))
    sources = [Path(s["path"]) for s in meta["sources"] if Path(s["path"]).exists()]
    extra = {k: v for k, v in meta.items() if k.startswith("lsb_")}
    write_caldir(caldir, res, second, sources + getattr(cap, "paths", [cap.bin_path]),
                 lsb_fit=read_lsb_fit(caldir),
                 delay_s=d, extra={**extra, "delay": {
                     "capture": str(cap.bin_path), "light": light,
                     "counts_used": np.round(est.signal_counts).tolist(),
                     "sigma_ps": np.round(est.sigma_s * 1e12, 3).tolist(),
                     "scale_from": source.tolist(),
                     "scale_from_reset_peak": int(np.sum(source == "reset peak")),
                     "tdcs_with_delay": int(np.isfinite(d).sum()),
                     "reasons": reasons.tolist(),
                     "irf_sigma_s": sigma}})
    return d


@dataclass(frozen=True)
class Quality:
    """What makes one calibration better than another: more TDCs calibrated, a smaller
    statistical INL error, a smaller LSB-fit residual, a measured delay."""

    tdcs_ok: int
    inl_error_lsb: float      #: median over calibrated TDCs
    lsb_residual_ps: float    #: RMS of the LSB fit's residuals (NaN with <= 4 levels: a
    #: cubic through 4 points has none, so there is nothing to compare)
    has_delay: bool

    def worse_than(self, other: Quality, slack: float = 0.1) -> list[str]:
        """Reasons this calibration is worse than ``other`` (empty: not worse). ``slack``
        is the relative margin a statistical figure may grow before it counts as worse."""
        why = []
        if self.tdcs_ok < other.tdcs_ok:
            why.append(f"calibrates {self.tdcs_ok} TDCs, the current one {other.tdcs_ok}")
        if self.inl_error_lsb > other.inl_error_lsb * (1 + slack):
            why.append(f"INL error {self.inl_error_lsb:.3f} LSB RMS against "
                       f"{other.inl_error_lsb:.3f}")
        if self.lsb_residual_ps > other.lsb_residual_ps * (1 + slack) + 0.05:  # NaN: False
            why.append(f"LSB fit residual {self.lsb_residual_ps:.3f} ps RMS against "
                       f"{other.lsb_residual_ps:.3f}")
        if other.has_delay and not self.has_delay:
            why.append("has no delay measurement, the current one has")
        return why


def quality(caldir: str | Path) -> Quality:
    res, meta = read_density(caldir)
    ok = res.ok
    delay = read_tdc_table(caldir).column("delay_ps").to_numpy(zero_copy_only=False)
    resid = np.asarray(meta.get("lsb_residual_ps", []), np.float64)
    return Quality(int(ok.sum()),
                   float(np.nanmedian(res.inl_error_lsb[ok])) if ok.any() else float("inf"),
                   float(np.sqrt(np.nanmean(resid ** 2))) if resid.ndim == 2
                   and resid.shape[1] > 4 else float("nan"),
                   bool(np.isfinite(np.asarray(delay, np.float64)).any()))
