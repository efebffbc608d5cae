"""``tcspc export``: a ranges file and a geometry as a point cloud (docs/geometry.md)."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from pipeline.cli.console import err, warn

_SUFFIX = {".las": "las", ".ply": "ply", ".pcd": "pcd", ".mcap": "mcap"}


@click.command(short_help="Ranges and a geometry as a point cloud (LAS, PLY, PCD, MCAP).")
@click.argument("ranges", type=click.Path(exists=True))
@click.option("--geometry", "geometry", required=True,
              help="A shipped geometry (thesis128, tmf8820, linospad2), a geometry .toml or a "
                   "pixel_geometry .parquet (docs/geometry.md).")
@click.option("--format", "fmt", type=click.Choice(["las", "ply", "pcd", "mcap"]),
              default=None, help="Default: from --out's suffix.")
@click.option("--out", required=True, type=click.Path(), help="The file to write.")
@click.option("--overwrite", is_flag=True,
              help="Replace an existing --out (without it an existing output is refused).")
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
    from pipeline.io.atomic import check_output

    check_output(out, "file", overwrite=overwrite)
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


def range_spatial(capture, out, spatial, geometry, irf_ps, p_fa, delay_ps, max_returns,
                  quiet, **refused) -> None:
    """`tcspc range --spatial` (pipeline/offline/spatial.py)."""
    import time

    from stages.ranging.validation import check_p_fa, check_sigma

    if not spatial:
        raise click.UsageError("--geometry is for --spatial (and `tcspc export`)")
    zero = refused.pop("zero", None)
    given = [f"--{k}" for k, v in refused.items() if v]
    if given:
        raise click.UsageError(f"{', '.join(given)}: not with --spatial (it takes "
                               "--delay-ps or --zero, and --irf-ps)")
    if irf_ps is None or (delay_ps is None) == (zero is None):
        raise click.UsageError("--spatial needs --irf-ps (the pulse's sigma) and one of "
                               "--delay-ps and --zero (a zero-distance file to measure the "
                               "delay on with the neighbours)")
    try:
        check_p_fa(p_fa)
        check_sigma(irf_ps, name="--irf-ps")
        if delay_ps is not None and not np.isfinite(delay_ps):
            raise ValueError(f"--delay-ps must be finite, found {delay_ps}")
    except ValueError as exc:
        raise click.BadParameter(str(exc)) from exc
    _spatial_input(capture)
    from pipeline.cli import instruments
    from pipeline.io.geometry import load_geometry
    from pipeline.offline.generic import write_ranges
    from pipeline.offline.spatial import range_spatial as run
    from pipeline.offline.spatial import zero_delay_spatial

    t0 = time.perf_counter()
    geom = load_geometry(geometry) if geometry else None
    delay_s, delay_sd, response = (delay_ps or 0.0) * 1e-12, 0.0, None
    if zero is not None:
        _spatial_input(zero)
        delay_s, delay_sd, n_zero, response = zero_delay_spatial(zero, irf_ps * 1e-12, p_fa,
                                                                 geom)
        if not quiet:
            k = -response.first + int(np.ceil(3 * irf_ps * 1e-12 / response.bin_s))
            late = response.share[k:].sum() / max(response.share.sum(), 1e-300)
            err.print(f"delay {delay_s * 1e12:.1f} ps +- {delay_sd * 1e12:.2f} ps and the "
                      f"response ({late:.0%} of a return's counts later than 3 sigma), "
                      "measured "
                      f"with the neighbours on {zero} ({n_zero} pixels detected)",
                      highlight=False)
    table, unplaced = run(capture, delay_s, irf_ps * 1e-12, p_fa, geom, max_returns or 2,
                          delay_sd_s=delay_sd, response=response)
    if unplaced:
        warn(f"{unplaced} row(s) without a place on the array: not ranged")
    write_ranges(table, out)
    if not quiet:
        det = np.asarray(table.column("detected").to_numpy(zero_copy_only=False))
        first = np.asarray(table.column("return_index").to_numpy()) == 0
        err.print(f"{int((det & first).sum())} of {int(first.sum())} pixels detected "
                  f"(+{int((det & ~first).sum())} further returns) (spatial, P_fa {p_fa:g} "
                  f"a pixel) in {time.perf_counter() - t0:.2f} s; "
                  f"{instruments.detected_span(table)}; wrote {out}", highlight=False)


def _spatial_input(capture) -> None:
    """--spatial without --calibration ranges generic histograms only: anything else is
    refused in one line naming the file and what it is (a LinoSPAD2 file was refused with
    pyarrow's "Parquet magic bytes not found", its fine-code histograms as not 'generic')."""
    from pipeline.cli import instruments

    fmt = instruments.detect(capture, None, histograms=True)
    if fmt == "histograms":
        if instruments.is_generic(capture):
            return
        import pyarrow.parquet as pq

        names = pq.ParquetFile(capture).schema_arrow.names
        inst = (sorted(set(map(str, pq.read_table(capture, columns=["instrument"])
                               .column("instrument").to_pylist())))
                if "instrument" in names else ["tcspc-chip"])
        what = ("LinoSPAD2 fine-code histograms (codes of a 2.5 ns clock period, not a "
                "time of flight)" if inst == ["linospad2"] else
                f"histograms of instrument {', '.join(inst)}")
    elif fmt == "tcspc":
        what = "a tcspc capture (its --spatial takes --calibration and --geometry)"
    else:
        what = {"linospad2": "a LinoSPAD2 raw capture (photon times with no laser sync)",
                "ptu": "a PicoQuant PTU file"}.get(fmt, f"a {fmt} file")
    raise instruments.BadInput(f"{capture}: {what}; --spatial without --calibration ranges "
                               "generic histograms (docs/instruments_generic.md)")
