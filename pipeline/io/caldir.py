"""Reading what the data path needs from a calibration directory (DESIGN.md "Outputs")."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from schemas.core import validate
from schemas.errors import CalibrationError, SchemaMismatch, SchemaVersionError
from schemas.outputs import CALIBRATION_TDC
from stages.artifact import ArtifactBounds


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
    # tables of version 1.0 lack the "ok" column: validate what 1.0 had
    table = pq.read_table(path)
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
