"""What the readers of our datasets share: the schema name and version a file records,
checked against the majors this software reads, and a file or a directory of them read
and upgraded to the current version."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from schemas.core import META_NAME, META_VERSION, SchemaSpec
from schemas.errors import SchemaMismatch, SchemaVersionError


def readable(table: pa.Table, spec: SchemaSpec, reads: tuple[int, ...],
             where: str = "") -> tuple[dict, str, int]:
    """(metadata, recorded version, its major) of a ``spec`` table, refused with the file's
    name when it is another dataset, records no version or a major not in ``reads``."""
    where = where or spec.name
    meta = dict(table.schema.metadata or {})
    found = meta.get(META_VERSION, b"").decode() or None
    name = meta.get(META_NAME, spec.name.encode()).decode()
    if name != spec.name:
        raise SchemaMismatch(f"{where}: expected a '{spec.name}' dataset, found {name!r}")
    if found is None:
        raise SchemaVersionError(f"{where}: no schema version recorded")
    major = int(found.split(".")[0])
    if major not in reads:
        raise SchemaVersionError(
            f"{where}: {spec.name} schema version {found} is not readable by this "
            f"software, which reads majors {list(reads)}")
    return meta, found, major


def read_upgraded(path: str | Path, upgrade: Callable[[pa.Table, str], pa.Table],
                  what: str) -> pa.Table:
    """A parquet file (or a directory of them: a dataset) through ``upgrade``, as one
    table; FileNotFoundError for a missing path or an empty directory."""
    path = Path(path)
    files = sorted(path.rglob("*.parquet")) if path.is_dir() else [path]
    if not files:
        raise FileNotFoundError(f"{path}: no {what} parquet files")
    parts = [upgrade(pq.read_table(f), str(f)) for f in files]
    if len(parts) == 1:
        return parts[0]
    meta = parts[0].schema.metadata
    return pa.concat_tables([p.replace_schema_metadata(meta) for p in parts],
                            promote_options="default")
