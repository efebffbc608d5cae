"""``ranges`` parquet files read in any version this software knows (1.x files are
upgraded on read, as histograms are)."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa

from pipeline.io.versions import read_upgraded, readable
from schemas.core import META_VERSION
from schemas.outputs import RANGES, RANGES_READS


def upgrade_ranges(table: pa.Table, where: str = "") -> pa.Table:
    """A ``ranges`` table of any readable version as version 2.0.

    1.x: one row a TDC; it becomes its return 0 (``return_index`` 0) with an empty
    ``flag``. Its ``fwhm_m`` stays what it was (the instrument response's FWHM).
    1.x and 2.x: ``tdc`` uint16 is widened to 3.0's uint32.
    """
    meta, found, major = readable(table, RANGES, RANGES_READS, where)
    if major == 1:
        n = table.num_rows
        table = table.append_column("return_index", pa.array([0] * n, pa.uint8()))
        table = table.append_column("flag", pa.array([""] * n, pa.string()))
    if major < RANGES.major:
        meta[META_VERSION] = RANGES.version.encode()
        meta[b"tcspc.upgraded_from"] = found.encode()
    rest = [c for c in table.column_names if c not in RANGES.names]
    table = table.select(RANGES.names + rest)
    table = table.cast(pa.schema(list(RANGES.fields) + [table.schema.field(c) for c in rest]))
    return table.replace_schema_metadata(meta)


def read_ranges(path: str | Path) -> pa.Table:
    """A ``ranges`` parquet file (or a directory of them) as a 2.0 table."""
    return read_upgraded(path, upgrade_ranges, "ranges")
