"""Where each pixel looks: a geometry (a grid with its field of view, or a direction per
pixel, plus the sensor's position and orientation) and the points that distances along
those directions make. Pure numpy; the files are read by :mod:`pipeline.io.geometry`.

Frames follow ROS REP 103: the sensor looks along +x, +y is to its left, +z up.
Azimuth is measured from +x towards +y (to the left), elevation from the x-y plane up;
a pixel's unit direction is ``(cos el cos az, cos el sin az, sin el)``. On a grid, row 0
is the top row and column 0 the left column (an image seen from behind the sensor), so
row 0 looks up and column 0 to the left. The sensor's orientation is roll, pitch and yaw
(about x, y and z, applied in that order to the sensor frame: R = Rz(yaw) Ry(pitch)
Rx(roll)); a point is ``position + R @ (d * direction)``.

A distance is ``radial`` (the range along the pixel's line of sight, what a time of flight
measures: the default) or ``axial`` (the depth along the optical axis, +x: what a
calibration against a flat target's perpendicular distance gives, as the TMF8820's
`calibrate distance` does, its off-axis zones' longer slanted path taken up by the per-zone
scale).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

PROJECTIONS = ("pinhole", "equiangular")
DISTANCES = ("radial", "axial")


@dataclass(frozen=True)
class Geometry:
    """Per-pixel directions and the sensor's pose.

    ``tdc``, ``row``, ``col``, ``azimuth_rad``, ``elevation_rad``: arrays of one entry per
    pixel (``tdc`` the histogram row that pixel is, unique); ``rows`` x ``cols`` the
    array's shape (an organised cloud's height and width); ``position_m`` (3,) and
    ``rpy_rad`` (3,) the sensor's pose in the output frame ``frame_id``.
    """

    name: str
    rows: int
    cols: int
    tdc: np.ndarray
    row: np.ndarray
    col: np.ndarray
    azimuth_rad: np.ndarray
    elevation_rad: np.ndarray
    position_m: np.ndarray = field(default_factory=lambda: np.zeros(3))
    rpy_rad: np.ndarray = field(default_factory=lambda: np.zeros(3))
    distance: str = "radial"
    frame_id: str = "tcspc"
    note: str = ""

    def __post_init__(self) -> None:
        n = np.asarray(self.tdc).size
        if n == 0:
            raise ValueError(f"geometry {self.name!r}: no pixels")
        for k in ("row", "col", "azimuth_rad", "elevation_rad"):
            if np.asarray(getattr(self, k)).shape != (n,):
                raise ValueError(f"geometry {self.name!r}: {k} has shape "
                                 f"{np.asarray(getattr(self, k)).shape}, expected ({n},)")
        if np.unique(self.tdc).size != n:
            raise ValueError(f"geometry {self.name!r}: a tdc appears twice")
        if n and (np.asarray(self.row).min() < 0 or np.asarray(self.row).max() >= self.rows
                  or np.asarray(self.col).min() < 0 or np.asarray(self.col).max() >= self.cols):
            raise ValueError(f"geometry {self.name!r}: row/col outside {self.rows} x "
                             f"{self.cols}")
        if np.unique(np.asarray(self.row) * self.cols + np.asarray(self.col)).size != n:
            raise ValueError(f"geometry {self.name!r}: two pixels share a row and col")
        if not (np.all(np.isfinite(self.azimuth_rad))
                and np.all(np.isfinite(self.elevation_rad))):
            raise ValueError(f"geometry {self.name!r}: azimuth and elevation must be finite")
        if np.any(np.abs(self.elevation_rad) > math.pi / 2):
            raise ValueError(f"geometry {self.name!r}: elevation outside +-90 degrees")
        if self.distance not in DISTANCES:
            raise ValueError(f"geometry {self.name!r}: distance must be one of {DISTANCES}, "
                             f"found {self.distance!r}")

    @property
    def n_pixels(self) -> int:
        return int(np.asarray(self.tdc).size)

    def directions(self) -> np.ndarray:
        """Unit line-of-sight vectors (n_pixels, 3) in the sensor frame."""
        az, el = np.asarray(self.azimuth_rad), np.asarray(self.elevation_rad)
        return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)

    def rotation(self) -> np.ndarray:
        """R = Rz(yaw) Ry(pitch) Rx(roll), sensor frame to output frame."""
        return rotation_rpy(*np.asarray(self.rpy_rad, np.float64))

    def index_of(self, tdc) -> np.ndarray:
        """The geometry's pixel index of each ``tdc`` (-1 where it has none)."""
        tdc = np.asarray(tdc, np.int64)
        keys = np.asarray(self.tdc, np.int64)
        order = np.argsort(keys)
        pos = np.clip(np.searchsorted(keys[order], tdc), 0, keys.size - 1)
        return np.where(keys[order][pos] == tdc, order[pos], -1)


def rotation_rpy(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """The rotation matrix Rz(yaw) @ Ry(pitch) @ Rx(roll) (radians).

    >>> np.round(rotation_rpy(0, 0, math.pi / 2) @ [1, 0, 0], 12).tolist()  # yaw left
    [0.0, 1.0, 0.0]
    """
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch),
                              math.sin(pitch), math.cos(yaw), math.sin(yaw))
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def grid(name: str, rows: int, cols: int, fov_h_deg: float, fov_v_deg: float,
         projection: str = "pinhole", first_tdc: int = 0, **pose) -> Geometry:
    """A rows x cols array, ``tdc = first_tdc + row * cols + col``, its pixels' centres
    spread over the field of view.

    ``pinhole``: a flat array behind a lens (the centres equally spaced in the tangent of
    the angle, edges at +-tan(fov / 2)); ``equiangular``: equal angles (zones of a
    multi-zone sensor, a scanner). A field of view of 0 on an axis of one pixel is a line.

    >>> g = grid("g", 1, 3, 90.0, 0.0)
    >>> (np.round(np.degrees(g.azimuth_rad), 3) + 0.0).tolist()  # column 0 looks left
    [33.69, 0.0, -33.69]
    """
    if not (isinstance(rows, int | np.integer) and isinstance(cols, int | np.integer)
            and rows >= 1 and cols >= 1):
        raise ValueError(f"geometry {name!r}: rows and cols must be integers >= 1, found "
                         f"{rows} x {cols}")
    for k, v in (("fov_h_deg", fov_h_deg), ("fov_v_deg", fov_v_deg)):
        lim = 180.0 if projection == "equiangular" else 179.0
        if not (math.isfinite(v) and 0 <= v < lim):
            raise ValueError(f"geometry {name!r}: {k} must be in [0, {lim:g}), found {v}")
    if projection not in PROJECTIONS:
        raise ValueError(f"geometry {name!r}: projection must be one of {PROJECTIONS}, "
                         f"found {projection!r}")
    r, c = np.divmod(np.arange(rows * cols), cols)
    u = (c + 0.5) / cols * 2 - 1    # -1 (left edge) .. 1 (right edge)
    v = (r + 0.5) / rows * 2 - 1    # -1 (top) .. 1 (bottom)
    hh, hv = math.radians(fov_h_deg) / 2, math.radians(fov_v_deg) / 2
    if projection == "equiangular":
        az, el = -u * hh, -v * hv
    else:  # the ray through the image-plane point (1, -u tan hh, -v tan hv)
        y, z = -u * math.tan(hh), -v * math.tan(hv)
        az, el = np.arctan2(y, 1.0), np.arctan2(z, np.hypot(1.0, y))
    return Geometry(name, rows, cols, first_tdc + np.arange(rows * cols), r, c, az, el,
                    **pose)


def points(geom: Geometry, tdc, distance_m) -> np.ndarray:
    """x, y, z (n, 3) in the output frame of each (tdc, distance) pair; NaN where the tdc
    has no pixel in ``geom`` or the distance is not finite.

    >>> g = grid("g", 1, 1, 0.0, 0.0, position_m=np.array([0.0, 0.0, 1.5]))
    >>> points(g, [0], [2.0]).tolist()
    [[2.0, 0.0, 1.5]]
    """
    idx = geom.index_of(tdc)
    d = np.asarray(distance_m, np.float64)
    dirs = geom.directions()[np.maximum(idx, 0)]
    if geom.distance == "axial":  # the depth along +x: the range is depth / cos(off-axis)
        d = d / dirs[:, 0]
    local = dirs * d[:, None]
    out = local @ geom.rotation().T + np.asarray(geom.position_m, np.float64)
    out[(idx < 0) | ~np.isfinite(d)] = np.nan
    return out
