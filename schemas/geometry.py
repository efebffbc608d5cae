"""Where each pixel looks: the per-pixel table of a geometry (docs/geometry.md). A geometry
file (TOML) gives a grid and its field of view, or this table; either way the loader
(:mod:`pipeline.io.geometry`) makes this table, and `tcspc geometry --out` writes it."""

from __future__ import annotations

import pyarrow as pa

from schemas.core import SchemaSpec, field

PIXEL_GEOMETRY = SchemaSpec("pixel_geometry", "1.0", (
    field("tdc", pa.uint16(), "", "the histogram row (TDC, zone or pixel) this pixel is"),
    field("row", pa.uint16(), "", "row on the array, 0 at the top (an image seen from "
          "behind the sensor)"),
    field("col", pa.uint16(), "", "column on the array, 0 at the left"),
    field("azimuth_rad", pa.float64(), "rad", "line of sight from the sensor's +x "
          "(forward) towards +y (left), ROS REP 103"),
    field("elevation_rad", pa.float64(), "rad", "line of sight above the sensor's x-y "
          "plane"),
))
