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
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.atomic import atomic_path
from pipeline.caldir import read_tdc_table
from pipeline.capture import Capture
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


def density_from_capture(capture: Capture, inl_rms_lsb: float | None = 0.3,
                         progress=None) -> tuple[cal.DensityResult, cal.SecondStage]:
    """Run a density test on a uniform-light capture (two passes: second stage, then D1st).

    Raises CalibrationError when the capture is too small for ``inl_rms_lsb`` (None: no
    check), saying how many cycles are needed.
    """
    n_tdc = capture.meta.n_tdc
    ss = cal.SecondStageAccumulator(n_tdc)
    for first, words in capture.iter_chunks():
        ss.update(words, first)
        if progress:
            progress(words.size)
    second = cal.second_stage_params(ss.counts)
    acc = HistogramAccumulator(n_tdc, second.bounds)
    for first, words in capture.iter_chunks():
        acc.update(words, first)
        if progress:
            progress(words.size)
    state = acc.snapshot()
    res = cal.density_test(state.hits, state.cycles, capture.meta.window_ns * 1e-9)
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
