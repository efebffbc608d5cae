"""Calibration directories (docs/design.md "Outputs"), loaded and saved in one place.

A directory holds ``tdc.parquet`` (calibration_tdc), ``inl.parquet`` (calibration_inl) and
``meta.json``: schema version, software version, date, the SHA-256 of every capture it came
from, the light level of each density test, the scaling of the LSB polynomial's x and the
delay measurement with a reason for every TDC without a delay.
:func:`load_calibration` reads and validates the whole directory once into a
:class:`stages.calibration_set.Calibration`; :func:`save_calibration` writes one atomically
(a failure leaves the old directory in place). :func:`read_bounds` reads only what the
data path needs (Nmin/Nmax)."""

from __future__ import annotations

import datetime as dt
import hashlib
import json
import os
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.io.atomic import atomic_path
from schemas.constants import N_CODES
from schemas.core import validate
from schemas.errors import CalibrationError, SchemaMismatch, SchemaVersionError
from schemas.outputs import CALIBRATION_INL, CALIBRATION_TDC
from stages import calibration as cal
from stages.artifact import ArtifactBounds
from stages.calibration_set import Calibration


def read_tdc_table(caldir: str | os.PathLike):
    """``tdc.parquet`` of a calibration directory, validated."""
    path = Path(caldir) / "tdc.parquet"
    if not path.is_file():
        raise CalibrationError(f"{caldir}: not a calibration directory (no tdc.parquet)")
    meta_path = Path(caldir) / "meta.json"
    if meta_path.is_file():
        try:
            meta = json.loads(meta_path.read_text())
        except json.JSONDecodeError as exc:
            raise CalibrationError(f"{meta_path}: not valid JSON: {exc}") from exc
        CALIBRATION_TDC.check_version(str(meta.get("schema_version", "1.0")), str(meta_path))
    # (read_table imports pyarrow.dataset: 60 ms)
    return _validated_tdc(pq.ParquetFile(path).read(), path)


def _validated_tdc(table, path: Path):
    """tables of version 1.0 lack the "ok" column: validate what 1.0 had"""
    try:
        CALIBRATION_TDC.check_metadata(table.schema.metadata, str(path))
        spec = CALIBRATION_TDC
        if "ok" not in table.column_names:  # a 1.0 table: every TDC counts as ok
            spec = type(spec)(spec.name, "1.0", tuple(f for f in spec.fields
                                                       if f.name != "ok"))
        validate(table, spec, str(path), allow_extra=True)
    except (SchemaMismatch, SchemaVersionError) as exc:
        raise CalibrationError(str(exc)) from exc
    return table


def read_bounds(caldir: str | os.PathLike, n_tdc: int) -> ArtifactBounds:
    """Per-TDC [Nmin, Nmax] from a calibration, checked against the data's TDC count."""
    table = read_tdc_table(caldir)
    tdc = table.column("tdc").to_numpy().astype(np.int64)
    if np.unique(tdc).size != tdc.size or tdc.size != n_tdc or tdc.max() != n_tdc - 1:
        raise CalibrationError(f"{caldir}: calibration covers TDCs {sorted(set(tdc))[:4]}"
                               f"... ({tdc.size} rows); the data has {n_tdc} TDCs")
    order = np.argsort(tdc)
    return ArtifactBounds(table.column("n_min").to_numpy()[order],
                          table.column("n_max").to_numpy()[order],
                          source=f"calibration:{Path(caldir).resolve()}")


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


#: inl.parquet's column of each code width's standard error (LSB), from the calibration's
#: counts (calibration_inl 1.1, issue 33.3); null where not known, absent in 1.0 files
WIDTH_SIGMA = "width_sigma_lsb"

#: the files whose bytes make a calibration's identity (:func:`calibration_id`)
CAL_FILES = ("tdc.parquet", "inl.parquet", "meta.json")


def _snapshot(caldir: Path, attempts: int = 3) -> tuple[Path, dict]:
    """The bytes of every file of one version, read through ``caldir`` resolved once: a
    ``current`` link swapped by a publish while we read never mixes two versions. A version
    pruned between the resolve and the reads is retried through the link."""
    for _ in range(attempts):
        real = Path(os.path.realpath(caldir))
        try:
            return real, {name: (real / name).read_bytes() for name in CAL_FILES
                          if name != "meta.json" or (real / name).is_file()}
        except FileNotFoundError:
            continue
    missing = "tdc.parquet" if not (caldir / "tdc.parquet").is_file() else "inl.parquet"
    what = ("not a calibration directory (no tdc.parquet)" if missing == "tdc.parquet"
            else "no inl.parquet (not a density-test calibration)")
    raise CalibrationError(f"{caldir}: {what}")


def calibration_id(files: dict) -> str:
    """A calibration's identity: the SHA-256 (first 16 hex digits) of its files' names and
    bytes, the same wherever the directory is copied; recorded by every output made with it."""
    h = hashlib.sha256()
    for name in sorted(files):
        h.update(f"{name}\0{len(files[name])}\0".encode())
        h.update(files[name])
    return h.hexdigest()[:16]


def load_calibration(caldir: str | os.PathLike) -> Calibration:
    """The whole calibration directory, validated, as one immutable object. A link
    (``current``) is resolved once and every file read from that version; ``path`` is the
    version's own directory and ``meta["calibration_id"]`` its identity."""
    caldir = Path(caldir)
    real, files = _snapshot(caldir)
    meta_path = real / "meta.json"
    try:
        meta = json.loads(files["meta.json"]) if "meta.json" in files else {}
    except json.JSONDecodeError as exc:
        raise CalibrationError(f"{meta_path}: not valid JSON: {exc}") from exc
    CALIBRATION_TDC.check_version(str(meta.get("schema_version", "1.0")), str(meta_path))
    tdc = _validated_tdc(pq.ParquetFile(pa.BufferReader(files["tdc.parquet"])).read(),
                         real / "tdc.parquet")
    inl_path = real / "inl.parquet"
    inl = pq.ParquetFile(pa.BufferReader(files["inl.parquet"])).read()
    spec = CALIBRATION_INL
    if WIDTH_SIGMA not in inl.column_names:  # a 1.0 table: no uncertainty stored
        spec = type(spec)(spec.name, "1.0", tuple(f for f in spec.fields
                                                   if f.name != WIDTH_SIGMA))
    try:
        validate(inl, spec, str(inl_path), allow_extra=True)
    except (SchemaMismatch, SchemaVersionError) as exc:
        raise CalibrationError(str(exc)) from exc
    meta = {**meta, "calibration_id": calibration_id(files)}
    caldir = real
    n = tdc.num_rows
    if inl.num_rows != n * N_CODES:
        raise CalibrationError(f"{inl_path}: {inl.num_rows} rows, {n} TDCs x {N_CODES} codes "
                               "expected")
    order = np.argsort(tdc.column("tdc").to_numpy())
    if not np.array_equal(tdc.column("tdc").to_numpy()[order], np.arange(n)):
        raise CalibrationError(f"{caldir}: tdc.parquet must hold TDCs 0..{n - 1} once each")

    def col(name):
        return tdc.column(name).to_numpy(zero_copy_only=False)[order]

    key = np.lexsort((inl.column("code").to_numpy(), inl.column("tdc").to_numpy()))

    def grid(c):
        return inl.column(c).to_numpy()[key].reshape(n, N_CODES)

    ok = col("ok").astype(bool) if "ok" in tdc.column_names else np.ones(n, bool)
    d = meta.get("density", {})
    density = cal.DensityResult(col("lsb_ps") * 1e-12,
                                np.asarray(d.get("x_t", np.full(n, np.nan)), np.float64),
                                grid("width_lsb"), grid("dnl_lsb"), grid("inl_lsb"),
                                np.full(n, np.nan),
                                np.full(n, d.get("detections_per_pixel_per_cycle", np.nan)),
                                ok, np.asarray(d.get("inl_error_lsb", np.full(n, np.nan)),
                                               np.float64),
                                tuple(d["reasons"]) if len(d.get("reasons", ())) == n else ())
    second = cal.SecondStage(*(col(c).astype(np.int64) for c in ("n_min", "n_max", "n_th",
                                                                  "pdm")))
    px = meta.get("lsb_poly_x")
    fit = None
    if px is not None:
        resid = np.asarray(meta.get("lsb_residual_ps", np.empty((n, 0))), np.float64)
        levels = px.get("levels")  # absent in calibrations before the spline: the cubic
        sig = meta.get("lsb_sigma_ps")  # absent before the points' own errors
        sig = None if sig is None else np.array(
            [[np.nan if v is None else v for v in row] for row in sig], np.float64)
        fit = cal.LsbFit(np.stack(col("lsb_poly")), px["mean"], px["scale"],
                         tuple(px["n_range"]), resid,
                         None if levels is None or len(levels) != resid.shape[-1]
                         else np.asarray(levels, np.float64),
                         None if sig is None or sig.shape != resid.shape else sig)
    delay = np.asarray(col("delay_ps"), np.float64) * 1e-12
    dm = meta.get("delay", {})
    var = None
    if WIDTH_SIGMA in inl.column_names and inl.column(WIDTH_SIGMA).null_count < inl.num_rows:
        var = grid(WIDTH_SIGMA) ** 2
    return Calibration(density, second, fit, delay, tuple(dm.get("reasons", ())),
                       dm.get("irf_sigma_s"), meta, str(caldir), width_var_lsb2=var)


def save_calibration(calibration: Calibration, out: str | os.PathLike,
                     sources: list | None = None) -> Path:
    """Write a calibration directory atomically (a failure leaves the old one in place).
    ``sources``: the captures it came from (recorded with their SHA-256); by default the
    ones its provenance already names."""
    c, n = calibration, calibration.n_tdc
    density, second, fit = c.density, c.second, c.lsb_fit
    lsb_ps = density.lsb_s * 1e12
    poly = fit.coef if fit is not None else np.column_stack([lsb_ps, np.zeros((n, 3))])
    delay = np.where(np.isfinite(c.delay_s), c.delay_s * 1e12, np.nan)
    tdc = pa.table({
        "tdc": pa.array(np.arange(n), pa.uint16()),
        "lsb_ps": pa.array(lsb_ps),
        "lsb_poly": pa.FixedSizeListArray.from_arrays(pa.array(np.ravel(poly)), 4),
        "n_min": pa.array(np.maximum(second.n_min, 0), pa.uint16()),
        "n_max": pa.array(np.maximum(second.n_max, 0), pa.uint16()),
        "n_th": pa.array(np.maximum(second.n_th, 0), pa.uint16()),
        "pdm": pa.array(np.maximum(second.pdm, 0), pa.uint16()),
        "delay_ps": pa.array(delay, pa.float64(), mask=~np.isfinite(delay)),
        "ok": pa.array(np.asarray(density.ok, bool)),
    }, schema=CALIBRATION_TDC.schema)
    codes = np.arange(N_CODES)
    inl = pa.table({
        "tdc": pa.array(np.repeat(np.arange(n), N_CODES), pa.uint16()),
        "code": pa.array(np.tile(codes, n), pa.uint16()),
        "width_lsb": pa.array(np.ravel(density.width_lsb)),
        "dnl_lsb": pa.array(np.ravel(density.dnl_lsb)),
        "inl_lsb": pa.array(np.ravel(density.inl_lsb)),
        WIDTH_SIGMA: (pa.nulls(n * N_CODES, pa.float64()) if c.width_var_lsb2 is None
                      else pa.array(np.ravel(np.sqrt(c.width_var_lsb2)))),
    }, schema=CALIBRATION_INL.schema)
    if sources is None:
        recorded = c.meta.get("sources", [])
    else:
        recorded = [{"path": str(p), "sha256": sha256(Path(p))} for p in sources]
    meta = {
        **{k: v for k, v in c.meta.items() if k not in ("lsb_poly_x", "lsb_residual_ps",
                                                         "lsb_sigma_ps", "delay",
                                                         "calibration_id")},
        "schema_version": CALIBRATION_TDC.version, "software": software_version(),
        "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        "sources": recorded,
        "density": {**c.meta.get("density", {}),
                    "detections_per_pixel_per_cycle": float(
                        np.nanmean(density.detections_per_cycle)),
                    "x_t": np.asarray(density.x_t).tolist(),
                    "inl_error_lsb": np.asarray(density.inl_error_lsb).tolist(),
                    "flagged_tdcs": np.flatnonzero(~np.asarray(density.ok, bool)).tolist(),
                    "reasons": list(density.reasons)},
        **({"lsb_poly_x": {"mean": fit.x_mean, "scale": fit.x_scale,
                           "n_range": list(fit.n_range),
                           **({"levels": np.asarray(fit.levels).tolist()}
                              if fit.levels is not None else {})},
            "lsb_residual_ps": np.asarray(fit.residual_ps).tolist(),
            **({"lsb_sigma_ps": [[None if not np.isfinite(v) else float(v) for v in row]
                                 for row in np.asarray(fit.sigma_ps, np.float64)]}
               if fit.sigma_ps is not None else {})} if fit else {}),
        **({"delay": c.meta["delay"]} if "delay" in c.meta else {}),
    }
    out = Path(out)
    with atomic_path(out) as tmp:
        tmp.mkdir(parents=True)
        pq.write_table(tdc, tmp / "tdc.parquet")
        pq.write_table(inl, tmp / "inl.parquet")
        (tmp / "meta.json").write_text(json.dumps(meta, indent=1))
    return out
