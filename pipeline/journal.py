"""The journal: raw words on disk before they are passed on, readable while written.

Segments are raw captures (``RUN-000000.bin``: big-endian words, cycle after cycle) with an
index of appended chunks (``RUN.index.jsonl``: first_word, segment, offset, words), flushed
per chunk, so a restarted stage can read back any word range, including from the segment
still being written. A closed segment also gets its capture sidecar.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from pipeline.capture import CaptureMeta


class JournalWriter:
    def __init__(self, directory: str | Path, run: str, n_tdc: int, t_laser_win_ns: float,
                 window_ns: float = 80.0, segment_words: int = 1 << 26):
        self.dir = Path(directory)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.run, self.n_tdc = run, n_tdc
        self.meta = dict(n_tdc=n_tdc, window_ns=window_ns, t_laser_win_ns=t_laser_win_ns)
        self.segment_words = segment_words
        self.segment = -1
        self.fh = None
        self.offset = 0
        self.index = open(self.dir / f"{run}.index.jsonl", "a")
        self.segments: list[Path] = []

    def _rotate(self) -> None:
        self._close_segment()
        self.segment += 1
        path = self.dir / f"{self.run}-{self.segment:06d}.bin"
        self.fh = open(path, "ab")
        self.offset = 0
        self.segments.append(path)

    def append(self, first_word: int, words: np.ndarray) -> None:
        if self.fh is None or self.offset + words.size > self.segment_words:
            self._rotate()
        self.fh.write(np.asarray(words, np.uint32).astype(">u4").tobytes())
        self.fh.flush()
        self.index.write(json.dumps({"first_word": int(first_word), "segment": self.segment,
                                     "offset": self.offset, "words": int(words.size)}) + "\n")
        self.index.flush()
        self.offset += words.size

    def _close_segment(self) -> None:
        if self.fh is None:
            return
        self.fh.flush()
        os.fsync(self.fh.fileno())
        self.fh.close()
        path = self.segments[-1]
        cycles = self.offset // self.n_tdc
        meta = CaptureMeta.from_dict({**self.meta, "cycles": cycles, "format": "tcspc-raw",
                                      "version": 1, "kind": "journal"}, str(path))
        path.with_suffix(".json").write_text(json.dumps(meta.to_dict()))
        self.fh = None

    def close(self) -> None:
        """Close the last segment and record the run's end (its total words)."""
        self._close_segment()
        total = 0
        for line in (self.dir / f"{self.run}.index.jsonl").read_text().splitlines():
            e = json.loads(line)
            total = max(total, e.get("first_word", 0) + e.get("words", 0))
        self.index.write(json.dumps({"end": True, "words": total}) + "\n")
        self.index.flush()
        self.index.close()


def read_range(directory: str | Path, run: str, start: int, stop: int
               ) -> Iterator[tuple[int, np.ndarray]]:
    """Journaled words of ``run`` with stream index in [start, stop), as (first, words)."""
    d = Path(directory)
    index = d / f"{run}.index.jsonl"
    if not index.exists():
        return
    for line in index.read_text().splitlines():
        e = json.loads(line)
        if e.get("end"):
            continue
        lo, hi = e["first_word"], e["first_word"] + e["words"]
        a, b = max(lo, start), min(hi, stop)
        if a >= b:
            continue
        with open(d / f"{run}-{e['segment']:06d}.bin", "rb") as fh:
            fh.seek(4 * (e["offset"] + a - lo))
            raw = fh.read(4 * (b - a))
        yield a, np.frombuffer(raw, ">u4").astype(np.uint32)


def run_end(directory: str | Path, run: str) -> int | None:
    """Total words of ``run`` once its source has closed the journal, else None."""
    index = Path(directory) / f"{run}.index.jsonl"
    if not index.exists():
        return None
    for line in reversed(index.read_text().splitlines()):
        e = json.loads(line)
        if e.get("end"):
            return int(e["words"])
    return None
