"""Histograms from any instrument: a parquet file written by any tool (pyarrow, Polars) with
the columns of ``histograms`` an instrument can fill, and nothing of ours in its metadata.

Columns read (others are ignored): ``measurement`` (string), ``tdc`` (the row: a pixel or
zone), ``counts`` (a list of counts per bin, arrival order, the same length in every row of
a measurement), ``bin_width_ps`` (> 0), ``instrument`` (``"generic"``), ``cycles`` (the
laser pulses each histogram covers; null or absent where the instrument does not report
them: then no pile-up correction), and optionally ``reference`` (true for a reference
channel: an internal zero-distance path, the instrument response and time origin of its
measurement, not ranged).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from schemas.errors import SchemaMismatch

GENERIC = "generic"
REQUIRED = ("measurement", "tdc", "counts", "instrument", "bin_width_ps")


@dataclass(frozen=True)
class Measurement:
    """One measurement's rows: ``counts`` (n_rows, n_bins) float64, ``tdc`` (n_rows,),
    ``cycles`` (n_rows,) NaN where unknown, ``reference`` (n_rows,) bool,
    ``bin_width_s`` (the rows' common nominal width)."""

    name: str
    tdc: np.ndarray
    counts: np.ndarray
    cycles: np.ndarray
    reference: np.ndarray
    bin_width_s: float


def read_generic(path: str | Path, table: pa.Table | None = None,
                 row_numbers: np.ndarray | None = None) -> list[Measurement]:
    """The measurements of a generic histograms file, in file order (or of ``table``, a
    part of it whose rows are the file's ``row_numbers``: the rows an error names).

    Raises ``SchemaMismatch`` (a ValueError), one line naming the file and the row, for a
    missing column, an unknown instrument, a null or ragged counts list, a negative or
    non-finite count, a bin width that is not a positive finite number, or negative cycles.
    """
    def _bad(path, row: int, what: str) -> SchemaMismatch:
        return SchemaMismatch(f"{path}: row "
                              f"{row if row_numbers is None else int(row_numbers[row])}: {what}")

    if table is None:
        check_size(path)
        table = pq.read_table(path)
    missing = [c for c in REQUIRED if c not in table.column_names]
    if missing:
        raise SchemaMismatch(f"{path}: generic histograms need the columns {list(REQUIRED)}"
                             f"; missing {missing}")
    inst = table.column("instrument").to_pylist()
    for i, v in enumerate(inst):
        if v != GENERIC:
            raise _bad(path, i, f"instrument {v!r} is not 'generic' (a tcspc-chip or "
                       "picoquant-t3 file is read by its own path)")
    names = table.column("measurement").to_pylist()
    tdc = table.column("tdc").to_pylist()
    width = table.column("bin_width_ps").cast(pa.float64()).to_pylist()
    cycles = (table.column("cycles").cast(pa.float64()).to_pylist()
              if "cycles" in table.column_names else [None] * table.num_rows)
    ref = (table.column("reference").fill_null(False).to_pylist()
           if "reference" in table.column_names else [False] * table.num_rows)
    counts_col = table.column("counts")
    lengths = pc.list_value_length(counts_col).to_pylist()
    rows: dict[str, list[int]] = {}
    for i in range(table.num_rows):
        if names[i] is None or tdc[i] is None:
            raise _bad(path, i, "measurement and tdc must not be null")
        if not 0 <= tdc[i] <= MAX_TDC:  # (the ranges' tdc column is uint32)
            raise _bad(path, i, f"tdc must be 0..{MAX_TDC}, found {tdc[i]}")
        if lengths[i] is None or lengths[i] < 3:
            raise _bad(path, i, f"counts must be a list of >= 3 bins, found "
                       f"{'null' if lengths[i] is None else lengths[i]}")
        w = width[i]
        if w is None or not np.isfinite(w) or w <= 0:
            raise _bad(path, i, f"bin_width_ps must be a positive finite number, found {w}")
        if cycles[i] is not None and (not np.isfinite(cycles[i]) or cycles[i] < 0):
            raise _bad(path, i, f"cycles must be >= 0 or null, found {cycles[i]}")
        rows.setdefault(names[i], []).append(i)
    flat = counts_col.combine_chunks().flatten() if table.num_rows else pa.array([], pa.float64())
    values = np.asarray(flat.cast(pa.float64()).fill_null(np.nan).to_numpy(
        zero_copy_only=False), np.float64)
    starts = np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64)
    out = []
    for name, idx in rows.items():
        n = lengths[idx[0]]
        for i in idx:
            if lengths[i] != n:
                raise _bad(path, i, f"counts has {lengths[i]} bins where measurement "
                           f"{name!r}'s first row has {n} (ragged histograms)")
            if abs(width[i] / width[idx[0]] - 1) > 1e-9:
                raise _bad(path, i, f"bin_width_ps {width[i]} differs from {width[idx[0]]} "
                           f"in measurement {name!r}")
        c = np.stack([values[starts[i]:starts[i + 1]] for i in idx])
        bad = ~np.isfinite(c) | (c < 0)
        if bad.any():
            r = idx[int(np.argmax(bad.any(axis=1)))]
            raise _bad(path, r, "counts must be finite and >= 0")
        cyc = np.array([np.nan if cycles[i] is None else cycles[i] for i in idx])
        over = np.isfinite(cyc) & (cyc < c.sum(axis=1))
        if over.any():
            r = idx[int(np.argmax(over))]
            raise _bad(path, r, f"cycles {cycles[r]:.0f} is fewer than the row's "
                       f"{c[idx.index(r)].sum():.0f} counts")
        out.append(Measurement(name, np.array([tdc[i] for i in idx], np.int64), c, cyc,
                               np.array([bool(ref[i]) for i in idx]), width[idx[0]] * 1e-12))
    if not out:
        raise SchemaMismatch(f"{path}: no rows")
    return out


#: the largest row number (``tdc``) the ranges can carry (their column is uint32 since
#: ranges 3.0; it was uint16)
MAX_TDC = 2 ** 32 - 1
#: bytes of memory that ranging takes per count value (measured on 10^5 x 4 096 bins:
#: 14-23 GB, 34-56 bytes a value, issue 34.7), with room
BYTES_PER_VALUE = 64


def check_size(path: str | Path, available: int | None = None) -> None:
    """Refuse, in one line and before reading, a file whose counts would not fit in memory
    once ranged (a 147 KB parquet of 10^4 rows x 10^5 bins reached 3.4 GB and died in
    Arrow; 10^5 x 4 096 took the machine's memory): the values from the parquet's own
    metadata, against the memory available (``available`` bytes; default the system's)."""
    import os

    md = pq.ParquetFile(path).metadata
    names = [md.schema.column(j).path for j in range(md.num_columns)]
    cols = [j for j, n in enumerate(names) if n.split(".")[0] == "counts"]
    values = sum(md.row_group(g).column(j).num_values for g in range(md.num_row_groups)
                 for j in cols)
    if available is None:
        try:
            available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):  # (no sysconf: not checked)
            return
    need = values * BYTES_PER_VALUE
    if need > available:
        raise SchemaMismatch(
            f"{path}: {md.num_rows:,} rows holding {values:,} count values need ~"
            f"{need / 2 ** 30:.1f} GiB to range, {available / 2 ** 30:.1f} GiB available: "
            "split the file by measurement (each part is ranged alone)")


def is_generic(path: str | Path) -> bool:
    """Whether a parquet file is to be read as generic histograms: its rows say
    ``instrument = 'generic'`` (read cheaply: one column of the first row group), or it
    is not one of ours (no schema name in its metadata: :func:`read_generic` then says
    which columns it lacks)."""
    from schemas.core import META_NAME

    f = pq.ParquetFile(path)
    if META_NAME not in (f.schema_arrow.metadata or {}):
        return True
    if "instrument" not in f.schema_arrow.names or f.metadata.num_row_groups == 0:
        return False
    col = f.read_row_group(0, columns=["instrument"]).column(0)
    return col.length() > 0 and col[0].as_py() == GENERIC
