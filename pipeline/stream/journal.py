"""The journal: raw words on disk before they are passed on, readable while written.

Segments are captures (the words cycle after cycle) with an index of appended chunks
(``RUN.index.jsonl``), flushed per chunk, so a restarted stage can read back any word
range, including from the segment still being written. A closed segment also gets its
capture sidecar (``RUN-000000.json``).

Each chunk is one frame; its index entry ``{first_word, segment, offset, bytes, words,
enc, check}`` locates it and names its encoding (``enc``), so a word range is read back
frame by frame and one run may hold segments of every encoding:

- ``"zstd-nohit"`` (the default, ``RUN-000000.bin.nhz``): zstd (level -20: NOHIT_LEVEL) on
  the chunk less its no-hit pattern: a bit per word where it differs from its position's
  no-hit word, then those words (pipeline.io.nohit). Lossless for any words; 2.8x the words
  per CPU-second of ``"zstd"`` at 5 % hits and 6.7x at 18 %, in about the same bytes.
- ``"zstd"`` (``RUN-000000.bin.zst``): zstd (level -3: ZSTD_LEVEL) on the big-endian
  words. Concatenated frames are one zstd stream: ``zstd -d`` gives the raw capture of
  docs/design.md byte for byte.
- raw (``compression=None``, ``RUN-000000.bin``; entries without ``enc``, offsets in
  words).

:class:`pipeline.io.capture.Capture` reads a closed segment of any encoding directly, and
``tcspc journal export`` writes it as the raw capture. A reader meeting an ``enc`` it does
not know refuses it by name (JournalEncodingUnknown).

Integrity. Every frame carries zstd's content checksum (XXH64 of its content; index
entries say ``"check": "xxh64"``), so a bit flip or a truncated frame is detected when the
frame is read; a zstd-nohit frame's content is also checked against itself and the index
(word count, first word, the mask's bits against the words that follow); a raw segment's
entries carry the CRC-32 of their bytes (``"crc32"``). A damaged chunk is never yielded as
words: it is reported to ``on_corrupt(first_word, words, reason)`` (default: raise
JournalCorrupt). Frames written before checksums were added (no ``check`` in their entry)
still read: a truncated one is still detected (its length or decoding fails), a flipped
bit in one is not (they are reported as ``unchecked`` by :func:`verify`).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipeline.io import nohit
from pipeline.io.capture import CaptureMeta
from schemas.errors import TcspcError

COMPRESSIONS = ("zstd-nohit", "zstd", None)
DEFAULT_COMPRESSION = "zstd-nohit"
#: each encoding's segment file suffix (after ``.bin``); entries name theirs (``enc``)
SUFFIXES = {None: "", "zstd": ".zst", "zstd-nohit": ".nhz"}
# zstd's fast level -3: 1.3x level 1's words per CPU-second at 5 % and at 18 % hits, for
# 6.6 % against 6.1 % and 23 % against 20 % of the bytes; LZ4 (pyarrow's) is no faster and
# twice the size at 5 % (`python benchmarks/source_path.py --codecs`, docs/performance.md).
# A level is the writer's choice only: the frames, and every reader, are zstd's.
ZSTD_LEVEL = -3
# zstd-nohit's frames hold the bit mask and the words that differ: at 5 % hits zstd's time
# goes to the mask, where level -20 takes 1.3x the words per CPU-second of -3 for 7.6 %
# against 6.8 % of the bytes (the same at 18 %, where the mask is near random); the disk
# has room for the difference, the CPU is the goal's limit.
NOHIT_LEVEL = -20


class JournalEncodingUnknown(TcspcError, ValueError):
    """An index entry whose encoding (``enc``) this reader does not know (a newer writer's)."""

    def __init__(self, enc, first_word: int | None = None):
        at = "" if first_word is None else f" (the chunk at word {first_word})"
        known = ", ".join(repr(e) for e in SUFFIXES if e)
        super().__init__(f"journal encoding {enc!r}{at} is not one this tcspc reads "
                         f"({known} or raw); read it with the tcspc that wrote it")


class JournalCorrupt(TcspcError, ValueError):
    """A journal chunk whose bytes fail their checksum, are cut short or do not decode."""

    def __init__(self, first_word: int, words: int, reason: str):
        super().__init__(f"journal words [{first_word}, {first_word + words}): {reason}")
        self.first_word, self.words, self.reason = first_word, words, reason


DISK_FULL_ERRNOS = frozenset({28, 122, 30, 27})  # ENOSPC, EDQUOT, EROFS, EFBIG


def is_disk_full(exc: BaseException) -> bool:
    """An error a full, over-quota or read-only disk raises (wait and retry, not crash)."""
    return isinstance(exc, OSError) and exc.errno in DISK_FULL_ERRNOS


def _write_all(fd: int, data) -> None:
    view = memoryview(data).cast("B")
    while view.nbytes:
        n = os.write(fd, view)
        view = view[n:]


class JournalLocked(TcspcError, OSError):
    """Another live process is writing this run's journal (one run, one writer)."""


def segment_path(directory: str | Path, run: str, segment: int, enc: str | None,
                 first_word: int | None = None) -> Path:
    """A segment's file: ``RUN-000000.bin`` (raw), ``.bin.zst`` (zstd) or ``.bin.nhz``
    (zstd-nohit); JournalEncodingUnknown for an encoding this reader does not know."""
    if enc not in SUFFIXES:
        raise JournalEncodingUnknown(enc, first_word)
    return Path(directory) / f"{run}-{segment:06d}.bin{SUFFIXES[enc]}"


def segment_files(directory: str | Path, run: str) -> list[Path]:
    """The run's segment files, raw and compressed, in segment order."""
    d = Path(directory)
    return sorted([p for ext in SUFFIXES.values() for p in d.glob(f"{run}-*.bin{ext}")],
                  key=lambda p: p.name.split(".", 1)[0])


def segment_number(path: Path) -> int:
    return int(path.name.split(".", 1)[0].rsplit("-", 1)[1])


class FrameEncoder:
    """One chunk as a journal segment holds it: ``encode(first_word, words)`` gives its
    bytes and its index entry's fields (``enc``, ``bytes``, ``check``; a raw chunk's
    ``crc32``). ``words``: uint32, native or big-endian (as a capture holds them)."""

    def __init__(self, enc: str | None, n_tdc: int):
        if enc not in COMPRESSIONS:
            raise ValueError(f"journal compression must be one of {COMPRESSIONS}, found "
                             f"{enc!r}")
        self.enc, self.n_tdc = enc, n_tdc
        self._codec, self.level = None, None
        if enc is not None:
            import zstandard

            # content checksum: a damaged frame fails to decode instead of giving words
            self.level = NOHIT_LEVEL if enc == "zstd-nohit" else ZSTD_LEVEL
            self._codec = zstandard.ZstdCompressor(level=self.level, write_checksum=True,
                                                   write_content_size=True)
        self._be = np.empty(0, ">u4")
        if enc == "zstd-nohit":
            nohit.warm()  # (a first build compiles its kernel: at start, not at a batch)

    def encode(self, first_word: int, words: np.ndarray, sparse=None
               ) -> tuple[bytes | memoryview, dict]:
        """``sparse``: the words' :class:`stages.datapath.SparseWords` where the caller has
        it (a chip's source): a ``zstd-nohit`` frame is then made from it, the same bytes
        without a second pass over the words."""
        n = words.size
        if self.enc == "zstd-nohit" and sparse is not None and sparse.n == n:
            data = nohit.encode_sparse(sparse.index, sparse.words, n, first_word, self.n_tdc)
        elif self.enc == "zstd-nohit":  # (takes native or big-endian words as they are)
            data = nohit.encode(words, first_word, self.n_tdc)
        elif words.dtype == np.dtype(">u4") and words.flags.c_contiguous:
            data = words  # already as the file holds them
        else:
            if self._be.size < n:
                self._be = np.empty(max(n, 1 << 20), ">u4")
            np.copyto(self._be[:n], words, casting="unsafe")  # one byte-swap, reused buffer
            data = self._be[:n]
        if self._codec is not None:  # one frame per chunk (releases the GIL)
            blob = self._codec.compress(memoryview(data).cast("B"))
            return blob, {"bytes": len(blob), "enc": self.enc, "check": "xxh64"}
        import zlib

        blob = memoryview(data).cast("B")
        return blob, {"crc32": zlib.crc32(blob)}


class JournalWriter:
    def __init__(self, directory: str | Path, run: str, n_tdc: int, t_laser_win_ns: float,
                 window_ns: float = 80.0, segment_words: int = 1 << 26,
                 compression: str | None = DEFAULT_COMPRESSION):
        self.encoder = FrameEncoder(compression, n_tdc)
        self.enc = compression
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self._lock = _lock_run(self.dir, run)  # before anything is written
        self.run, self.n_tdc = run, n_tdc
        self.meta = dict(n_tdc=n_tdc, window_ns=window_ns, t_laser_win_ns=t_laser_win_ns)
        self.segment_words = segment_words
        # a restarted source appends: its words go to a new segment after the last one
        self.segment = max((e["segment"] for e in _entries(self.dir / f"{run}.index.jsonl")
                            if "segment" in e), default=-1)
        self.fh = None
        self.offset = 0
        index = self.dir / f"{run}.index.jsonl"
        # unbuffered: a write a full disk refuses is rolled back, never left in a buffer
        self.index = open(index, "ab", buffering=0)
        if index.read_bytes()[-1:] not in (b"", b"\n"):
            _write_all(self.index.fileno(), b"\n")  # end a line a crash cut short
        _reopen_index(self.index.fileno(), index)  # an earlier stop's end is not the run's
        meta = self.dir / f"{run}.meta.json"
        if not meta.exists():  # the run's constants, for a stage that starts after its end
            from pipeline.io.atomic import atomic_path

            try:
                with atomic_path(meta) as tmp:
                    tmp.write_text(json.dumps({"run": run, **self.meta}))
            except OSError:
                pass  # (derived: the index and the sidecars hold the same)
        self.segments: list[Path] = []

    def _rotate(self) -> None:
        self._close_segment()
        self.segment += 1
        path = segment_path(self.dir, self.run, self.segment, self.enc)
        self.fh = open(path, "ab", buffering=0)
        self.offset = self.fh.tell() if self.enc else 0  # bytes (compressed) or words
        self.words = 0
        self.segments.append(path)

    def append(self, first_word: int, words: np.ndarray, extra: dict | None = None,
               sparse=None) -> None:
        """Journal one chunk: its bytes, then its index line. All or nothing: if the disk
        refuses either (full, read-only), both files are cut back to where they were and
        the OSError is raised, so the caller may wait and append the same chunk again.
        ``extra``: more keys for the chunk's index line (the UDP ingest's datagram
        sequence number, from which a restarted ingest resumes). ``sparse``: the chunk's
        sparse form, where the caller made it (:meth:`FrameEncoder.encode`)."""
        if self.fh is None or self.words + words.size > self.segment_words:
            self._rotate()
        n = words.size
        blob, fields = self.encoder.encode(first_word, words, sparse)
        entry = {"first_word": int(first_word), "segment": self.segment,
                 "offset": self.offset, "words": int(n), **(extra or {}), **fields}
        step = len(blob) if self.enc else n
        # where the files end (not tell(): after a cut-back write the position is past it)
        seg_at, index_at = (os.fstat(f.fileno()).st_size for f in (self.fh, self.index))
        try:
            _write_all(self.fh.fileno(), blob)
            _write_all(self.index.fileno(), (json.dumps(entry) + "\n").encode())
        except OSError:
            for fh, at in ((self.fh, seg_at), (self.index, index_at)):
                try:
                    os.ftruncate(fh.fileno(), at)
                    os.lseek(fh.fileno(), at, os.SEEK_SET)
                except OSError:
                    pass
            raise
        self.offset += step
        self.words += n

    def _close_segment(self) -> None:
        if self.fh is None:
            return
        fh, self.fh = self.fh, None
        try:
            os.fsync(fh.fileno())
        finally:
            fh.close()
        path = self.segments[-1]
        cycles = self.words // self.n_tdc
        meta = CaptureMeta.from_dict({**self.meta, "cycles": cycles, "format": "tcspc-raw",
                                      "version": 1, "kind": "journal"}, str(path))
        side = self.dir / f"{self.run}-{self.segment:06d}.json"
        d = meta.to_dict()
        if self.enc:
            d["compression"] = self.enc
        try:
            side.write_text(json.dumps(d))
        except OSError:  # (derived from the index: a full disk must not stop the journal)
            side.unlink(missing_ok=True)

    def close(self, complete: bool = False) -> None:
        """Close the last segment and record the run's end (its total words);
        ``complete``: the source's stream ended there (its cycles done, the UDP stream's
        last datagram or ``idle``), not a stop (a signal, an error), so a daemon started
        again on the run finishes it from the journal instead of reopening it
        (:func:`stream_ended`)."""
        self._close_segment()
        total = 0
        for e in _entries(self.dir / f"{self.run}.index.jsonl"):
            total = max(total, e.get("first_word", 0) + e.get("words", 0))
        end = {"end": True, "words": total, **({"complete": True} if complete else {})}
        _write_all(self.index.fileno(), (json.dumps(end) + "\n").encode())
        self.index.close()
        self._lock.close()  # (the kernel also drops it when a writer dies)


def _lock_run(directory: Path, run: str):
    """An exclusive lock on ``RUN.lock`` for this writer's life; JournalLocked if another
    process holds it (a second source, or an orphan of a killed daemon still writing)."""
    import fcntl

    fh = open(directory / f"{run}.lock", "a+")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fh.seek(0)
        holder = fh.read().strip() or "?"
        fh.close()
        raise JournalLocked(f"{directory}: run {run!r} is being journaled by another process "
                            f"(pid {holder}); one run has one writer") from None
    fh.seek(0)
    fh.truncate()
    fh.write(f"{os.getpid()}\n")
    fh.flush()
    return fh


def read_range(directory: str | Path, run: str, start: int, stop: int,
               on_corrupt=None) -> Iterator[tuple[int, np.ndarray]]:
    """Journaled words of ``run`` with stream index in [start, stop), as (first, words).

    A chunk that fails its check is never yielded: ``on_corrupt(first_word, words,
    reason)`` is told of it (its whole chunk), or, without one, JournalCorrupt is raised."""
    d = Path(directory)
    index = d / f"{run}.index.jsonl"
    if not index.exists():
        return
    for e in _entries(index):
        if "first_word" not in e:  # (end and reopen lines)
            continue
        lo, hi = e["first_word"], e["first_word"] + e["words"]
        a, b = max(lo, start), min(hi, stop)
        if a >= b:
            continue
        seg = segment_path(d, run, e["segment"], e.get("enc"), e["first_word"])
        if not seg.exists():  # pruned (retention): those words are gone
            continue
        try:
            raw = _read_chunk(seg, e)
        except JournalCorrupt as exc:
            if on_corrupt is None:
                raise
            on_corrupt(exc.first_word, exc.words, exc.reason)
            continue
        raw = memoryview(raw)[4 * (a - lo):4 * (b - lo)]
        yield a, np.frombuffer(raw, ">u4").astype(np.uint32)


def _read_chunk(seg: Path, e: dict):
    """The bytes of one index entry's whole chunk (big-endian words), checked."""
    enc, n = e.get("enc"), e["words"]
    with open(seg, "rb") as fh:
        if enc is None:
            fh.seek(4 * e["offset"])
            raw = fh.read(4 * n)
        else:
            fh.seek(e["offset"])
            frame = fh.read(e["bytes"])
    if enc is None:
        if len(raw) != 4 * n:
            raise JournalCorrupt(e["first_word"], n, f"truncated: {len(raw)} of {4 * n} "
                                 f"bytes in {seg.name}")
        if "crc32" in e:
            import zlib

            if zlib.crc32(raw) != e["crc32"]:
                raise JournalCorrupt(e["first_word"], n, f"CRC-32 mismatch in {seg.name}")
        return raw
    if len(frame) != e["bytes"]:
        raise JournalCorrupt(e["first_word"], n, f"truncated frame: {len(frame)} of "
                             f"{e['bytes']} bytes in {seg.name} at {e['offset']}")
    if enc == "zstd":
        return _decompress(frame, 4 * n, e["first_word"], seg)
    content = _decompress(frame, None, e["first_word"], seg, n)
    try:
        return nohit.decode(content, e["first_word"], n)[1].view(np.uint8)
    except nohit.FrameError as exc:
        raise JournalCorrupt(e["first_word"], n, f"zstd-nohit frame in {seg.name}: "
                             f"{exc}") from None


def _decompress(frame: bytes, size: int | None, first_word: int, seg: Path,
                words: int | None = None) -> bytes:
    """A zstd frame's content, checked: ``size`` bytes exactly (None: a zstd-nohit frame's,
    at most its header, mask and every word)."""
    import zstandard

    words = size // 4 if words is None else words
    limit = size if size is not None else nohit.HEADER.size + -(-words // 8) + 4 * words
    try:  # verifies the frame's content checksum when it has one
        if zstandard.frame_content_size(frame) > limit:  # (a damaged header: no allocation)
            raise zstandard.ZstdError(f"its header says {zstandard.frame_content_size(frame)}"
                                      f" bytes, more than {limit}")
        raw = zstandard.ZstdDecompressor().decompress(frame, max_output_size=limit)
    except (zstandard.ZstdError, MemoryError) as exc:
        raise JournalCorrupt(first_word, words, f"zstd frame in {seg.name} does "
                             f"not decode ({exc})") from None
    if size is not None and len(raw) != size:
        raise JournalCorrupt(first_word, words, f"zstd frame in {seg.name} "
                             f"holds {len(raw)} bytes, the index says {size}")
    return raw


def verify(directory: str | Path, run: str) -> dict:
    """Read every chunk of ``run`` and check it: ``{chunks, words, corrupt: [[first_word,
    words, reason], ...], corrupt_words, unchecked_chunks, pruned_chunks}``."""
    d = Path(directory)
    out = {"chunks": 0, "words": 0, "corrupt": [], "corrupt_words": 0,
           "unchecked_chunks": 0, "pruned_chunks": 0}
    for e in _entries(d / f"{run}.index.jsonl"):
        if "first_word" not in e:  # (end and reopen lines)
            continue
        out["chunks"] += 1
        out["words"] += e["words"]
        seg = segment_path(d, run, e["segment"], e.get("enc"), e["first_word"])
        if not seg.exists():
            out["pruned_chunks"] += 1
            continue
        if "check" not in e and "crc32" not in e:
            out["unchecked_chunks"] += 1
        try:
            _read_chunk(seg, e)
        except JournalCorrupt as exc:
            out["corrupt"].append([exc.first_word, exc.words, exc.reason])
            out["corrupt_words"] += exc.words
    return out


def run_meta(directory: str | Path, run: str) -> dict:
    """The run's constants (``n_tdc``, ``t_laser_win_ns``, ``window_ns``) as its first
    writer recorded them; {} for a journal written before they were."""
    path = Path(directory) / f"{run}.meta.json"
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return {}


def run_end(directory: str | Path, run: str) -> int | None:
    """Total words of ``run`` once its source has closed the journal, else None. Only the
    index's last record counts: an end line followed by a ``reopen`` line or by more
    chunks is an earlier stop's (a graceful stop, then the run resumed), not the run's."""
    index = Path(directory) / f"{run}.index.jsonl"
    if not index.exists():
        return None
    entries = _entries(index)
    if entries and entries[-1].get("end"):
        return int(entries[-1]["words"])
    return None


def stream_ended(directory: str | Path, run: str) -> bool:
    """True when ``run``'s journal ends where its source's stream ended (the end line's
    ``complete``): nothing more will come; a daemon started again finishes the run from
    the journal (a daemon killed during its reconciliation, a finished UDP run)."""
    entries = _entries(Path(directory) / f"{run}.index.jsonl")
    return bool(entries and entries[-1].get("end") and entries[-1].get("complete"))


def _reopen_index(fd: int, index: Path) -> None:
    """After an end line, a ``{"reopen": true}`` line: the run goes on."""
    entries = _entries(index)
    if entries and entries[-1].get("end"):
        _write_all(fd, (json.dumps({"reopen": True}) + "\n").encode())


def reopen(directory: str | Path, run: str) -> bool:
    """Mark ``run`` as going on again (a daemon resuming a run that an earlier stop closed),
    before any stage starts: no worker may take the earlier stop's end line for the run's
    end. Under the run's writer lock; True when there was an end to reopen."""
    d = Path(directory)
    index = d / f"{run}.index.jsonl"
    entries = _entries(index)
    if not (entries and entries[-1].get("end")):
        return False
    lock = _lock_run(d, run)
    try:
        with open(index, "ab", buffering=0) as fh:
            _reopen_index(fh.fileno(), index)
    finally:
        lock.close()
    return True


def journaled_words(directory: str | Path, run: str) -> int:
    """Words of ``run`` already in the journal from its start without a hole (where a
    restarted deterministic source resumes)."""
    index = Path(directory) / f"{run}.index.jsonl"
    if not index.exists():
        return 0
    done = 0
    for e in _entries(index):
        if "first_word" not in e:  # (end and reopen lines)
            continue
        if e["first_word"] <= done:
            done = max(done, e["first_word"] + e["words"])
    return done


def _entries(index: Path) -> list[dict]:
    """The index's records; a line a crash cut short is skipped (its chunk is not in the
    journal: the words were written, their record was not, so they were never passed on)."""
    if not index.exists():
        return []
    out = []
    for line in index.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except ValueError:
            continue
    return out


def journaled_total(directory: str | Path, run: str) -> int:
    """Words of ``run`` in the journal (a gap, such as a lost datagram, is not counted)."""
    return sum(e["words"] for e in _entries(Path(directory) / f"{run}.index.jsonl")
               if "first_word" in e)


def segment_spans(directory: str | Path, run: str) -> dict[int, tuple[int, int]]:
    """Per segment number, the stream span [first, end) of the words it holds."""
    spans: dict[int, tuple[int, int]] = {}
    for e in _entries(Path(directory) / f"{run}.index.jsonl"):
        if "first_word" not in e:  # (end and reopen lines)
            continue
        lo, hi = e["first_word"], e["first_word"] + e["words"]
        a, b = spans.get(e["segment"], (lo, hi))
        spans[e["segment"]] = (min(a, lo), max(b, hi))
    return spans


def prune(directory: str | Path, run: str, keep_bytes: int, consumed_word: int,
          spans: dict[int, tuple[int, int]] | None = None) -> list[Path]:
    """Delete the oldest closed segments of ``run`` while the journal holds more than
    ``keep_bytes``, but only segments every consumer is past (their words all below
    ``consumed_word``). Returns the files deleted. The index stays: it still says which
    words existed, so a later reader knows what was pruned rather than lost."""
    d = Path(directory)
    segs = segment_files(d, run)
    total = sum(p.stat().st_size for p in segs)
    spans = segment_spans(d, run) if spans is None else spans
    gone = []
    for p in segs[:-1]:  # never the segment being written
        if total <= keep_bytes:
            break
        n = segment_number(p)
        if n not in spans or spans[n][1] > consumed_word:
            break
        size = p.stat().st_size
        p.unlink()
        (d / f"{run}-{n:06d}.json").unlink(missing_ok=True)
        total -= size
        gone.append(p)
    return gone


def pruned_words(directory: str | Path, run: str, start: int, stop: int) -> int:
    """Words of [start, stop) the index records but retention has deleted."""
    d = Path(directory)
    n = 0
    for e in _entries(d / f"{run}.index.jsonl"):
        if "first_word" not in e:  # (end and reopen lines)
            continue
        a = max(e["first_word"], start)
        b = min(e["first_word"] + e["words"], stop)
        if a < b and not segment_path(d, run, e["segment"], e.get("enc"),
                                      e["first_word"]).exists():
            n += b - a
    return n


class JournalCapture:
    """A run of a daemon's journal read as a capture (what the calibration code takes):
    ``meta``, ``name``, ``bin_path`` (the run's index), ``paths`` (its segments) and
    ``iter_chunks()``. The journal is readable while it is written; a run still being
    written is read up to where it stands."""

    def __init__(self, directory: str | Path, run: str):
        self.dir, self.name = Path(directory), run
        self.bin_path = self.dir / f"{run}.index.jsonl"
        if not self.bin_path.exists():
            from schemas.errors import CaptureError

            raise CaptureError(f"{self.bin_path}: no run {run!r} in the journal {self.dir}")
        sides = sorted(self.dir.glob(f"{run}-*.json"))
        self.paths = segment_files(self.dir, run)
        first = json.loads(sides[0].read_text()) if sides else {}
        n_tdc = int(first.get("n_tdc", 128))
        self.n_words = journaled_total(self.dir, run)
        self.meta = CaptureMeta.from_dict(
            {"format": "tcspc-raw", "version": 1, "kind": "journal", "n_tdc": n_tdc,
             "window_ns": first.get("window_ns", 80.0),
             "t_laser_win_ns": first.get("t_laser_win_ns", 140.0),
             "cycles": self.n_words // n_tdc}, str(self.bin_path))

    def iter_chunks(self, chunk_words: int = 1 << 20) -> Iterator[tuple[int, np.ndarray]]:
        end = run_end(self.dir, self.name) or self.n_words
        for start in range(0, end, chunk_words):
            yield from read_range(self.dir, self.name, start, min(start + chunk_words, end))


class IndexSpans:
    """The per-segment spans of a run's index (as :func:`segment_spans`), read
    incrementally: a daemon that runs for weeks must not re-read a growing index every
    second (the soak showed the supervisor's memory climbing with it)."""

    def __init__(self, directory: str | Path, run: str):
        self.path = Path(directory) / f"{run}.index.jsonl"
        self.offset = 0
        self.partial = b""
        self.spans: dict[int, tuple[int, int]] = {}
        self.words = 0  #: words journaled (as journaled_total)

    def update(self) -> dict[int, tuple[int, int]]:
        if not self.path.exists():
            return self.spans
        with open(self.path, "rb") as fh:
            fh.seek(self.offset)
            data = fh.read()
        self.offset += len(data)
        lines = (self.partial + data).split(b"\n")
        self.partial = lines.pop()  # a line still being written
        for line in lines:
            try:
                e = json.loads(line)
            except ValueError:
                continue
            if e.get("end") or "segment" not in e:
                continue
            lo, hi = e["first_word"], e["first_word"] + e["words"]
            a, b = self.spans.get(e["segment"], (lo, hi))
            self.spans[e["segment"]] = (min(a, lo), max(b, hi))
            self.words += e["words"]
        return self.spans
