"""Messages between stages: ``[header_json, arrow_ipc_stream]`` (docs/streaming.md)."""

from __future__ import annotations

import json

import pyarrow as pa

from schemas.core import SchemaSpec, validate
from schemas.errors import Rejected, SchemaMismatch, SchemaVersionError

MAX_MESSAGE_BYTES = 64 << 20
REQUIRED = ("kind", "schema", "version", "run", "seq", "step")


class WireError(Rejected):
    """A message that cannot be taken."""


def encode(header: dict, batch: pa.RecordBatch | None) -> list[bytes | pa.Buffer]:
    """Frames of one message (the Arrow payload as a buffer, sent without copying)."""
    head = json.dumps(header, separators=(",", ":")).encode()
    if batch is None:
        return [head, b""]
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema) as writer:
        writer.write_batch(batch)
    return [head, sink.getvalue()]


def decode(frames, spec: SchemaSpec | dict[str, SchemaSpec] | None = None,
           max_bytes: int = MAX_MESSAGE_BYTES) -> tuple[dict, pa.RecordBatch | None]:
    """Header and batch of a message, checked; a bad message raises WireError.

    ``spec``: the schema expected, or a mapping of the schemas a stage takes by name (a
    sink), the header naming which."""
    if len(frames) != 2:
        raise WireError("bad_frames", f"{len(frames)} frames, expected 2")
    raw_head, payload = (memoryview(f.buffer if hasattr(f, "buffer") else f)
                         for f in frames)
    size = raw_head.nbytes + payload.nbytes
    if size > max_bytes:
        raise WireError("oversized", f"{size} bytes > limit {max_bytes}")
    try:
        header = json.loads(bytes(raw_head))
    except (ValueError, UnicodeDecodeError) as exc:
        raise WireError("bad_header", f"header is not JSON: {exc}") from None
    if not isinstance(header, dict) or any(k not in header for k in REQUIRED):
        raise WireError("bad_header", f"header lacks one of {REQUIRED}")
    if header["kind"] == "stop" and payload.nbytes == 0:
        return header, None
    if isinstance(spec, dict):
        if header["schema"] not in spec:
            raise WireError("schema_mismatch", f"{header['schema']!r}, expected one of "
                                               f"{sorted(spec)}")
        spec = spec[header["schema"]]
    if spec is not None:
        if header["schema"] != spec.name:
            raise WireError("schema_mismatch", f"{header['schema']!r}, expected {spec.name!r}")
        try:
            spec.check_version(str(header["version"]))
        except SchemaVersionError as exc:
            raise WireError("schema_version", str(exc)) from None
    try:
        reader = pa.ipc.open_stream(pa.py_buffer(payload))
        batch = reader.read_next_batch()
    except (pa.ArrowInvalid, pa.ArrowException, StopIteration, OSError) as exc:
        raise WireError("bad_payload", f"Arrow payload unreadable: {exc}") from None
    if spec is not None:
        try:
            validate(batch, spec, f"message {header.get('seq')} from {header.get('step')}")
        except SchemaMismatch as exc:
            raise WireError("schema_mismatch", str(exc)) from None
    return header, batch
