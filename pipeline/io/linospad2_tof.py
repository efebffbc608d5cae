"""A LinoSPAD2 capture's photons as time-of-flight histograms: a generic histograms parquet
(docs/instruments_generic.md) with ``row`` and ``col``, for ``tcspc range`` and
``tcspc range --spatial --geometry linospad2``.

A LinoSPAD2 word holds a photon's time since its acquisition cycle's start (28 bits of
17.857 ps, :mod:`stages.instruments.linospad2`), not since a laser pulse: with a laser
fired by the board's 400 MHz clock every ``--period-ps`` (a multiple of 2.5 ns), the
times folded on that period are times of flight. Each pixel (``tdc`` = the pixel 0..255
of the firmware's map, ``row`` 0, ``col`` the pixel) gets ``--bins`` bins of
``period / bins``. The fine code's time is the carry chain's nominal 17.857 ps a code unless
``--code-times`` gives the board's code-density table (daplis' ``TDC_*.csv``, read by
:func:`pipeline.io.linospad2.read_published_calibration`): without it a period that is a
whole number of clock periods puts the chain's dead and wide codes at the same place in
every fold, a comb of empty and full bins shared by the 4 pixels of a TDC
(docs/instruments_linospad2.md "Times of flight"). ``cycles`` is null (a line's
buffer may fill before its window ends, so the laser pulses a pixel saw are not known):
no pile-up correction.

Usage: ``python -m pipeline.io.linospad2_tof CAPTURE.dat --period-ps 80000 --bins 1024
[--code-times TDC.csv] --out H.parquet``
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.io.atomic import atomic_path
from pipeline.io.linospad2 import (
    Linospad2Error,
    iter_cycles,
    looks_like_linospad2,
    read_published_calibration,
)
from stages.instruments import linospad2 as lino


def tof_counts(path, period_ps: float, bins: int, table_ps=None, firmware: str = "2212b",
               words_per_line: int = lino.WORDS_PER_LINE) -> tuple[np.ndarray, lino.Tally]:
    """(256, bins) int64 counts of the capture's photons folded on ``period_ps``, a row per
    pixel, and the file's tally; in chunks of whole cycles (bounded memory)."""
    if not (np.isfinite(period_ps) and period_ps > 0):
        raise Linospad2Error(f"{path}: --period-ps must be > 0, found {period_ps:g}")
    if bins < 3:
        raise Linospad2Error(f"{path}: --bins must be >= 3, found {bins}")
    counts = np.zeros((lino.N_PIXEL, bins), np.int64)
    tally = lino.Tally()
    for d in iter_cycles(path, firmware, words_per_line=words_per_line):
        t = lino.photon_times_ps(d.code, d.pixel, table_ps)
        counts += lino.folded_histograms(d.pixel, t, lino.N_PIXEL, period_ps, bins)
        tally = tally + d.tally
    return counts, tally


def tof_table(counts: np.ndarray, period_ps: float, measurement: str) -> pa.Table:
    """The generic histograms table of :func:`tof_counts`' counts."""
    n, bins = counts.shape
    return pa.table({
        "measurement": pa.array([measurement] * n, pa.string()),
        "tdc": pa.array(np.arange(n), pa.uint32()),
        "counts": pa.array(counts.tolist(), pa.list_(pa.uint64())),
        "cycles": pa.nulls(n, pa.uint64()),
        "instrument": pa.array(["generic"] * n, pa.string()),
        "bin_width_ps": pa.array(np.full(n, period_ps / bins), pa.float64()),
        "row": pa.array(np.zeros(n, np.uint16), pa.uint16()),
        "col": pa.array(np.arange(n, dtype=np.uint16), pa.uint16()),
    })


def convert(path, out, period_ps: float, bins: int, code_times=None,
            firmware: str = "2212b", measurement: str | None = None) -> tuple[int, lino.Tally]:
    """Write the parquet (atomically); returns (photons, tally)."""
    if not looks_like_linospad2(path):
        raise Linospad2Error(f"{path}: not a LinoSPAD2 capture (firmware 2212b/2212s, "
                             f"{lino.WORDS_PER_LINE} words a line: "
                             "docs/instruments_linospad2.md)")
    table_ps = read_published_calibration(code_times) if code_times else None
    counts, tally = tof_counts(path, period_ps, bins, table_ps, firmware)
    with atomic_path(out) as tmp:
        pq.write_table(tof_table(counts, period_ps, measurement or Path(path).stem), tmp)
    return int(counts.sum()), tally


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m pipeline.io.linospad2_tof",
                                description=__doc__.split("\n\n")[0])
    p.add_argument("capture")
    p.add_argument("--period-ps", type=float, required=True,
                   help="the laser's period (a multiple of 2500 ps for a clock-fired laser)")
    p.add_argument("--bins", type=int, default=1024)
    p.add_argument("--code-times", default=None,
                   help="the board's code-density table (daplis' TDC_*.csv)")
    p.add_argument("--firmware", default="2212b", choices=["2212b", "2212s"])
    p.add_argument("--measurement", default=None)
    p.add_argument("--out", required=True, help="histograms parquet to write")
    a = p.parse_args(argv)
    try:
        n, tally = convert(a.capture, a.out, a.period_ps, a.bins, a.code_times, a.firmware,
                           a.measurement)
    except (Linospad2Error, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {a.out}: {n:,} photons of {tally.cycles:,} cycles, 256 pixels x {a.bins} "
          f"bins of {a.period_ps / a.bins:g} ps ("
          + ("fine codes by " + a.code_times if a.code_times else "nominal fine codes")
          + ")", file=sys.stderr)
    if not a.code_times and a.period_ps % lino.CLOCK_PS == 0:
        print(f"warning: {a.capture}: nominal fine codes folded on whole clock periods: the "
              "carry chain's dead and wide codes make a comb in every pixel, shared by a "
              "TDC's 4 (false surfaces with --spatial); give --code-times",
              file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
