"""Messages between stages: ``[header_json, arrow_ipc_stream]`` (docs/streaming.md)."""

from __future__ import annotations

import datetime as dt
import hmac
import json
import os
import re

import pyarrow as pa

from schemas.core import SchemaSpec, validate
from schemas.errors import Rejected, SchemaMismatch, SchemaVersionError

MAX_MESSAGE_BYTES = 64 << 20
REQUIRED = ("kind", "schema", "version", "run", "seq", "step")


class WireError(Rejected):
    """A message that cannot be taken."""


# --------------------------------------------------------------- header schemas
# Every value that may become part of a path is held to a strict pattern: a run id or a
# step id of 1..64 of [A-Za-z0-9._-] (not "." or ".."), a date YYYY-MM-DD that is a date.
ID_PATTERN = re.compile(r"(?!\.{1,2}$)[A-Za-z0-9._-]{1,64}")
DATE_PATTERN = re.compile(r"\d{4}-\d{2}-\d{2}")


def run_id_from(name: str, suffix: str = "") -> str:
    """A run id made from a file's name (a capture "my street.bin" gives "my_street"): each
    run of characters outside [A-Za-z0-9._-] becomes one "_", and the name is cut so that
    the id with ``suffix`` holds at most 64 characters. Every default run id is made here,
    so a name the daemon derives is one it accepts (an id given explicitly is checked
    against :data:`ID_PATTERN`, never changed)."""
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", name).strip("._") or "run"
    return stem[:64 - len(suffix)] + suffix
MAX_INDEX = 1 << 62  # word and measurement indices: far beyond any run, far below int64


def _int(lo=0, hi=MAX_INDEX):
    return {"type": "int", "min": lo, "max": hi}


_NUM_POS = {"type": "number", "min": 1e-3, "max": 1e9}
_COMMON = {
    "kind": {"type": "str", "enum": ("data", "stop"), "required": True},
    "schema": {"type": "str", "pattern": ID_PATTERN, "required": True},
    "version": {"type": ("str", "int", "number"), "required": True},
    "run": {"type": "str", "pattern": ID_PATTERN, "required": True},
    "seq": {"type": "int", "min": 0, "max": MAX_INDEX, "required": True},
    "step": {"type": "str", "pattern": ID_PATTERN, "required": True},
    "token": {"type": "str"},
    "date": {"type": "str", "pattern": DATE_PATTERN, "date": True},
    "window_ns": _NUM_POS,
    "t_laser_win_ns": _NUM_POS,
    "tdc_range": {"type": "list", "items": "int", "len": 2, "min": 0, "max": 65_536},
}
#: The declared header of each message kind (by kind and payload schema): the keys a
#: receiver needs, their types and bounds. A header that breaks its schema is rejected
#: (reason ``bad_header``), counted and quarantined before any stage code sees it.
HEADER_SCHEMAS: dict[tuple[str, str | None], dict] = {
    ("stop", None): {**_COMMON, "words": _int()},
    ("data", "raw_words"): {
        **_COMMON,
        "first_word": {**_int(), "required": True},
        "n_tdc": {**_int(1, 65_536), "required": True},
        "n_tdc_total": _int(1, 65_536),
        "t_laser_win_ns": {**_NUM_POS, "required": True}},
    ("data", "raw_sparse"): {
        **_COMMON,
        "first_word": {**_int(), "required": True},
        "n_words": {**_int(0, MAX_MESSAGE_BYTES), "required": True},
        "n_tdc": {**_int(1, 65_536), "required": True},
        "n_tdc_total": _int(1, 65_536),
        "t_laser_win_ns": {**_NUM_POS, "required": True}},
    ("data", "histograms"): {
        **_COMMON,
        "t_laser_win_ns": {**_NUM_POS, "required": True},
        "measurement": {"type": "str", "pattern": re.compile(r"[A-Za-z0-9._-]{1,96}")},
        "measurement_index": _int(),
        "partial": {"type": "bool"},
        "cycles": {"type": "list", "items": "int", "len": 2, "min": 0, "max": MAX_INDEX},
        "words": _int(),
        "class_counts": {"type": "dict"},
        "n_tdc_total": _int(1, 65_536)},
}
HEADER_SCHEMAS[("data", "ranges")] = {**HEADER_SCHEMAS[("data", "histograms")],
                                      "detected": _int(),
                                      # a spatial frame's missing TDC ranges
                                      "spatial_missing": {"type": "list", "items": "list"}}

_TYPES = {"str": (str,), "int": (int,), "number": (int, float), "bool": (bool,),
          "list": (list,), "dict": (dict,)}


def _is(value, name: str) -> bool:
    if name in ("int", "number") and isinstance(value, bool):
        return False  # JSON true is not a count
    return isinstance(value, _TYPES[name])


def check_header(header: dict, schema: dict) -> None:
    """Check ``header`` against a declared header ``schema``; raise WireError naming the key.

    A schema maps each key to ``{type, required, enum, pattern, min, max, items, len,
    date}``; keys it does not declare pass (a newer sender may add some)."""
    for key, rule in schema.items():
        if key not in header:
            if rule.get("required"):
                raise WireError("bad_header", f"header lacks {key!r}")
            continue
        value = header[key]
        types = rule["type"] if isinstance(rule["type"], tuple) else (rule["type"],)
        if not any(_is(value, t) for t in types):
            raise WireError("bad_header", f"header {key!r} = {value!r:.80} is not {types}")
        if "enum" in rule and value not in rule["enum"]:
            raise WireError("bad_header", f"header {key!r} = {value!r:.80} not in "
                            f"{rule['enum']}")
        if "pattern" in rule and not rule["pattern"].fullmatch(value):
            raise WireError("bad_header", f"header {key!r} = {value!r:.80} does not match "
                            f"{rule['pattern'].pattern}")
        if rule.get("date"):
            try:
                dt.date.fromisoformat(value)
            except ValueError:
                raise WireError("bad_header", f"header {key!r} = {value!r} is not a date"
                                ) from None
        items = [value] if types[0] in ("int", "number") else (
            value if types[0] == "list" else [])
        if types[0] == "list":
            if "len" in rule and len(value) != rule["len"]:
                raise WireError("bad_header", f"header {key!r} has {len(value)} items, "
                                f"expected {rule['len']}")
            if not all(_is(v, rule["items"]) for v in value):
                raise WireError("bad_header", f"header {key!r} items are not {rule['items']}")
        for v in items:
            if not rule.get("min", v) <= v <= rule.get("max", v):
                raise WireError("bad_header", f"header {key!r} = {v!r} outside "
                                f"[{rule.get('min')}, {rule.get('max')}]")


def header_schema(header: dict) -> dict:
    """The declared schema of ``header``'s kind (a kind or payload schema with none is
    rejected: a receiver takes nothing it cannot check)."""
    kind = header.get("kind")
    key = (kind, None) if kind == "stop" else (kind, header.get("schema"))
    if key not in HEADER_SCHEMAS:
        raise WireError("bad_header", f"no header schema for kind {kind!r}, schema "
                        f"{header.get('schema')!r:.80}")
    return HEADER_SCHEMAS[key]


# --------------------------------------------------------------- run tokens
TOKEN_ENV = "TCSPC_TOKEN_FILE"


def load_token(path: str | os.PathLike | None = None) -> str | None:
    """The run's token: from ``path``, else the file named by $TCSPC_TOKEN_FILE (the
    daemon writes it, mode 0600, in its state directory; never on a command line)."""
    path = path or os.environ.get(TOKEN_ENV)
    if not path:
        return None
    return open(path).read().strip() or None


def check_token(header: dict, token: str | None) -> None:
    """Reject a message whose header does not carry the run's token (when one is set)."""
    if token is None:
        return
    got = header.get("token")
    if not isinstance(got, str) or not hmac.compare_digest(got.encode(), token.encode()):
        raise WireError("bad_token", f"message {header.get('seq')!r:.20} claiming step "
                        f"{header.get('step')!r:.40} lacks the run's token")


def encode(header: dict, batch: pa.RecordBatch | None, token: str | None = None
           ) -> list[bytes | pa.Buffer]:
    """Frames of one message (the Arrow payload as a buffer, sent without copying);
    ``token``: the run's token, added to the header."""
    if token is not None:
        header = {**header, "token": token}
    head = json.dumps(header, separators=(",", ":")).encode()
    if batch is None:
        return [head, b""]
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, batch.schema) as writer:
        writer.write_batch(batch)
    return [head, sink.getvalue()]


def decode(frames, spec: SchemaSpec | dict[str, SchemaSpec] | None = None,
           max_bytes: int = MAX_MESSAGE_BYTES, token: str | None = None
           ) -> tuple[dict, pa.RecordBatch | None]:
    """Header and batch of a message, checked; a bad message raises WireError.

    ``spec``: the schema expected, or a mapping of the schemas a stage takes by name (a
    sink), the header naming which. The header is checked against its declared schema
    (:data:`HEADER_SCHEMAS`) and, with ``token``, for the run's token."""
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
    check_token(header, token)
    check_header(header, header_schema(header))
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
