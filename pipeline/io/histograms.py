"""``histograms`` parquet files: written atomically with provenance, read in any version
this software knows (1.x files are upgraded on read, so old outputs stay usable)."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.io.atomic import atomic_path
from pipeline.io.versions import read_upgraded, readable
from schemas.core import META_VERSION, validate
from schemas.outputs import HISTOGRAMS, HISTOGRAMS_READS

CHIP = "tcspc-chip"


def write_histogram_table(table: pa.Table, out: str | Path,
                          provenance: dict[str, object] | None = None) -> Path:
    """Write a ``histograms`` table (checked against the schema) atomically; each
    ``provenance`` item lands in the file's metadata as ``tcspc.<key>``."""
    validate(table, HISTOGRAMS)
    meta = dict(table.schema.metadata or {})
    meta.update({f"tcspc.{k}".encode(): str(v).encode() for k, v in (provenance or {}).items()})
    table = table.replace_schema_metadata(meta)
    with atomic_path(out) as tmp:
        pq.write_table(table, tmp)
    return Path(out)


def upgrade_histograms(table: pa.Table, where: str = "") -> pa.Table:
    """A ``histograms`` table of any readable version as version 2.0.

    1.x: ``counts`` was a fixed list of 512 D1st codes and every row the thesis chip's;
    the list becomes variable, ``instrument`` is ``'tcspc-chip'`` and ``bin_width_ps``
    null (the chip's widths come from its calibration).
    """
    meta, found, major = readable(table, HISTOGRAMS, HISTOGRAMS_READS, where)
    if major == 1:
        n = table.num_rows
        counts = table.column("counts").cast(pa.list_(pa.uint64()))
        table = table.set_column(table.schema.get_field_index("counts"), "counts", counts)
        table = table.append_column("instrument", pa.array([CHIP] * n, pa.string()))
        table = table.append_column("bin_width_ps", pa.nulls(n, pa.float64()))
        meta[META_VERSION] = HISTOGRAMS.version.encode()
        meta[b"tcspc.upgraded_from"] = found.encode()
    table = table.select(HISTOGRAMS.names + [c for c in table.column_names
                                             if c not in HISTOGRAMS.names])
    table = table.cast(pa.schema(list(HISTOGRAMS.fields) + [
        table.schema.field(c) for c in table.column_names[len(HISTOGRAMS.names):]]))
    return table.replace_schema_metadata(meta)


def read_histograms(path: str | Path) -> pa.Table:
    """A ``histograms`` parquet file (or a directory of them: a dataset) as a 2.0 table.

    Raises ``SchemaVersionError`` / ``SchemaMismatch`` naming the file for an unknown major
    version or another dataset; FileNotFoundError for a missing path.
    """
    return read_upgraded(path, upgrade_histograms, "histograms")
