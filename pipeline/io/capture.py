"""Raw captures: ``NAME.bin`` (big-endian uint32 words, cycle after cycle) + ``NAME.json``.

Reading streams the file in chunks into one reused buffer, so a capture of any size is
processed in bounded memory. Every problem with a capture is a :class:`CaptureError` that
names the file and what is wrong.
"""

from __future__ import annotations

import json
import math
import os
import sys
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from pipeline.io.buffers import aligned_empty
from pipeline.io.limits import FileTooLarge, read_bounded
from schemas.errors import CaptureError
from stages.codec import MARKER_MASK, MARKER_VALUE, MAX_TDC

FORMAT = "tcspc-raw"
#: the largest sidecar read (a simulated capture's holds its truth: 1.9 MB for the street
#: scene's 40 000 cycles); a bigger one is refused before it is read
MAX_SIDECAR_BYTES = 64 << 20
VERSION = 1
#: Words per read: 4 MiB, well inside the bounded-memory budget and large enough to
#: amortise per-call overhead.
CHUNK_WORDS = 1 << 20


@dataclass(frozen=True)
class CaptureMeta:
    """The sidecar of a capture (docs/design.md "Capture files")."""

    n_tdc: int
    window_ns: float
    t_laser_win_ns: float
    cycles: int
    kind: str | None = None
    note: str | None = None
    truth: dict | None = field(default=None, repr=False)
    format: str = FORMAT
    version: int = VERSION

    def to_dict(self) -> dict:
        d = asdict(replace(self, truth=None))
        d["truth"] = _plain(self.truth)  # (a LazyTruth's arrays read: a dict of values)
        return {k: v for k, v in d.items() if v is not None}

    @classmethod
    def from_dict(cls, d: dict, where: str) -> CaptureMeta:
        if not isinstance(d, dict):
            raise CaptureError(f"{where}: sidecar must be a JSON object, found "
                               f"{type(d).__name__}")
        if d.get("format") != FORMAT:
            raise CaptureError(f"{where}: format is {d.get('format')!r}, expected {FORMAT!r}")
        if d.get("version") != VERSION:
            raise CaptureError(f"{where}: format version {d.get('version')!r} is not "
                               f"readable by this software, which knows version {VERSION}")
        missing = [k for k in ("n_tdc", "window_ns", "t_laser_win_ns", "cycles") if k not in d]
        if missing:
            raise CaptureError(f"{where}: missing keys {missing}")
        n_tdc, cycles = d["n_tdc"], d["cycles"]
        if not isinstance(n_tdc, int) or not 1 <= n_tdc <= MAX_TDC:
            raise CaptureError(f"{where}: n_tdc must be an integer in 1..{MAX_TDC}, "
                               f"found {n_tdc!r}")
        if not isinstance(cycles, int) or cycles < 0:
            raise CaptureError(f"{where}: cycles must be a non-negative integer, "
                               f"found {cycles!r}")
        for k in ("window_ns", "t_laser_win_ns"):
            v = d[k]
            if not isinstance(v, int | float) or not math.isfinite(v) or v <= 0:
                raise CaptureError(f"{where}: {k} must be a positive number, found {v!r}")
        known = {f for f in cls.__dataclass_fields__}
        return cls(**{k: v for k, v in d.items() if k in known})


#: a compressed capture's file suffix (after NAME.bin) and its encoding
COMPRESSED_ENC = {".zst": "zstd", ".nhz": "zstd-nohit"}
COMPRESSED = tuple(f".bin{ext}" for ext in COMPRESSED_ENC)


def capture_paths(path: str | os.PathLike) -> tuple[Path, Path]:
    """``(NAME.bin, NAME.json)`` from any of NAME, NAME.bin, NAME.bin.zst, NAME.bin.nhz or
    NAME.json."""
    p = Path(path)
    if p.name.endswith(COMPRESSED):
        p = p.with_suffix("")
    if p.suffix in (".bin", ".json"):
        p = p.with_suffix("")
    return p.with_name(p.name + ".bin"), p.with_name(p.name + ".json")


def _not_a_capture(given: Path, bin_path: Path) -> str:
    """What was given and what a capture is, when ``bin_path`` is not there."""
    what = "a capture is NAME.bin (raw 32-bit words) with NAME.json beside it"
    if given.is_dir():
        return f"{given}: a directory, not a capture; {what}"
    if given.is_file() and given != bin_path and given.suffix not in (".json", ".zst", ".nhz"):
        return f"{given}: not a capture ({bin_path.name} not found); {what}"
    return f"{given}: capture not found ({bin_path} does not exist); {what}"


class Capture:
    """An open raw capture, validated on open.

    Parameters
    ----------
    path : path
        NAME, NAME.bin or NAME.json.
    strict : bool
        When True (the default), a word count that disagrees with ``cycles * n_tdc`` in
        the sidecar is an error; when False, the file's own length is used.
    allow_truncated : bool
        A file cut short (fewer bytes than the sidecar's cycles take) is read to its last
        whole cycle and :attr:`truncated` says so, where it is otherwise an error (the
        commands flag such an output and exit 3, as for a PTU file cut short).
    """

    #: buffers :meth:`iter_chunks` cycles through: a view it yielded stays valid while
    #: this many less one further chunks are read. One by default (the least memory); a
    #: reader that hands chunks to other threads sets more on its capture.
    chunk_ring = 1
    #: why the file holds fewer words than its sidecar says (None: it holds them all)
    truncated: str | None = None

    def __init__(self, path: str | os.PathLike, strict: bool = True,
                 allow_truncated: bool = False):
        self.bin_path, self.json_path = capture_paths(path)
        # a compressed capture (a journal segment, see pipeline.stream.journal): the same
        # words, read through a streaming decoder (zstd's, or the zstd-nohit frames')
        self.compressed = None
        if not self.bin_path.is_file():
            for ext, enc in COMPRESSED_ENC.items():
                packed = self.bin_path.with_name(self.bin_path.name + ext)
                if packed.is_file():
                    self.bin_path, self.compressed = packed, enc
                    break
        if not self.bin_path.is_file():
            raise CaptureError(_not_a_capture(Path(path), self.bin_path))
        if not self.json_path.is_file():
            raise CaptureError(f"{self.json_path}: sidecar not found (every NAME.bin needs "
                               "a NAME.json beside it)")
        try:
            raw = json.loads(read_bounded(self.json_path, MAX_SIDECAR_BYTES, "sidecar"))
        except FileTooLarge as exc:
            raise CaptureError(str(exc)) from None
        except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as exc:
            raise CaptureError(f"{self.json_path}: sidecar is not valid JSON: "
                               f"{str(exc) or 'nested too deeply'}") from None
        self.meta = CaptureMeta.from_dict(raw, str(self.json_path))
        if self.meta.truth is not None:  # (large arrays beside it, read when asked for)
            self.meta = replace(self.meta,
                                truth=_resolve_truth(self.meta.truth, self.json_path))
        if self.compressed:  # the sidecar's count; a short file fails while read
            self.n_words = self.meta.cycles * self.meta.n_tdc
            self._check_addresses()
            return
        size = self.bin_path.stat().st_size
        expected = self.meta.cycles * self.meta.n_tdc
        if size < 4 * expected and allow_truncated:  # cut short: its whole cycles are read
            n_tdc = self.meta.n_tdc
            self.n_words = size // 4 // n_tdc * n_tdc
            self.truncated = (f"{self.bin_path} is cut short: {size:,} bytes where the "
                              f"sidecar's {self.meta.cycles:,} cycles take {4 * expected:,}")
            self._check_addresses()
            return
        if size % 4:
            raise CaptureError(f"{self.bin_path}: size {size} bytes is not a multiple of 4 "
                               f"(a truncated word at the end?)")
        self.n_words = size // 4
        if self.n_words != expected and strict:
            raise CaptureError(
                f"{self.bin_path}: holds {self.n_words} words, but the sidecar says "
                f"{self.meta.cycles} cycles x {self.meta.n_tdc} TDCs = {expected}")
        self._check_addresses()

    @property
    def name(self) -> str:
        return self.bin_path.name.split(".", 1)[0]

    def _open(self):
        if self.compressed == "zstd-nohit":
            from pipeline.io.nohit import FrameReader

            return FrameReader(self.bin_path, self.meta.n_tdc)
        if self.compressed:
            import pyarrow as pa

            return pa.input_stream(str(self.bin_path), compression="zstd")
        return open(self.bin_path, "rb")

    def _check_addresses(self) -> None:
        """Refuse a sidecar ``n_tdc`` that the words' address fields contradict."""
        n_tdc = self.meta.n_tdc
        head = self.read_words(0, min(self.n_words, 64 * n_tdc))
        ok = (head & MARKER_MASK) == MARKER_VALUE
        if ok.sum() < n_tdc:
            return  # too few well-formed words to judge; they are counted as malformed
        addr = ((head >> 1) & 0xFF)[ok]
        pos = (np.arange(head.size) % n_tdc)[ok]
        if np.mean(addr != pos) > 0.2:  # a healthy capture has a few malformed words at most
            guess = int(addr.max()) + 1
            raise CaptureError(
                f"{self.bin_path}: n_tdc={n_tdc} in the sidecar does not match the words' "
                f"addresses ({np.mean(addr != pos):.0%} of the first {head.size} words sit "
                f"at the wrong position; the addresses run 0..{guess - 1}, suggesting "
                f"n_tdc={guess})")

    def read_words(self, first: int, count: int) -> np.ndarray:
        """``count`` native uint32 words starting at word ``first`` (a fresh array)."""
        count = max(0, min(count, self.n_words - first))
        out = aligned_empty(count)
        with self._open() as fh:
            if self.compressed:  # a stream: read up to ``first``
                for _ in range(0, 4 * first, 1 << 24):
                    fh.read(min(1 << 24, 4 * first - _))
            else:
                fh.seek(4 * first)
            self._readinto(fh, out)
        return out

    def _readinto(self, fh, out: np.ndarray, native: bool = True) -> None:
        try:
            n = fh.readinto(memoryview(out).cast("B"))
        except Exception as exc:  # a corrupt zstd frame (pyarrow's error types)
            if not self.compressed:
                raise
            raise CaptureError(f"{self.bin_path}: corrupt compressed capture: {exc}") from exc
        if n != out.nbytes:
            raise CaptureError(f"{self.bin_path}: file shrank while reading, or holds fewer "
                               f"words than its sidecar says (got {n} of {out.nbytes} bytes)")
        if native and sys.byteorder == "little":  # from big-endian in place: 2.4x byteswap()
            np.copyto(out, out.view(">u4"))

    def iter_chunks(self, chunk_words: int = CHUNK_WORDS, native: bool = True
                    ) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(first_word, words)`` over the whole capture in arrival order.

        ``words`` is a view of one of :attr:`chunk_ring` reused buffers (native uint32):
        it stays valid until ``chunk_ring - 1`` more chunks have been asked for (with one
        buffer: use it before asking for the next), then it is overwritten; copy it to
        keep it. Chunks are whole cycles where the file allows. ``native=False``: the
        words as the file holds them (big-endian ``>u4``, not swapped: what a journal
        writes as it is).
        """
        n_tdc = self.meta.n_tdc
        chunk_words = max(n_tdc, chunk_words // n_tdc * n_tdc)
        ring = [aligned_empty(min(chunk_words, self.n_words))  # (pipeline.io.buffers: 4x)
                for _ in range(min(max(1, self.chunk_ring), -(-self.n_words // chunk_words)))]
        with self._open() as fh:
            for i, first in enumerate(range(0, self.n_words, chunk_words)):
                n = min(chunk_words, self.n_words - first)
                view = ring[i % len(ring)][:n]
                self._readinto(fh, view, native)
                yield first, view if native else view.view(">u4")


class CaptureWriter:
    """Write a capture: words stream into ``NAME.bin``, the sidecar is written on close.

    Both files are written under temporary names and renamed into place on a clean close,
    so a crash leaves no capture that looks complete.

    Examples
    --------
    >>> import tempfile, numpy as np
    >>> from stages.codec import encode_words
    >>> d = tempfile.mkdtemp()
    >>> with CaptureWriter(d + "/x", n_tdc=2, window_ns=80.0, t_laser_win_ns=140.0) as w:
    ...     w.write(encode_words(0, 0, 0, 0, [0, 1, 0, 1]))
    >>> Capture(d + "/x.bin").meta.cycles
    2
    """

    def __init__(self, path: str | os.PathLike, n_tdc: int, window_ns: float = 80.0,
                 t_laser_win_ns: float = 140.0, kind: str | None = None,
                 note: str | None = None, truth: dict | None = None):
        self.bin_path, self.json_path = capture_paths(path)
        self.bin_path.parent.mkdir(parents=True, exist_ok=True)
        self._tmp_bin = self.bin_path.with_name(f".{self.bin_path.name}.tmp-{os.getpid()}")
        self._meta = dict(n_tdc=n_tdc, window_ns=float(window_ns),
                          t_laser_win_ns=float(t_laser_win_ns), kind=kind, note=note,
                          truth=truth)
        CaptureMeta.from_dict({**self._meta, "cycles": 0, "format": FORMAT,
                               "version": VERSION}, str(self.json_path))
        self._fh = open(self._tmp_bin, "wb")
        self.n_words = 0

    def write(self, words: np.ndarray) -> None:
        """Append native uint32 words (written big-endian)."""
        words = np.asarray(words)
        if words.dtype != np.uint32:
            raise TypeError(f"{self.bin_path}: words must be uint32, found {words.dtype}")
        self._fh.write(words.astype(">u4", copy=False).tobytes())
        self.n_words += words.size

    def set_truth(self, truth: dict) -> None:
        self._meta["truth"] = truth

    def close(self) -> CaptureMeta:
        n_tdc = self._meta["n_tdc"]
        if self.n_words % n_tdc:
            self.abort()
            raise CaptureError(f"{self.bin_path}: {self.n_words} words is not a whole "
                               f"number of cycles of {n_tdc} TDCs")
        self._fh.flush()
        os.fsync(self._fh.fileno())
        self._fh.close()
        meta = CaptureMeta.from_dict({**self._meta, "cycles": self.n_words // n_tdc,
                                      "format": FORMAT, "version": VERSION},
                                     str(self.json_path))
        doc = meta.to_dict()
        table_path = truth_table_path(self.json_path)
        tables: dict = {}
        if "truth" in doc:
            doc["truth"], tables = _split_truth(doc["truth"], table_path.name)
        tmp_json = self.json_path.with_name(f".{self.json_path.name}.tmp-{os.getpid()}")
        tmp_json.write_text(json.dumps(doc, separators=(",", ":"), default=_jsonable))
        if tables:  # (written before the sidecar that names it)
            tmp_table = table_path.with_name(f".{table_path.name}.tmp-{os.getpid()}")
            _write_truth_table(tables, tmp_table)
            os.replace(tmp_table, table_path)
        else:  # (a capture written over one that had a table: not its truth)
            table_path.unlink(missing_ok=True)
        os.replace(self._tmp_bin, self.bin_path)
        os.replace(tmp_json, self.json_path)
        return meta

    def abort(self) -> None:
        self._fh.close()
        self._tmp_bin.unlink(missing_ok=True)

    def __enter__(self) -> CaptureWriter:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


def _jsonable(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, LazyTruth):
        return dict(o.items())
    if isinstance(o, np.generic):
        return o.item()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


# --- the simulator's truth: small values in the sidecar, tables beside it -----------------
#
# A simulated capture's truth holds the chip's INL tables (2 x 128 x 512 numbers): 1.25 MB
# of the 1.9 MB an indented sidecar took. Arrays of TRUTH_TABLE_MIN numbers or more go to
# NAME.truth.parquet, a row each (``key``: the path in the truth, ``shape``, ``dtype``
# (numpy's: integers come back as integers), ``values`` flattened as float64), and the
# sidecar, written compact, names them:
# ``{"$truth_table": "NAME.truth.parquet", "key": "chip/inl_lsb"}``. A reader resolves a
# reference when the value is first asked for (a command that does not read the truth
# never opens the table), and a sidecar with every array inline (written before) reads
# as it did.

#: arrays of at least this many numbers are kept in NAME.truth.parquet
TRUTH_TABLE_MIN = 4096
_REF = "$truth_table"


def truth_table_path(json_path: str | os.PathLike) -> Path:
    """NAME.truth.parquet beside NAME.json."""
    p = Path(json_path)
    return p.with_name(p.name[:-len(".json")] + ".truth.parquet")


def _split_truth(node, table_name: str, key: str = "", tables: dict | None = None):
    """(the truth with its large arrays replaced by references, {key: array})."""
    tables = {} if tables is None else tables
    if isinstance(node, dict):
        return {k: _split_truth(v, table_name, f"{key}/{k}" if key else str(k), tables)[0]
                for k, v in node.items()}, tables
    if isinstance(node, np.ndarray | list | tuple) and not isinstance(node, str):
        try:
            arr = np.asarray(node)
            if arr.dtype.kind not in "biuf":
                raise TypeError(arr.dtype)
        except (TypeError, ValueError):  # (None among numbers, dicts: kept as it is)
            return node, tables
        if arr.size >= TRUTH_TABLE_MIN:
            tables[key] = arr
            return {_REF: table_name, "key": key}, tables
    return node, tables


def _write_truth_table(tables: dict, path: Path) -> None:
    import pyarrow as pa
    import pyarrow.parquet as pq

    keys = sorted(tables)
    table = pa.table({"key": pa.array(keys, pa.string()),
                      "shape": pa.array([list(tables[k].shape) for k in keys],
                                        pa.list_(pa.int64())),
                      "dtype": pa.array([tables[k].dtype.str for k in keys], pa.string()),
                      "values": pa.array([tables[k].astype(np.float64).ravel() for k in keys],
                                         pa.list_(pa.float64()))})
    pq.write_table(table, path)


class _TruthTables:
    """The arrays of one NAME.truth.parquet, read on first use."""

    def __init__(self, path: Path) -> None:
        self.path, self._arrays = path, None

    def get(self, key: str) -> np.ndarray:
        if self._arrays is None:
            import pyarrow.parquet as pq

            if not self.path.is_file():
                raise CaptureError(f"{self.path}: not found; the sidecar's truth names it "
                                   "(a simulated capture is NAME.bin, NAME.json and "
                                   "NAME.truth.parquet)")
            t = pq.read_table(self.path).to_pydict()
            self._arrays = {k: np.asarray(v, np.float64).reshape(shape).astype(dtype)
                            for k, shape, dtype, v in zip(t["key"], t["shape"], t["dtype"],
                                                          t["values"], strict=True)}
        if key not in self._arrays:
            raise CaptureError(f"{self.path}: holds no truth {key!r}")
        return self._arrays[key]


class LazyTruth(dict):
    """A truth (section) whose large arrays are read from NAME.truth.parquet when asked for:
    a plain dict to its readers (``truth["chip"]["inl_lsb"]``, ``.get``, ``.items``)."""

    def __init__(self, node: dict, tables: _TruthTables) -> None:
        super().__init__({k: LazyTruth(v, tables) if isinstance(v, dict) and _REF not in v
                          else v for k, v in node.items()})
        self._tables = tables

    def __getitem__(self, k):
        v = super().__getitem__(k)
        if isinstance(v, dict) and _REF in v:
            v = self._tables.get(v["key"]).tolist()
            super().__setitem__(k, v)
        return v

    def get(self, k, default=None):
        return self[k] if k in self else default

    def items(self):
        return [(k, self[k]) for k in self]

    def values(self):
        return [self[k] for k in self]

    def __reduce__(self):  # (pickled, e.g. by a Prefect task: as the plain dict it is)
        return dict, (dict(self.items()),)


def _has_ref(node) -> bool:
    return isinstance(node, dict) and (_REF in node or any(_has_ref(v) for v in node.values()))


def _plain(node):
    """A truth as plain dicts (a LazyTruth's references read), for a new sidecar."""
    if isinstance(node, dict):
        return {k: _plain(v) for k, v in node.items()}
    return node


def _resolve_truth(truth, json_path: Path):
    """The sidecar's truth, its references to NAME.truth.parquet made lazy."""
    if _has_ref(truth):
        return LazyTruth(truth, _TruthTables(truth_table_path(json_path)))
    return truth


def write_capture(path: str | os.PathLike, words: np.ndarray, n_tdc: int,
                  **meta) -> CaptureMeta:
    """Write a whole capture at once (see :class:`CaptureWriter`)."""
    with CaptureWriter(path, n_tdc, **meta) as w:
        w.write(np.asarray(words, np.uint32))
    return Capture(path).meta
