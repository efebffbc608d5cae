"""The offline commands on real instruments' files (PTU, LinoSPAD2): the parts of
``tcspc decode``, ``histogram`` and ``range`` that are not the thesis chip's."""

from __future__ import annotations

import time
from pathlib import Path

import click

from pipeline.cli.console import Incomplete, InternalError, err, warn

#: what a command's CAPTURE may be, for the messages that refuse one
_INPUTS = ("a capture (NAME.bin with NAME.json beside it), a PicoQuant PTU file or "
           "LinoSPAD2 raw words")


def detect(path: str, given: str | None, histograms: bool = False) -> str:
    """The format of ``path``: ``--format`` if given, else read from the content; a
    parquet file is a ``histograms`` dataset, which only ``range`` takes (``histograms``).
    A directory, an empty file or a parquet file where none is taken is refused by what
    it is, not by the formats it is not."""
    from pipeline.io.capture import capture_paths
    from pipeline.io.formats import FormatError, resolve_format

    p = Path(path)
    if p.is_dir() and not capture_paths(p)[0].is_file():
        raise FormatError(f"{path}: a directory; give a file: {_INPUTS}"
                          + (", or a histograms parquet file" if histograms else ""))
    if p.is_file() and given is None:
        with open(path, "rb") as fh:  # 4 bytes, not the file (a PTU file can be GBs)
            head = fh.read(4)
        if not head:
            raise FormatError(f"{path}: an empty file (0 bytes)")
        if head == b"PAR1":
            if not histograms:
                raise FormatError(f"{path}: a parquet file; this command takes {_INPUTS} "
                                  "(`tcspc range` takes histograms parquet)")
            return "histograms"
    return resolve_format(path, given)


def is_generic(path: str) -> bool:
    from pipeline.io.generic import is_generic as generic

    return generic(path)


def range_generic(path: str, out: str, calibration, delay_ps, zero, gate, estimator, irf_ps,
                  p_fa, quiet: bool, max_returns: int | None = None) -> None:
    """Ranges of a generic histograms file (any instrument's) on its own uniform bins."""
    import polars as pl

    from pipeline.offline.generic import DistanceCalibration, write_ranges
    from pipeline.offline.generic import range_generic as rng_generic
    from schemas.errors import CalibrationError

    given = [n for n, x in (("--calibration", calibration), ("--delay-ps", delay_ps),
                            ("--zero", zero)) if x is not None]
    if len(given) != 1:
        raise click.UsageError("generic histograms need exactly one of --calibration (from "
                               "`tcspc calibrate distance`), --delay-ps or --zero"
                               + (f"; given {' and '.join(given)}" if given else ""))
    if gate is not None:
        raise click.UsageError("--gate is for a PicoQuant T3 file")
    t0 = time.perf_counter()
    try:
        cal = DistanceCalibration.load(calibration) if calibration else None
        table, info = rng_generic(path, cal, None if delay_ps is None else delay_ps * 1e-12,
                                  zero, None if irf_ps is None else irf_ps * 1e-12,
                                  estimator, p_fa, max_returns=max_returns)
    except (CalibrationError, ValueError) as exc:
        msg = str(exc)
        if irf_ps is not None and msg.startswith("sigma_s"):  # (name the user's option)
            msg = f"--irf-ps {irf_ps:g}: {msg}"
        elif msg.startswith("p_fa"):
            msg = f"--p-fa {p_fa:g}: {msg}"
        raise BadInput(f"{path}: {msg}" if str(path) not in msg else msg) from None
    write_ranges(table, out)
    if not quiet:
        err.print(f"instrument response: {info['response']}; pile-up: {info['pileup']}",
                  highlight=False)
    if "bright" in info:
        warn(info["bright"])
    if "returns" in info and not quiet:
        err.print(f"returns: {info['returns']}", highlight=False)
    if "crosstalk" in info:
        warn(info["crosstalk"])
    df = pl.from_arrow(table)
    more = df.filter(pl.col("detected") & (pl.col("return_index") > 0)).height
    df = df.filter(pl.col("return_index") == 0)
    det = df.filter(pl.col("detected"))
    if not quiet:
        err.print(f"{det.height} of {df.height} rows detected"
                  + (f" (+{more} further returns)" if more else "")
                  + f" ({estimator}, P_fa {p_fa:g}) in "
                  f"{df['measurement'].n_unique()} measurement(s), "
                  f"{time.perf_counter() - t0:.2f} s; {detected_span(table)}; wrote {out}",
                  highlight=False)


def detected_span(table) -> str:
    """The summary's distances: the detected returns' range, or that there is none (an
    undetected row's distance is its best candidate's, not a return: never summarised)."""
    import numpy as np

    det = np.asarray(table.column("detected").to_numpy(zero_copy_only=False), bool)
    d = np.asarray(table.column("distance_m").to_numpy(zero_copy_only=False), np.float64)[det]
    d = d[np.isfinite(d)]
    if not d.size:
        return "no return detected"
    return f"distance {d.min():.4f}..{d.max():.4f} m"


def _print_summary(summary, quiet: bool) -> None:
    lines = summary.lines()
    for line in lines if not quiet else [ln for ln in lines if ln.startswith("warning")]:
        err.print(line, highlight=False, markup=False)


#: exit status of `tcspc histogram` / `decode` on an instrument file cut short (the output
#: holds the records before the damage and is flagged truncated; --allow-truncated: 0)
EXIT_TRUNCATED = 3


class Truncated(Incomplete):
    """An input file cut short (exit 3, :data:`EXIT_TRUNCATED`)."""


class BadInput(click.ClickException):
    """A file or an option that no result can come from: one line, exit 2 (docs/design.md;
    a plain ClickException exits 1)."""
    exit_code = 2


def _check_truncated(path: str, out: str, summary, allow: bool) -> None:
    if summary.truncated and not allow:
        raise Truncated(f"{path} is truncated: {out} holds its {summary.records:,} whole "
                        "records before the damage, flagged truncated in its metadata; "
                        "--allow-truncated accepts that (exit 0)")


def _check_accounting(summary) -> None:
    if summary.accounted != summary.records:
        raise InternalError(f"accounting error: {summary.accounted:,} records "
                            f"classified, {summary.records:,} read")


def histograms_of(path: str, fmt: str, measurement: str | None, firmware: str, by: str):
    """(histograms table, summary or None) of an instrument's file or a histograms file."""
    from pipeline.offline import instruments as inst

    if fmt == "histograms":
        from pipeline.io.histograms import read_histograms

        return read_histograms(path), None
    if fmt == "ptu":
        return inst.histogram_ptu(path, measurement)
    if fmt == "linospad2":
        return inst.histogram_linospad2(path, firmware, by, measurement)
    raise click.ClickException(f"{path}: {fmt} is not an instrument format")


def refuse_if_not(path: str, fmt: str) -> None:
    """A file given ``--format linospad2`` whose lines mostly break that format's structure
    is refused before anything is written, naming the format its content reads as (a tcspc
    capture read as LinoSPAD2 gave a parquet of millions of invalid records, exit 0)."""
    if fmt != "linospad2" or not Path(path).is_file():
        return
    from pipeline.io.formats import FormatError, detect_format
    from pipeline.io.linospad2 import broken_lines

    broken, lines = broken_lines(path)
    if lines and broken * 2 > lines:
        try:
            likely = detect_format(path)
        except FormatError:
            likely = None
        hint = (f"; its content reads as a {likely} file: give --format {likely} or leave "
                "--format out" if likely and likely != fmt else "")
        raise FormatError(f"{path}: not a LinoSPAD2 file: {broken} of its first {lines} "
                          "lines have invalid words before valid ones, which that format "
                          f"never has{hint}; nothing written")


def histogram(path: str, fmt: str, out: str, measurement, firmware: str, by: str,
              quiet: bool, allow_truncated: bool = False) -> None:
    from pipeline.offline.instruments import write_instrument_histograms

    refuse_if_not(path, fmt)
    table, summary = histograms_of(path, fmt, measurement, firmware, by)
    _check_accounting(summary)
    write_instrument_histograms(table, out, path, summary)
    _print_summary(summary, quiet)
    if summary.events == 0:  # said even with --quiet: an all-zero histogram is suspicious
        err.print(f"warning: {path}: no photon in the file; the histograms are all zero",
                  highlight=False)
    if not quiet:
        err.print(f"wrote {out} ({table.num_rows} rows)")
    _check_truncated(path, out, summary, allow_truncated)


def decode(path: str, fmt: str, out: str, firmware: str, quiet: bool,
           allow_truncated: bool = False) -> None:
    from pipeline.offline.instruments import decode_instrument

    refuse_if_not(path, fmt)
    if Path(out).suffix.lower() in (".h5", ".hdf5"):
        return _photon_hdf5(path, fmt, out, quiet)

    summary = decode_instrument(path, fmt, out, firmware)
    _check_accounting(summary)
    _print_summary(summary, quiet)
    if not quiet:
        err.print(f"wrote {out}")
    _check_truncated(path, out, summary, allow_truncated)


def _photon_hdf5(path: str, fmt: str, out: str, quiet: bool) -> None:
    """``tcspc decode FILE.ptu --out FILE.h5``: the photons as Photon-HDF5 (phconvert)."""
    if fmt != "ptu":
        raise click.UsageError(f"Photon-HDF5 export takes a PTU file; {path} is {fmt}")
    from pipeline.io.ptu import export_photon_hdf5

    try:
        info = export_photon_hdf5(path, out)
    except ModuleNotFoundError as exc:
        raise click.ClickException(f"{exc}; or: pip install 'tcspc-lidar[hdf5]'") from None
    if not quiet:
        err.print(f"wrote {out} (Photon-HDF5): " + ", ".join(
            f"{k} {v:,}" for k, v in info.items() if isinstance(v, int)), highlight=False)


def _gate(gate: str | None):
    if gate is None:
        return None
    try:
        lo, hi = (float(x) for x in gate.split(":"))
    except ValueError:
        raise click.BadParameter(f"--gate takes LO:HI in ns, found {gate!r}") from None
    if not 0 <= lo < hi:
        raise click.BadParameter(f"--gate needs 0 <= LO < HI, found {gate!r}")
    return lo, hi


def range_instrument(path: str, fmt: str, out: str, delay_ps, zero, gate, estimator,
                     irf_ps, p_fa, firmware: str, quiet: bool,
                     max_returns: int | None = None, allow_truncated: bool = False) -> None:
    """Ranges of a T3 file's (or its histograms') channels on the instrument's own uniform
    time axis, with a given delay or one measured on a zero-distance file. One return a
    channel unless ``max_returns`` asks for more: then the zero file's returns are the
    instrument's measured response, which the search for further returns models each
    found return with, tail included; without ``--zero`` further returns are searched with
    Gaussian tails, and a warning says that a real response's tail may be found as a
    surface (docs/ranging.md, "Real responses")."""
    import numpy as np
    import polars as pl

    from pipeline.io.atomic import atomic_path
    from pipeline.offline.instruments import (
        measured_delay,
        range_uniform,
        truncation,
        zero_response,
    )
    from pipeline.offline.ranging import ranges_table

    if (delay_ps is None) == (zero is None):
        raise click.UsageError("an instrument's file needs its delay: give --delay-ps or "
                               "--zero ZERO_DISTANCE_FILE (not both)")
    t0 = time.perf_counter()
    g = _gate(gate)
    table, summary = histograms_of(path, fmt, None, firmware, "tdc")
    cut = [truncation(path, table, summary)]
    sigma = None if irf_ps is None else irf_ps * 1e-12
    response = None
    if zero is not None:
        ztable, zsummary = histograms_of(zero, detect(zero, None, histograms=True), None,
                                      firmware, "tdc")
        cut.append(truncation(zero, ztable, zsummary))
    cut = [c for c in cut if c]
    if cut and not allow_truncated:  # a delay or a return from part of a file: refused
        raise Truncated("; ".join(cut) + ": its ranges would come from part of a "
                        "measurement; nothing written (--allow-truncated ranges it anyway, "
                        "flagged in the output)")
    for c in cut:
        warn(c + " (--allow-truncated: ranged anyway, flagged tcspc.truncated)")
    if zero is not None:
        delay, zsigma = measured_delay(ztable, sigma, estimator, p_fa, g)
        if ztable.num_rows != table.num_rows:
            raise BadInput(f"{zero} has {ztable.num_rows} channels, {path} "
                                       f"{table.num_rows}")
        if sigma is None and np.isfinite(zsigma).any():
            sigma = float(np.nanmedian(zsigma))
        how = f"measured on {zero} ({int(np.isfinite(delay).sum())} of {delay.size} channels)"
        if not np.isfinite(delay).any():
            raise BadInput(f"{zero}: no return detected on any channel, no delay")
        response = zero_response(ztable, delay, str(zero), g)
        wz = np.nanmedian(ztable.column("bin_width_ps").to_numpy())
        w = np.nanmedian(table.column("bin_width_ps").to_numpy())
        if abs(wz / w - 1) > 0.01:
            raise BadInput(f"{zero} has {wz:g} ps bins, {path} {w:g} ps: the zero "
                                       "file must be taken at the same resolution")
    else:
        delay = np.full(table.num_rows, delay_ps * 1e-12)
        how = f"given, {delay_ps:g} ps"
    max_returns = max_returns or 1
    if max_returns > 1 and response is None:
        warn(f"--max-returns {max_returns} without --zero: further returns are searched with "
             "Gaussian tails, so a further return may be the response's own tail (give "
             "--zero: its returns are the measured response)")
    est, d, s, note = range_uniform(table, delay, sigma, estimator, p_fa, g, max_returns,
                                    response)
    if max_returns > 1 and response is not None:
        note += f"; further returns modelled on the response measured on {response.source}"
    name = table.column("measurement")[0].as_py() if table.num_rows else Path(path).stem
    ranges = ranges_table(name, est, d, s)
    ranges = ranges.replace_schema_metadata({
        **ranges.schema.metadata, b"tcspc.source": str(path).encode(),
        b"tcspc.delay": how.encode(), b"tcspc.time_axis": note.encode(),
        **({b"tcspc.truncated": b"True"} if cut else {})})
    import pyarrow.parquet as pq

    with atomic_path(out) as tmp:
        pq.write_table(ranges, tmp)
    if not quiet:
        err.print(f"time axis: {note}; delay {how}", highlight=False)
        df = pl.from_arrow(ranges)
        for r in df.iter_rows(named=True):
            err.print(f"  channel {r['tdc']}"
                      + (f" return {r['return_index']}" if r["return_index"] else "") + ": " + (
                f"{r['distance_m']:.4f} m +- {r['sigma_m']:.4f} m, {r['signal_counts']:.0f} "
                "signal counts" if r["detected"] else "not detected")
                      + (f" [{r['flag']}]" if r["flag"] else ""), highlight=False)
        first = df.filter(pl.col("return_index") == 0)
        err.print(f"{int(first['detected'].sum())} of {first.height} channels detected "
                  f"({estimator}) in {time.perf_counter() - t0:.2f} s; wrote {out}")
