"""PicoQuant PTU files (TTTR T2/T3): header, streaming reads, decode, histogram, a writer.

A PTU file is the magic ``PQTTTR\\0\\0``, an 8-byte version string, a list of tags and the
records (little-endian uint32, :mod:`stages.instruments.ptu` decodes them). Each tag is a
32-byte NUL-padded name, an int32 index (-1 when the tag is not indexed), a uint32 type and
an 8-byte value; strings, wide strings, float arrays and blobs put their length in bytes in
the value and their data right after. The tag ``Header_End`` closes the header and the
records start right after it.

Records are read in chunks into one reused buffer, so a file of any size is decoded or
histogrammed in bounded memory. A file shorter than its header says (or whose data does
not end on a whole record) is read up to its last whole record and flagged
(``PtuHeader.truncated``); with ``strict=True`` it is an error instead. Every problem is a
one-line :class:`PtuError` that names the file.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import io
import os
import struct
import sys
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pyarrow as pa

from pipeline.io.atomic import atomic_path
from pipeline.io.buffers import aligned_empty
from schemas.errors import TcspcError
from schemas.instruments import PTU_MAGIC, PTU_T2_EVENTS, PTU_T3_EVENTS
from stages.instruments.accumulate import column
from stages.instruments.ptu import (
    SYNC_CHANNEL,
    Decoded,
    RecordFormat,
    Tally,
    decode_records,
    histogram_records,
    record_format,
    resolution_ps_fraction,
    to_picoseconds,
)

MAGIC = PTU_MAGIC
#: A T2 file's timetag unit is its TDC's bin (1-80 ps in PicoQuant's instruments): a
#: larger one is a corrupt header, and its times in ps would overflow int64.
T2_MAX_RESOLUTION_S = 1e-6
#: Records per read: 16 MiB, bounded memory and large enough to amortise per-call overhead.
CHUNK_RECORDS = 1 << 22

TY_EMPTY8 = 0xFFFF0008
TY_BOOL8 = 0x00000008
TY_INT8 = 0x10000008
TY_BITSET64 = 0x11000008
TY_COLOR8 = 0x12000008
TY_FLOAT8 = 0x20000008
TY_TDATETIME = 0x21000008
TY_FLOAT8ARRAY = 0x2001FFFF
TY_ANSISTRING = 0x4001FFFF
TY_WIDESTRING = 0x4002FFFF
TY_BINARYBLOB = 0xFFFFFFFF
#: tag types whose value is a length in bytes of data that follows the tag
_VARIABLE = {TY_FLOAT8ARRAY, TY_ANSISTRING, TY_WIDESTRING, TY_BINARYBLOB}
_FIXED = {TY_EMPTY8, TY_BOOL8, TY_INT8, TY_BITSET64, TY_COLOR8, TY_FLOAT8, TY_TDATETIME}
#: TDateTime is days since this instant (Delphi's epoch)
_DELPHI_EPOCH = dt.datetime(1899, 12, 30, tzinfo=dt.UTC)
_TAG = struct.Struct("<32siIQ")
#: the most bytes one tag's data may hold, and the most tags a header may hold: PicoQuant's
#: headers are tens of KiB; a length beyond these is refused before it is read (a sparse
#: file of 12 KB on disk may claim a 1 GiB string)
MAX_TAG_BYTES = 1 << 24
MAX_TAGS = 1 << 16


class PtuError(TcspcError, ValueError):
    """A PTU file is unreadable or inconsistent (one line, names the file)."""


@dataclass(frozen=True)
class PtuHeader:
    """What a PTU file's header says, and how much data the file really holds."""

    path: str
    record_type: int
    format: RecordFormat
    version: str
    resolution_s: float
    global_resolution_s: float
    sync_rate_hz: float | None
    n_records: int
    data_offset: int
    file_bytes: int
    tags: dict = field(repr=False, default_factory=dict)

    @property
    def records_in_file(self) -> int:
        """Whole records between the header and the end of the file."""
        return (self.file_bytes - self.data_offset) // 4

    @property
    def n_readable(self) -> int:
        """Records a reader decodes: those declared, or fewer if the file is short."""
        return min(self.n_records, self.records_in_file)

    @property
    def truncated(self) -> bool:
        """The file holds fewer whole records than ``TTResult_NumberOfRecords``."""
        return self.records_in_file < self.n_records

    @property
    def trailing_bytes(self) -> int:
        """Bytes after the declared records (ignored by the readers)."""
        return max(0, self.file_bytes - self.data_offset - 4 * self.n_records)

    @property
    def truncation(self) -> str:
        """A one-line account of a truncated file ('' when it is complete)."""
        if not self.truncated:
            return ""
        data = self.file_bytes - self.data_offset
        part = f" and {data % 4} bytes of a partial record" if data % 4 else ""
        return (f"{self.path}: truncated: the header declares {self.n_records} records, the "
                f"file holds {self.records_in_file}{part}")

    @property
    def warning(self) -> str:
        """What a caller should report about the data section ('' when it is regular): a
        truncation, or bytes after the declared records (which are not read)."""
        if self.truncated:
            return self.truncation
        if self.trailing_bytes:
            return (f"{self.path}: {self.trailing_bytes} bytes after the {self.n_records} "
                    "declared records, not read")
        return ""

    @property
    def n_input_channels(self) -> int:
        """Inputs (detector channels) the header describes, at most what records address.

        The indexed ``HWInpChan_*`` tags name one entry per input; ``HW_InpChannels``
        counts the sync input too on a HydraHarp, so it is the fallback. A PicoHarp T3's
        router addresses 4 channels whatever the header says.
        """
        fmt = self.format
        if fmt.n_channels == 4:
            return 4
        idx = {int(k.rsplit("(", 1)[1][:-1]) for k in self.tags
               if k.startswith("HWInpChan_") and k.endswith(")")}
        n = len(idx) or int(self.tags.get("HW_InpChannels", fmt.n_channels))
        return max(1, min(n, fmt.n_channels))


def _tag_value(typ: int, raw: int, data: bytes, name: str, where: str):
    value8 = raw.to_bytes(8, "little")
    if typ == TY_EMPTY8:
        return None
    if typ == TY_BOOL8:
        return raw != 0
    if typ == TY_INT8:
        return struct.unpack("<q", value8)[0]
    if typ in (TY_BITSET64, TY_COLOR8):
        return raw
    if typ == TY_FLOAT8:
        return struct.unpack("<d", value8)[0]
    if typ == TY_TDATETIME:
        days = struct.unpack("<d", value8)[0]
        try:
            return _DELPHI_EPOCH + dt.timedelta(days=days)
        except (OverflowError, ValueError):
            return days
    if typ == TY_FLOAT8ARRAY:
        if len(data) % 8:
            raise PtuError(f"{where}: tag {name} is a float array of {len(data)} bytes, not "
                           "a multiple of 8")
        return np.frombuffer(data, "<f8").astype(np.float64)
    if typ == TY_ANSISTRING:
        text = data.split(b"\0", 1)[0]
        try:
            return text.decode("utf-8")
        except UnicodeDecodeError:
            return text.decode("latin-1")
    if typ == TY_WIDESTRING:
        return data.decode("utf-16-le", errors="replace").split("\0", 1)[0]
    return bytes(data)  # TY_BINARYBLOB


def read_header(path: str | os.PathLike) -> PtuHeader:
    """Parse and check a PTU file's header.

    Raises
    ------
    PtuError
        The file is missing, not a PTU file (wrong magic), its header is cut short or
        has no ``Header_End``, a tag overruns the file or has an unknown type, the record
        type is unknown, a mandatory tag is missing, or it declares no records.
    """
    where = str(path)
    try:
        size = os.stat(path).st_size
        fh = open(path, "rb")
    except OSError as exc:
        raise PtuError(f"{where}: cannot open: {exc.strerror}") from exc
    with fh:
        head = fh.read(16)
        if head[:8] != MAGIC:
            raise PtuError(f"{where}: not a PTU file: starts with {head[:8]!r}, expected "
                           f"{MAGIC!r}")
        if len(head) < 16:
            raise PtuError(f"{where}: header cut short after {len(head)} bytes (a file of "
                           f"{size} bytes, truncated inside the header)")
        version = head[8:].split(b"\0", 1)[0].decode("ascii", "replace")
        tags: dict = {}
        offset = 16
        while True:
            raw = fh.read(_TAG.size)
            if len(raw) < _TAG.size:
                raise PtuError(f"{where}: header has no Header_End tag: the file ends at "
                               f"byte {size} inside the header (truncated, or not a "
                               "complete PTU file)")
            ident, idx, typ, value = _TAG.unpack(raw)
            # (printable, escaped: a corrupt name must not split the one-line error)
            name = ident.split(b"\0", 1)[0].decode("ascii", "backslashreplace")
            name = "".join(c if c.isprintable() else f"\\x{ord(c):02x}" for c in name)
            key = f"{name}({idx})" if idx >= 0 else name
            data = b""
            if len(tags) >= MAX_TAGS:
                raise PtuError(f"{where}: more than {MAX_TAGS} tags before Header_End "
                               "(corrupt header?)")
            if typ in _VARIABLE:
                start = offset + _TAG.size
                if value > size - start:
                    raise PtuError(f"{where}: tag {key} at byte {offset} declares {value} "
                                   f"bytes of data, past the end of the file ({size} bytes)")
                if value > MAX_TAG_BYTES:
                    raise PtuError(f"{where}: tag {key} at byte {offset} declares {value} "
                                   f"bytes of data, more than a tag may hold ({MAX_TAG_BYTES})")
                data = fh.read(value)
                offset = start + value
            elif typ in _FIXED:
                offset += _TAG.size
            else:
                raise PtuError(f"{where}: tag {key} at byte {offset} has unknown type "
                               f"0x{typ:08X} (corrupt header?)")
            tags[key] = _tag_value(typ, value, data, key, where)
            if name == "Header_End":
                break
    return _header_from_tags(where, tags, version, offset, size)


def _header_from_tags(where: str, tags: dict, version: str, data_offset: int,
                      size: int) -> PtuHeader:
    def need(name):
        if name not in tags:
            raise PtuError(f"{where}: header has no {name} tag (mandatory in PTU files)")
        return tags[name]

    code = need("TTResultFormat_TTTRRecType")
    if not isinstance(code, int) or isinstance(code, bool):
        raise PtuError(f"{where}: TTResultFormat_TTTRRecType must be an integer, found "
                       f"{code!r}")
    try:
        fmt = record_format(code)
    except ValueError as exc:
        raise PtuError(f"{where}: {exc}") from None
    bits = tags.get("TTResultFormat_BitsPerRecord", 32)
    if bits != 32:
        raise PtuError(f"{where}: {fmt.name} records of {bits} bits; this reader knows "
                       "32-bit records")
    n_records = need("TTResult_NumberOfRecords")
    if not isinstance(n_records, int) or n_records <= 0:
        raise PtuError(f"{where}: holds no records (TTResult_NumberOfRecords = {n_records})")
    global_res = need("MeasDesc_GlobalResolution")
    resolution = tags.get("MeasDesc_Resolution") if fmt.is_t3 else \
        tags.get("MeasDesc_Resolution", global_res)
    if fmt.is_t3 and resolution is None:
        need("MeasDesc_Resolution")
    for name, v in (("MeasDesc_GlobalResolution", global_res),
                    ("MeasDesc_Resolution", resolution)):
        if not isinstance(v, float | int) or not v > 0 or not np.isfinite(v):
            raise PtuError(f"{where}: {name} must be a positive number of seconds, found "
                           f"{v!r}")
    if not fmt.is_t3:
        if global_res > T2_MAX_RESOLUTION_S:  # a T2 unit is a TDC's bin: ps, not seconds
            raise PtuError(f"{where}: MeasDesc_GlobalResolution {global_res!r} s is no T2 "
                           f"time unit (at most {T2_MAX_RESOLUTION_S} s; a corrupt header?)")
        try:  # T2 times are written in whole ps: the timetag unit must be exact
            resolution_ps_fraction(global_res)
        except ValueError as exc:
            raise PtuError(f"{where}: MeasDesc_GlobalResolution: {exc}") from None
    sync = tags.get("TTResult_SyncRate")
    if not isinstance(sync, int | float) or isinstance(sync, bool):
        sync = None  # informational only: a missing or odd value is not an error
    return PtuHeader(where, int(code), fmt, version, float(resolution), float(global_res),
                     float(sync) if sync is not None else None, int(n_records), data_offset,
                     size, tags)


def iter_chunks(path: str | os.PathLike, chunk_records: int = CHUNK_RECORDS,
                header: PtuHeader | None = None,
                strict: bool = False) -> Iterator[tuple[int, np.ndarray]]:
    """Yield ``(first_record, words)`` over the file's records, in order.

    ``words`` is native uint32 and a view of one reused buffer: use it before asking for
    the next chunk, or copy it. A truncated file yields its whole records
    (``header.truncated`` tells; a trailing partial record is not read); with
    ``strict=True`` it raises :class:`PtuError` instead, before yielding anything.
    """
    header = header if header is not None else read_header(path)
    if strict and header.truncated:
        raise PtuError(header.truncation)
    if chunk_records < 1:
        raise ValueError(f"chunk_records must be >= 1, found {chunk_records}")
    n = header.n_readable
    buf = aligned_empty(min(chunk_records, max(n, 1)), "<u4")  # 4x faster reads
    with open(path, "rb", buffering=0) as fh:
        for first in range(0, n, chunk_records):
            yield first, read_records(fh, header, first, buf[:min(chunk_records, n - first)])


def read_records(fh, header: PtuHeader, first: int, out: np.ndarray) -> np.ndarray:
    """Records ``first .. first + out.size`` of the file open as ``fh`` (binary), read into
    ``out`` (``<u4``; page-aligned reads are 4x faster, ``pipeline.io.buffers``); returned
    as native uint32. Each thread of a parallel read passes its own ``fh`` and ``out``.

    Raises :class:`PtuError` when the file holds fewer bytes than asked for (it shrank
    after its header was read).
    """
    fh.seek(header.data_offset + 4 * first)
    view, got = memoryview(out).cast("B"), 0
    while got < out.nbytes:  # (a read may return less than asked, 0 at the end)
        k = fh.readinto(view[got:])
        if not k:
            raise PtuError(f"{header.path}: file shrank while reading (record {first}: "
                           f"got {got} of {out.nbytes} bytes)")
        got += k
    return out if sys.byteorder == "little" else out.astype(np.uint32)


def histogram_t3(path: str | os.PathLike, chunk_records: int = CHUNK_RECORDS,
                 n_channels: int | None = None, n_bins: int | None = None,
                 engine: str | None = None, strict: bool = False
                 ) -> tuple[np.ndarray, PtuHeader, Tally, bool]:
    """Micro-time histogram of a T3 file, streamed in bounded memory.

    Parameters
    ----------
    n_channels : int, optional
        Rows of the histogram. By default every channel the records can address is
        counted and the result keeps ``max(header.n_input_channels, last channel seen +
        1)`` rows, so no photon is out of range.
    n_bins : int, optional
        Columns (dtime codes); by default every code of the format (4096 or 32768). A
        photon beyond either bound is counted in ``tally.n_out_of_range``.

    Returns
    -------
    counts : ndarray of uint64, shape (n_channels, n_bins)
    header : PtuHeader
    tally : Tally
        Records by class; ``tally.n_records`` is the records read.
    truncated : bool
        The file held fewer records than its header declares (only with ``strict=False``).
    """
    header = read_header(path)
    fmt = header.format
    if not fmt.is_t3:
        raise PtuError(f"{header.path}: {fmt.name} is T2 data: there is no dtime to "
                       "histogram (decode it instead)")
    auto = n_channels is None
    counts = np.zeros((fmt.n_channels if auto else n_channels,
                       n_bins or fmt.n_dtime_codes), np.uint64)
    tally = Tally()
    for _, words in iter_chunks(path, chunk_records, header, strict):
        tally = tally.then(histogram_records(words, fmt, counts, tally.wraps, engine))
    if auto:
        seen = np.flatnonzero(counts.any(axis=1))
        rows = max(header.n_input_channels, int(seen[-1]) + 1 if seen.size else 0)
        if rows < counts.shape[0]:
            counts = counts[:rows].copy()
    return counts, header, tally, header.truncated


@dataclass
class DecodeReport:
    """Counters of a decode, filled while :func:`iter_decoded_batches` runs."""

    n_records_read: int = 0
    n_photons: int = 0
    n_sync: int = 0
    n_markers: int = 0
    n_overflow_records: int = 0
    n_invalid: int = 0
    wraps: int = 0
    truncated: bool = False
    header: PtuHeader | None = field(default=None, repr=False)

    def add(self, d: Decoded) -> None:
        self.n_records_read += d.n_records
        self.n_photons += d.n_photons
        self.n_sync += d.n_sync
        self.n_markers += d.n_markers
        self.n_overflow_records += d.n_overflow_records
        self.n_invalid += d.n_invalid
        self.wraps = d.wraps

    def metadata(self) -> dict[bytes, bytes]:
        """The counters as Arrow schema metadata (``ptu.*`` keys)."""
        h = self.header
        out = {"record_type": f"0x{h.record_type:08X}" if h else "",
               "format": h.format.name if h else "",
               "records_declared": h.n_records if h else "",
               "resolution_s": repr(h.resolution_s) if h else "",
               "global_resolution_s": repr(h.global_resolution_s) if h else "",
               "records_read": self.n_records_read, "photons": self.n_photons,
               "sync": self.n_sync, "markers": self.n_markers,
               "overflow_records": self.n_overflow_records, "invalid": self.n_invalid,
               "wraps": self.wraps, "truncated": str(self.truncated).lower()}
        return {f"ptu.{k}".encode(): str(v).encode() for k, v in out.items()}


def iter_decoded_batches(path: str | os.PathLike, chunk_records: int = CHUNK_RECORDS,
                         report: DecodeReport | None = None, engine: str | None = None,
                         strict: bool = False, header: PtuHeader | None = None
                         ) -> Iterator[pa.RecordBatch]:
    """Decode a PTU file chunk by chunk into Arrow record batches.

    Batches follow ``PTU_T2_EVENTS`` (``time_ps`` = overflow-corrected timetag x
    ``MeasDesc_GlobalResolution``, exact in integer ps) or ``PTU_T3_EVENTS``. Chunks
    without an event yield no batch. ``report``, when given, is filled as decoding goes
    (its ``truncated`` is set before the first batch). ``header``: the file's, read here
    unless given.
    """
    header = header if header is not None else read_header(path)
    fmt = header.format
    report = report if report is not None else DecodeReport()
    report.header, report.truncated = header, header.truncated
    schema = (PTU_T3_EVENTS if fmt.is_t3 else PTU_T2_EVENTS).schema
    wraps = 0
    for _, words in iter_chunks(path, chunk_records, header, strict):
        d = decode_records(words, fmt, wraps, engine)
        wraps = d.wraps
        report.add(d)
        if not len(d):
            continue
        if fmt.is_t3:
            cols = [d.kind, d.channel, d.time, d.dtime]
        else:
            cols = [d.kind, d.channel, to_picoseconds(d.time, header.global_resolution_s)]
        yield pa.RecordBatch.from_arrays(
            [column(c, f.type) for c, f in zip(cols, schema, strict=True)], schema=schema)


def decode(path: str | os.PathLike, chunk_records: int = CHUNK_RECORDS,
           engine: str | None = None, strict: bool = False) -> pa.Table:
    """Every event of a PTU file as one Arrow table (``PTU_T2_EVENTS`` / ``PTU_T3_EVENTS``).

    The schema metadata carries the counters (``ptu.records_read``, ``ptu.photons``,
    ``ptu.sync``, ``ptu.markers``, ``ptu.overflow_records``, ``ptu.invalid``,
    ``ptu.truncated``, ...). Holds every event in memory: stream large files with
    :func:`iter_decoded_batches`.
    """
    report = DecodeReport()
    batches = list(iter_decoded_batches(path, chunk_records, report, engine, strict))
    spec = PTU_T3_EVENTS if report.header.format.is_t3 else PTU_T2_EVENTS
    table = pa.Table.from_batches(batches, schema=spec.schema)
    return table.replace_schema_metadata({**spec.schema.metadata, **report.metadata()})


# --- writer -------------------------------------------------------------------------------

def _tag_bytes(key: str, value) -> bytes:
    name, idx = key, -1
    if key.endswith(")") and "(" in key:
        name, i = key[:-1].rsplit("(", 1)
        idx = int(i)
    ident = name.encode("ascii")
    if len(ident) > 31:
        raise ValueError(f"tag name {name!r} is longer than 31 characters")
    data = b""
    if value is None:
        typ, raw = TY_EMPTY8, b"\0" * 8
    elif isinstance(value, bool | np.bool_):
        typ, raw = TY_BOOL8, struct.pack("<q", -1 if value else 0)
    elif isinstance(value, int | np.integer):
        typ, raw = TY_INT8, struct.pack("<q", int(value))
    elif isinstance(value, float | np.floating):
        typ, raw = TY_FLOAT8, struct.pack("<d", float(value))
    elif isinstance(value, dt.datetime):
        days = (value - _DELPHI_EPOCH) / dt.timedelta(days=1)
        typ, raw = TY_TDATETIME, struct.pack("<d", days)
    elif isinstance(value, str):
        text = value.encode("utf-8") + b"\0"
        data = text + b"\0" * (-len(text) % 8)  # PicoQuant pads strings to 8 bytes
        typ, raw = TY_ANSISTRING, struct.pack("<q", len(data))
    elif isinstance(value, bytes | bytearray):
        data = bytes(value)
        typ, raw = TY_BINARYBLOB, struct.pack("<q", len(data))
    elif isinstance(value, np.ndarray):
        data = np.asarray(value, "<f8").tobytes()
        typ, raw = TY_FLOAT8ARRAY, struct.pack("<q", len(data))
    else:
        raise TypeError(f"tag {key}: no PTU tag type for {type(value).__name__}")
    return ident.ljust(32, b"\0") + struct.pack("<iI", idx, typ) + raw + data


def write_ptu(path: str | os.PathLike, record_type_code: int,
              words: np.ndarray | Iterable[np.ndarray], tags: dict | None = None, *,
              resolution_s: float | None = None, global_resolution_s: float | None = None,
              sync_rate_hz: float | None = None, n_records: int | None = None,
              version: str = "1.0.00") -> Path:
    """Write a minimal valid PTU file (for tests and benchmarks), atomically.

    Parameters
    ----------
    record_type_code : int
        A known record type (:data:`stages.instruments.ptu.FORMATS`).
    words : ndarray of uint32, or an iterable of them
        The records, in order; an iterable is streamed to disk chunk by chunk.
    tags : dict, optional
        Extra tags, ``{"Name": value}`` or ``{"Name(idx)": value}``; the type follows the
        Python type (None, bool, int, float, datetime, str, bytes, float ndarray). They
        replace the default tags of the same name, which is how a test writes an
        inconsistent file (another record type, another record count).
    resolution_s, global_resolution_s, sync_rate_hz : float, optional
        Default: 4 ps (PicoHarp) or 1 ps resolution; T3 sync at 10 MHz and the global
        resolution its period; T2 global resolution = resolution.
    n_records : int, optional
        ``TTResult_NumberOfRecords``; by default the number of records written.

    Examples
    --------
    >>> import tempfile
    >>> p = write_ptu(tempfile.mkdtemp() + "/x.ptu", 0x00010303,
    ...               np.array([(1 << 28) | 5], np.uint32))
    >>> h = read_header(p)
    >>> h.format.name, h.n_records, h.resolution_s, h.sync_rate_hz
    ('PicoHarpT3', 1, 4e-12, 10000000.0)
    """
    fmt = record_format(record_type_code)
    res = resolution_s or (4e-12 if fmt.n_channels == 4 else 1e-12)
    sync = sync_rate_hz or (1e7 if fmt.is_t3 else None)
    glob = global_resolution_s or (1.0 / sync if fmt.is_t3 else res)
    defaults = {
        "File_Comment": "written by tcspc-lidar pipeline.io.ptu.write_ptu",
        "Measurement_Mode": 3 if fmt.is_t3 else 2,
        "Measurement_SubMode": 0,
        "TTResultFormat_TTTRRecType": fmt.code,
        "TTResultFormat_BitsPerRecord": 32,
        "MeasDesc_Resolution": float(res),
        "MeasDesc_GlobalResolution": float(glob),
        "TTResult_NumberOfRecords": 0,  # patched below when not given
    }
    if sync is not None:
        defaults["TTResult_SyncRate"] = int(round(sync))
    all_tags = {**defaults, **(tags or {})}
    chunks = [words] if isinstance(words, np.ndarray) else words
    declared = n_records if n_records is not None else all_tags.get("TTResult_NumberOfRecords")
    patch = "TTResult_NumberOfRecords" not in (tags or {}) and n_records is None
    header = bytearray(MAGIC + version.encode("ascii")[:8].ljust(8, b"\0"))
    count_at = None
    for key, value in {**all_tags, "Header_End": None}.items():
        if key == "TTResult_NumberOfRecords":
            count_at = len(header) + 40
            value = int(declared)
        header += _tag_bytes(key, value)
    with atomic_path(path) as tmp:
        written = 0
        with open(tmp, "wb") as fh:
            fh.write(header)
            for chunk in chunks:
                chunk = np.asarray(chunk)
                if chunk.dtype != np.uint32:
                    raise TypeError(f"records must be uint32, found {chunk.dtype}")
                chunk.astype("<u4", copy=False).tofile(fh)
                written += chunk.size
            if patch and count_at is not None:
                fh.seek(count_at)
                fh.write(struct.pack("<q", written))
    return Path(path)


# --- Photon-HDF5 --------------------------------------------------------------------------

def export_photon_hdf5(path_ptu: str | os.PathLike, out_h5: str | os.PathLike,
                       engine: str | None = None, strict: bool = True) -> dict:
    """Write a PTU file's photons as Photon-HDF5 (needs ``phconvert``, which needs PyTables).

    Decoding is this module's (exact, every record counted); phconvert only writes and
    validates the file (``measurement_type = "generic"``). ``timestamps`` are the
    overflow-corrected nsync (T3) or timetag (T2) in units of
    ``MeasDesc_GlobalResolution``, ``detectors`` the 0-based input, ``nanotimes`` the
    dtime (T3). Markers and T2 sync events are not photons and are not written; their
    counts are in the file's ``description``. Photon-HDF5 is written from whole arrays:
    memory grows with the file (about 11 bytes per photon), unlike the other readers here.

    Returns the counters of the decode (records read, photons, markers, ...) and
    phconvert's warnings about optional fields left out (``"warnings"``).
    """
    try:
        import phconvert
    except ImportError as exc:  # an optional dependency: say how to get it
        raise ModuleNotFoundError("export_photon_hdf5 needs phconvert (pip install "
                                  "phconvert; it brings PyTables)") from exc
    report = DecodeReport()
    table = pa.Table.from_batches(
        list(iter_decoded_batches(path_ptu, report=report, engine=engine, strict=strict)),
        schema=(PTU_T3_EVENTS if read_header(path_ptu).format.is_t3
                else PTU_T2_EVENTS).schema)
    h = report.header
    fmt = h.format
    kind = table.column("kind").to_numpy()
    channel = table.column("channel").to_numpy()
    photon = (kind == 0) & (channel != SYNC_CHANNEL)
    if fmt.is_t3:
        timestamps = table.column("nsync").to_numpy()[photon].astype(np.int64)
    else:  # back to timetags: time_ps is timetag x the resolution, exactly
        frac = resolution_ps_fraction(h.global_resolution_s)
        if frac.denominator != 1:
            raise PtuError(f"{h.path}: a T2 resolution of {float(frac)} ps is not a whole "
                           "number of ps: export from the timetags is not implemented")
        timestamps = table.column("time_ps").to_numpy()[photon] // frac.numerator
    photon_data = {
        "timestamps": timestamps,
        "detectors": channel[photon],
        "timestamps_specs": {"timestamps_unit": h.global_resolution_s},
        "measurement_specs": {"measurement_type": "generic", "detectors_specs": {
            "spectral_ch1": np.unique(channel[photon]).astype(np.int64)}},
    }
    if fmt.is_t3:
        photon_data["nanotimes"] = table.column("dtime").to_numpy()[photon]
        photon_data["nanotimes_specs"] = {
            "tcspc_unit": h.resolution_s, "tcspc_num_bins": fmt.n_dtime_codes,
            "tcspc_range": h.resolution_s * fmt.n_dtime_codes}
    n_pixels = max(int(channel[photon].max()) + 1 if photon.any() else 1,
                   h.n_input_channels)
    data = {
        "description": (f"PicoQuant {fmt.name} ({h.path}): {report.n_photons} photons; not "
                        f"written: {report.n_markers} markers, {report.n_sync} sync events, "
                        f"{report.n_overflow_records} overflow records, {report.n_invalid} "
                        f"invalid records; truncated: {report.truncated}"),
        "photon_data": photon_data,
        "setup": {"num_pixels": n_pixels, "num_spots": 1, "num_spectral_ch": 1,
                  "num_polarization_ch": 1, "num_split_ch": 1,
                  "modulated_excitation": False, "lifetime": fmt.is_t3,
                  "excitation_alternated": [False],
                  # the sync is the laser's clock: pulsed at the sync rate when known
                  "excitation_cw": [not h.sync_rate_hz]},
        "provenance": {"filename": str(path_ptu), "software": "tcspc-lidar"},
    }
    if h.sync_rate_hz:
        data["setup"]["laser_repetition_rates"] = [h.sync_rate_hz]
        photon_data["measurement_specs"]["laser_repetition_rate"] = h.sync_rate_hz
    final = Path(out_h5).resolve()
    with atomic_path(out_h5) as tmp, warnings.catch_warnings(record=True) as caught, \
            contextlib.redirect_stdout(io.StringIO()):  # phconvert prints "Saving: ..."
        warnings.simplefilter("always")
        phconvert.hdf5.save_photon_hdf5(data, h5_fname=str(tmp), overwrite=True,
                                        close=True)
        import tables  # phconvert's dependency: name the file where it will live

        with tables.open_file(str(tmp), "r+") as h5:
            for name, value in (("filename", final.name), ("filename_full", str(final))):
                node = h5.get_node("/identity", name)
                title = node.title
                node._f_remove()
                h5.create_array("/identity", name, obj=value.encode(), title=title)
    counters = {k: v for k, v in vars(report).items() if k != "header"}
    # phconvert's notes on optional fields left out (wavelengths, author)
    return {**counters, "warnings": [str(w.message) for w in caught]}
