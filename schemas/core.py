"""Schema specs: an Arrow schema with a name, a version and units, defined once.

Every writer and reader of a dataset goes through a :class:`SchemaSpec`. The spec stamps its
name and version into the Arrow schema metadata, so a file or IPC stream says what it is; a
reader refuses a major version it does not know (:meth:`SchemaSpec.check_version`).
Validation at the edges is :func:`validate`; inside hot loops compare schema identity only.
"""

from __future__ import annotations

from dataclasses import dataclass

import pyarrow as pa

from schemas.errors import SchemaMismatch, SchemaVersionError

META_NAME = b"tcspc.schema"
META_VERSION = b"tcspc.version"


def field(name: str, type_: pa.DataType, unit: str, description: str,
          nullable: bool = False) -> pa.Field:
    """An Arrow field with its unit and description in the field metadata."""
    return pa.field(name, type_, nullable=nullable,
                    metadata={b"unit": unit.encode(), b"description": description.encode()})


@dataclass(frozen=True)
class SchemaSpec:
    """A named, versioned Arrow schema.

    Parameters
    ----------
    name : str
        Dataset name, e.g. ``"histograms"``.
    version : str
        ``"MAJOR.MINOR"``. Minor versions only add fields; a reader accepts any minor of a
        major it knows.
    fields : tuple of pyarrow.Field
        The columns, each with ``unit`` and ``description`` metadata.
    """

    name: str
    version: str
    fields: tuple[pa.Field, ...]

    @property
    def major(self) -> int:
        return int(self.version.split(".")[0])

    @property
    def schema(self) -> pa.Schema:
        got = self.__dict__.get("_schema")  # built once: every message is checked against it
        if got is None:
            got = pa.schema(list(self.fields), metadata={
                META_NAME: self.name.encode(), META_VERSION: self.version.encode()})
            object.__setattr__(self, "_schema", got)
        return got

    @property
    def names(self) -> list[str]:
        return [f.name for f in self.fields]

    def check_version(self, found: str | bytes | None, where: str = "") -> None:
        """Refuse a different name's data or an unknown major version, naming both."""
        if isinstance(found, bytes):
            found = found.decode()
        if found is None:
            raise SchemaVersionError(
                f"{where or self.name}: no schema version recorded; expected "
                f"{self.name} {self.version}")
        if int(found.split(".")[0]) != self.major:
            raise SchemaVersionError(
                f"{where or self.name}: {self.name} schema version {found} is not readable "
                f"by this software, which knows version {self.version}")

    def check_metadata(self, metadata: dict | None, where: str = "") -> None:
        """Check the name and version stamped in an Arrow schema's metadata."""
        metadata = metadata or {}
        name = metadata.get(META_NAME)
        if name is not None and name.decode() != self.name:
            raise SchemaMismatch(
                f"{where or self.name}: expected a {self.name!r} dataset, found "
                f"{name.decode()!r}")
        self.check_version(metadata.get(META_VERSION), where)

    def doc_table(self) -> str:
        """The schema as a Markdown table (docs are written from the spec, not by hand)."""
        rows = [f"### `{self.name}` (version {self.version})", "",
                "| column | type | unit | description |", "|---|---|---|---|"]
        for f in self.fields:
            md = f.metadata or {}
            rows.append(f"| `{f.name}` | `{f.type}` | {md.get(b'unit', b'').decode()} | "
                        f"{md.get(b'description', b'').decode()} |")
        return "\n".join(rows)


def validate(data: pa.Table | pa.RecordBatch | pa.Schema, spec: SchemaSpec,
             where: str = "", allow_extra: bool = False) -> None:
    """Check that ``data`` has every column of ``spec`` with the right type.

    Raises
    ------
    SchemaMismatch
        Naming the column, the expected type and what was found.

    Examples
    --------
    >>> import pyarrow as pa
    >>> spec = SchemaSpec("demo", "1.0", (field("tdc", pa.uint16(), "", "TDC address"),))
    >>> validate(pa.table({"tdc": pa.array([1], pa.uint16())}), spec)
    >>> validate(pa.table({"tdc": pa.array([1], pa.int64())}), spec)
    Traceback (most recent call last):
    ...
    schemas.errors.SchemaMismatch: demo: column 'tdc' should be uint16, found int64
    """
    schema = data if isinstance(data, pa.Schema) else data.schema
    prefix = where or spec.name
    for f in spec.fields:
        idx = schema.get_field_index(f.name)
        if idx < 0:
            raise SchemaMismatch(
                f"{prefix}: column {f.name!r} ({f.type}) is missing; found columns "
                f"{schema.names}")
        found = schema.field(idx)
        if not found.type.equals(f.type):
            raise SchemaMismatch(
                f"{prefix}: column {f.name!r} should be {f.type}, found {found.type}")
    if not allow_extra:
        extra = [n for n in schema.names if n not in spec.names]
        if extra:
            raise SchemaMismatch(f"{prefix}: unexpected columns {extra}; {spec.name} "
                                 f"{spec.version} has {spec.names}")
