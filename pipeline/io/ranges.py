"""``ranges`` parquet files read in any version this software knows (1.x files are
upgraded on read, as histograms are)."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from schemas.core import META_NAME, META_VERSION
from schemas.errors import SchemaMismatch, SchemaVersionError
from schemas.outputs import RANGES, RANGES_READS


def upgrade_ranges(table: pa.Table, where: str = "") -> pa.Table:
    """A ``ranges`` table of any readable version as version 2.0.

    1.x: one row a TDC; it becomes its return 0 (``return_index`` 0) with an empty
    ``flag``. Its ``fwhm_m`` stays what it was (the instrument response's FWHM).
    """
    meta = dict(table.schema.metadata or {})
    found = meta.get(META_VERSION, b"").decode() or None
    name = meta.get(META_NAME, RANGES.name.encode()).decode()
    if name != RANGES.name:
        raise SchemaMismatch(f"{where or 'ranges'}: expected a 'ranges' dataset, found "
                             f"{name!r}")
    if found is None:
        raise SchemaVersionError(f"{where or 'ranges'}: no schema version recorded")
    major = int(found.split(".")[0])
    if major not in RANGES_READS:
        raise SchemaVersionError(f"{where or 'ranges'}: ranges schema version {found} is not "
                                 f"readable by this software, which reads majors "
                                 f"{list(RANGES_READS)}")
    if major == 1:
        n = table.num_rows
        table = table.append_column("return_index", pa.array([0] * n, pa.uint8()))
        table = table.append_column("flag", pa.array([""] * n, pa.string()))
        meta[META_VERSION] = RANGES.version.encode()
        meta[b"tcspc.upgraded_from"] = found.encode()
    rest = [c for c in table.column_names if c not in RANGES.names]
    table = table.select(RANGES.names + rest)
    table = table.cast(pa.schema(list(RANGES.fields) + [table.schema.field(c) for c in rest]))
    return table.replace_schema_metadata(meta)


def read_ranges(path: str | Path) -> pa.Table:
    """A ``ranges`` parquet file (or a directory of them) as a 2.0 table."""
    path = Path(path)
    files = sorted(path.rglob("*.parquet")) if path.is_dir() else [path]
    if not files:
        raise FileNotFoundError(f"{path}: no ranges parquet files")
    parts = [upgrade_ranges(pq.read_table(f), str(f)) for f in files]
    if len(parts) == 1:
        return parts[0]
    meta = parts[0].schema.metadata
    return pa.concat_tables([p.replace_schema_metadata(meta) for p in parts],
                            promote_options="default")
