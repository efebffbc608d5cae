"""``histograms`` parquet files: written atomically with provenance, read in any version
this software knows (1.x files are upgraded on read, so old outputs stay usable)."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.io.atomic import atomic_path
from schemas.core import META_NAME, META_VERSION, validate
from schemas.errors import SchemaMismatch, SchemaVersionError
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
    meta = dict(table.schema.metadata or {})
    found = meta.get(META_VERSION, b"").decode() or None
    name = meta.get(META_NAME, HISTOGRAMS.name.encode()).decode()
    if name != HISTOGRAMS.name:
        raise SchemaMismatch(f"{where or 'histograms'}: expected a 'histograms' dataset, "
                             f"found {name!r}")
    if found is None:
        raise SchemaVersionError(f"{where or 'histograms'}: no schema version recorded")
    major = int(found.split(".")[0])
    if major not in HISTOGRAMS_READS:
        raise SchemaVersionError(
            f"{where or 'histograms'}: histograms schema version {found} is not readable by "
            f"this software, which reads majors {list(HISTOGRAMS_READS)}")
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
    path = Path(path)
    files = sorted(path.rglob("*.parquet")) if path.is_dir() else [path]
    if not files:
        raise FileNotFoundError(f"{path}: no histograms parquet files")
    parts = [upgrade_histograms(pq.read_table(f), str(f)) for f in files]
    if len(parts) == 1:
        return parts[0]
    meta = parts[0].schema.metadata
    return pa.concat_tables([p.replace_schema_metadata(meta) for p in parts],
                            promote_options="default")
