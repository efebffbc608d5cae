"""``tcspc export``: a ranges file and a geometry as a point cloud (docs/geometry.md)."""

from __future__ import annotations

from pathlib import Path

import click

from pipeline.cli.console import err, warn

_SUFFIX = {".las": "las", ".ply": "ply", ".pcd": "pcd", ".mcap": "mcap"}


@click.command(short_help="Ranges and a geometry as a point cloud (LAS, PLY, PCD, MCAP).")
@click.argument("ranges", type=click.Path(exists=True))
@click.option("--geometry", "geometry", required=True,
              help="A shipped geometry (thesis128, tmf8820), a geometry .toml or a "
                   "pixel_geometry .parquet (docs/geometry.md).")
@click.option("--format", "fmt", type=click.Choice(["las", "ply", "pcd", "mcap"]),
              default=None, help="Default: from --out's suffix.")
@click.option("--out", required=True, type=click.Path(), help="The file to write.")
@click.option("--overwrite", is_flag=True, help="Replace --out if it exists.")
@click.option("-q", "--quiet", is_flag=True, help="No summary.")
def export(ranges, geometry, fmt, out, overwrite, quiet) -> None:
    """Write RANGES (a ranges parquet file or directory) as a point cloud: a point per
    detected return, x y z in metres in the geometry's frame (ROS REP 103: x forward, y
    left, z up), intensity = signal counts, sigma_m, return_index.

    LAS 1.4 (extra bytes for sigma_m), PLY, PCD, or ROS 2 sensor_msgs/PointCloud2 in MCAP
    (organised rows x cols, NaN where no return, one message per measurement at its
    time, further returns on their own topics).
    """
    fmt = fmt or _SUFFIX.get(Path(out).suffix.lower())
    if fmt is None:
        raise click.BadParameter(f"cannot tell the format from {out!r}; give --format "
                                 "las, ply, pcd or mcap", param_hint="--format")
    if Path(out).exists() and not overwrite:
        raise click.UsageError(f"--out {out} exists; give --overwrite to replace it")
    from pipeline.io import pointcloud
    from pipeline.io.geometry import load_geometry
    from pipeline.io.ranges import read_ranges

    geom = load_geometry(geometry)
    table = read_ranges(ranges)
    clouds, missing = pointcloud.clouds(table, geom,
                                        pointcloud.measurement_times(table, ranges))
    if missing:
        warn(f"{missing} detected return(s) of TDCs that geometry {geom.name} has no "
             "pixel for: not exported")
    n = pointcloud.write(fmt, clouds, geom, out)
    if not quiet:
        what = "messages" if fmt == "mcap" else "points"
        err.print(f"wrote {out}: {n:,} {what}, {len(clouds)} measurement(s), geometry "
                  f"{geom.name} ({geom.rows} x {geom.cols}, {geom.distance} distances)")
