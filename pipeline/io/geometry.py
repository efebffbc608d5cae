"""Geometry files (docs/geometry.md): a shipped name (``thesis128``, ``tmf8820``,
``linospad2``), a TOML file with a ``[grid]`` or a ``[pixels]`` section and a ``[pose]``, or a
``pixel_geometry`` parquet table. Checked at the door: every problem in one pass, a line each
naming the file, the section and the key (:class:`GeometryError`, exit 2)."""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Literal

import numpy as np
import pyarrow as pa
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from schemas.errors import TcspcError
from schemas.geometry import PIXEL_GEOMETRY
from stages.geometry import Geometry, grid

SHIPPED = Path(__file__).parents[2] / "geometries"


class GeometryError(TcspcError, ValueError):
    """A geometry file is missing or invalid (names the file, the section and the key)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class _Grid(_Strict):
    rows: int = Field(ge=1, le=65535, description="pixels down")
    cols: int = Field(ge=1, le=65535, description="pixels across")
    fov_h_deg: float = Field(ge=0, lt=180, description="horizontal field of view")
    fov_v_deg: float = Field(ge=0, lt=180, description="vertical field of view")
    projection: Literal["pinhole", "equiangular"] = "pinhole"
    first_tdc: int = Field(0, ge=0, description="tdc of row 0, column 0 (row-major)")


class _Pixels(_Strict):
    tdc: list[int] = Field(min_length=1)
    row: list[int]
    col: list[int]
    azimuth_deg: list[float]
    elevation_deg: list[float]


class _Pose(_Strict):
    position_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy_deg: tuple[float, float, float] = Field((0.0, 0.0, 0.0),
                                                description="roll, pitch, yaw")


class _File(_Strict):
    name: str = ""
    note: str = ""
    distance: Literal["radial", "axial"] = "radial"
    frame_id: str = "tcspc"
    grid: _Grid | None = None
    pixels: _Pixels | str | None = Field(None, description="a table, or a pixel_geometry "
                                         "parquet file beside this one")
    pose: _Pose = _Pose()


def shipped() -> list[str]:
    """The names of the geometries shipped with the package."""
    return sorted(p.stem for p in SHIPPED.glob("*.toml"))


def load_geometry(spec: str | Path) -> Geometry:
    """The geometry ``spec`` names: a shipped name, a ``.toml`` file or a ``.parquet``
    pixel_geometry table (pose zero, distances radial)."""
    path = Path(spec)
    if not path.exists() and (SHIPPED / f"{spec}.toml").exists():
        path = SHIPPED / f"{spec}.toml"
    if not path.exists():
        raise GeometryError(f"--geometry {spec}: no such file and not a shipped geometry "
                            f"({', '.join(shipped())})")
    if path.suffix == ".parquet":
        return _from_table(_read_table(path), path.stem, path)
    try:
        raw = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise GeometryError(f"{path}: not valid TOML: {exc}") from None
    try:
        f = _File.model_validate(raw)
    except ValidationError as exc:
        raise GeometryError("\n".join(
            f"{path} [{'.'.join(map(str, e['loc'][:-1])) or '-'}] {e['loc'][-1]}: "
            f"{e['msg']}" for e in exc.errors())) from None
    if (f.grid is None) == (f.pixels is None):
        raise GeometryError(f"{path}: give exactly one of [grid] and [pixels]")
    name = f.name or path.stem
    pose = dict(position_m=np.array(f.pose.position_m, np.float64),
                rpy_rad=np.radians(np.array(f.pose.rpy_deg, np.float64)),
                distance=f.distance, frame_id=f.frame_id, note=f.note)
    bad = [k for k, v in (("position_m", f.pose.position_m), ("rpy_deg", f.pose.rpy_deg))
           if not all(map(math.isfinite, v))]
    if bad:
        raise GeometryError(f"{path} [pose] {bad[0]}: must be finite")
    try:
        if f.grid is not None:
            g = f.grid
            return grid(name, g.rows, g.cols, g.fov_h_deg, g.fov_v_deg, g.projection,
                        g.first_tdc, **pose)
        if isinstance(f.pixels, str):
            table = _read_table(path.parent / f.pixels)
            return _from_table(table, name, path, **pose)
        p = f.pixels
        n = len(p.tdc)
        short = [k for k in ("row", "col", "azimuth_deg", "elevation_deg")
                 if len(getattr(p, k)) != n]
        if short:
            raise GeometryError(f"{path} [pixels] {short[0]}: {len(getattr(p, short[0]))} "
                                f"entries, tdc has {n}")
        return _make(name, np.array(p.tdc), np.array(p.row), np.array(p.col),
                     np.radians(p.azimuth_deg), np.radians(p.elevation_deg), **pose)
    except GeometryError:
        raise
    except ValueError as exc:
        raise GeometryError(f"{path}: {exc}") from None


def _read_table(path: Path) -> pa.Table:
    import pyarrow.parquet as pq

    from schemas.core import validate

    try:
        table = pq.read_table(path)
        validate(table.cast(PIXEL_GEOMETRY.schema), PIXEL_GEOMETRY, where=str(path))
    except (OSError, pa.ArrowInvalid, ValueError) as exc:
        raise GeometryError(f"{path}: not a pixel_geometry table: {exc}") from None
    return table


def _make(name, tdc, row, col, az, el, **pose) -> Geometry:
    return Geometry(name, int(row.max()) + 1, int(col.max()) + 1, tdc.astype(np.int64),
                    row.astype(np.int64), col.astype(np.int64), np.asarray(az, np.float64),
                    np.asarray(el, np.float64), **pose)


def _from_table(table: pa.Table, name: str, where, **pose) -> Geometry:
    try:
        c = {k: table.column(k).to_numpy() for k in PIXEL_GEOMETRY.names}
        return _make(name, c["tdc"], c["row"], c["col"], c["azimuth_rad"],
                     c["elevation_rad"], **pose)
    except ValueError as exc:
        raise GeometryError(f"{where}: {exc}") from None


def geometry_table(geom: Geometry) -> pa.Table:
    """The per-pixel table of ``geom`` (schema ``pixel_geometry``)."""
    return pa.table({"tdc": geom.tdc, "row": geom.row, "col": geom.col,
                     "azimuth_rad": geom.azimuth_rad, "elevation_rad": geom.elevation_rad},
                    schema=PIXEL_GEOMETRY.schema)
