"""LinoSPAD2 raw captures (``.dat``) and the board's published TDC calibration (``.csv``).

A capture is little-endian uint32 words, cycle after cycle, each cycle 65 lines x
``words_per_line`` words (the format: :mod:`stages.instruments.linospad2`). There is no
header, so a file is recognised by its content (:func:`looks_like_linospad2`). Files are
read in chunks of whole cycles (bounded memory); bytes after the last whole cycle are not
decoded but counted (``Tally.truncated_bytes``), never an error.

The published calibration (daplis' ``TDC_<daughterboard>_<motherboard>_<firmware>.csv``) is a
pandas CSV: a header row ``,0,1,...,139``, then one row per pixel 0..255, its index first,
then 140 cumulative code times in ps (``cumsum(counts) / total x 2500``: code k's upper
edge, see ``stages.instruments.linospad2.CodeDensity``).
"""

from __future__ import annotations

import csv
import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pyarrow as pa

from schemas.core import validate
from schemas.errors import TcspcError
from schemas.instruments import LINOSPAD2_EVENTS
from stages.instruments import linospad2 as lino

#: cycles per read: 256 x 65 x 200 words = 13 MB at the sample's line length
CHUNK_CYCLES = 256
#: cycles :func:`looks_like_linospad2` inspects
SNIFF_CYCLES = 4
_LE_U32 = np.dtype("<u4")


class Linospad2Error(TcspcError, ValueError):
    """A LinoSPAD2 capture or calibration file is unreadable or inconsistent (names the
    file and what is wrong)."""


def _firmware(firmware: str, where: str) -> str:
    try:
        return lino.check_firmware(firmware)
    except ValueError as exc:
        raise Linospad2Error(f"{where}: {exc}") from None


def cycle_bytes(words_per_line: int = lino.WORDS_PER_LINE) -> int:
    """Bytes of one acquisition cycle (52 000 at 200 words per line)."""
    return lino.LINES * words_per_line * _LE_U32.itemsize


def file_cycles(path, words_per_line: int = lino.WORDS_PER_LINE) -> tuple[int, int]:
    """(whole cycles, bytes after them) of a capture, from its size."""
    size = os.path.getsize(path)
    return divmod(size, cycle_bytes(words_per_line))


def _native(words: np.ndarray) -> np.ndarray:
    return words.astype(np.uint32, copy=False)


def looks_like_linospad2(path, words_per_line: int = lino.WORDS_PER_LINE,
                         allow_truncated: bool = False) -> bool:
    """Whether ``path`` holds LinoSPAD2 2212 raw words with ``words_per_line`` words a line.

    Without a header, the evidence is the structure, checked on the first
    ``SNIFF_CYCLES`` cycles:

    1. the size is a whole number (>= 1) of cycles of 65 lines (any size with at least one
       whole cycle if ``allow_truncated``);
    2. in each of the 65 lines, the valid words (bit 31) come first and the padding after:
       the TDC's buffer is read out, then filled up. Random words have a valid bit after
       an invalid one in nearly every line (probability ~1 - 2^-(wpl-1) per line);
    3. along a line's valid words, the time codes increase (a TDC records in time order;
       one wrap of the 28-bit code is allowed per line, for windows over 4.8 ms);
    4. at least one valid word in the 64 TDC lines.

    A PTU file fails at 2 or 1 (its first word, "PQTT", has bit 31 clear and its header
    tags follow); other raw uint32 streams (this project's own ``.bin`` captures, which are
    big-endian with a marker per cycle) fail at 2 or 3. Bit 30 is not used: daplis does not
    document it, and in the sample it equals bit 31 (it is not zero).
    Unreadable files raise ``OSError``.
    """
    n_cycles, extra = file_cycles(path, words_per_line)
    if n_cycles == 0 or (extra and not allow_truncated):
        return False
    n = min(n_cycles, SNIFF_CYCLES)
    with open(path, "rb") as f:
        w = _native(np.fromfile(f, dtype=_LE_U32, count=n * lino.LINES * words_per_line))
    c = w.reshape(n, lino.LINES, words_per_line)
    valid = (c & lino.VALID_BIT) != 0
    # 2: valid words are a prefix of every line (no invalid -> valid step)
    if np.any(~valid[..., :-1] & valid[..., 1:]):
        return False
    # 3: codes increase along the valid words of each TDC line (at most one wrap a line)
    code = (c[:, : lino.LINES - 1] & lino.CODE_MASK).astype(np.int64)
    both = valid[:, : lino.LINES - 1, 1:] & valid[:, : lino.LINES - 1, :-1]
    steps_down = np.count_nonzero((np.diff(code, axis=2) <= 0) & both, axis=2)
    if np.any(steps_down > 1):
        return False
    # 4: some photons
    return bool(valid[:, : lino.LINES - 1].any())


def _iter_words(path, chunk_cycles: int, words_per_line: int
                ) -> Iterator[tuple[int, np.ndarray]]:
    """(first cycle, native uint32 words of whole cycles), chunk by chunk."""
    if chunk_cycles < 1:
        raise Linospad2Error(f"{path}: chunk_cycles must be >= 1, found {chunk_cycles}")
    if words_per_line < 1:
        raise Linospad2Error(f"{path}: words_per_line must be >= 1, found {words_per_line}")
    n_cycles, _ = file_cycles(path, words_per_line)
    per_cycle = lino.LINES * words_per_line
    with open(path, "rb") as f:
        for first in range(0, n_cycles, chunk_cycles):
            n = min(chunk_cycles, n_cycles - first)
            w = np.fromfile(f, dtype=_LE_U32, count=n * per_cycle)
            if w.size != n * per_cycle:   # the file shrank while being read
                raise Linospad2Error(f"{path}: expected {n * per_cycle} words at cycle "
                                     f"{first}, read {w.size}")
            yield first, _native(w)


def iter_cycles(path, firmware: str, chunk_cycles: int = CHUNK_CYCLES,
                words_per_line: int = lino.WORDS_PER_LINE) -> Iterator[lino.Decoded]:
    """Decoded photon words, ``chunk_cycles`` whole cycles at a time (bounded memory).

    The chunks' tallies add up to the file's: the last chunk carries the bytes after the
    last whole cycle (``truncated_bytes``); a file with no whole cycle yields one empty
    chunk that carries them.
    """
    _firmware(firmware, str(path))
    _, extra = file_cycles(path, words_per_line)
    chunks = _iter_words(path, chunk_cycles, words_per_line)
    pending = None
    for first, words in chunks:
        if pending is not None:
            yield pending
        pending = lino.decode_words(words, firmware, words_per_line, first_cycle=first)
    if pending is None:
        pending = lino.decode_words(np.zeros(0, np.uint32), firmware, words_per_line)
    if extra:
        pending = lino.Decoded(**{**pending.columns(),
                                  "tally": pending.tally + lino.Tally(truncated_bytes=extra)})
    yield pending


def histogram_file(path, firmware: str, by: str = "pixel",
                   chunk_cycles: int = CHUNK_CYCLES,
                   words_per_line: int = lino.WORDS_PER_LINE) -> tuple[np.ndarray, lino.Tally]:
    """Fine-code counts of a whole capture, (256, 140) by pixel or (64, 140) by TDC, uint64,
    and its tally (truncated bytes included)."""
    _firmware(firmware, str(path))
    if by not in ("tdc", "pixel"):
        raise Linospad2Error(f"{path}: by must be 'tdc' or 'pixel', found {by!r}")
    n_rows = lino.N_TDC if by == "tdc" else lino.N_PIXEL
    counts = np.zeros((n_rows, lino.N_FINE), np.uint64)
    tally = lino.Tally(truncated_bytes=file_cycles(path, words_per_line)[1])
    for _, words in _iter_words(path, chunk_cycles, words_per_line):
        c, t = lino.fine_histograms(words, firmware, by, words_per_line)
        counts += c
        tally = tally + t
    return counts, tally


#: Arrow schema metadata key of the decoded table's accounting (JSON of ``Tally``)
META_TALLY = b"linospad2.tally"
META_FIRMWARE = b"linospad2.firmware"


def decode_file(path, firmware: str, words_per_line: int = lino.WORDS_PER_LINE,
                chunk_cycles: int = CHUNK_CYCLES) -> pa.Table:
    """Every photon word of a capture as a ``linospad2_events`` table.

    The schema metadata carries the firmware and the tally (``META_TALLY``, JSON), so the
    table says how many padding, 65th-line and truncated words/bytes it does not hold.
    """
    parts = {name: [] for name in LINOSPAD2_EVENTS.names}
    tally = lino.Tally()
    for chunk in iter_cycles(path, firmware, chunk_cycles, words_per_line):
        for name, col in chunk.columns().items():
            parts[name].append(col)
        tally = tally + chunk.tally
    schema = LINOSPAD2_EVENTS.schema
    arrays = [pa.array(np.concatenate(parts[f.name]), type=f.type) for f in schema]
    meta = {**(schema.metadata or {}), META_FIRMWARE: firmware.encode(),
            META_TALLY: json.dumps(tally.to_dict()).encode()}
    table = pa.Table.from_arrays(arrays, schema=schema.with_metadata(meta))
    validate(table, LINOSPAD2_EVENTS, where=str(path))
    return table


def table_tally(table: pa.Table) -> lino.Tally:
    """The tally :func:`decode_file` stamped in a table's metadata."""
    raw = (table.schema.metadata or {}).get(META_TALLY)
    if raw is None:
        raise Linospad2Error("table has no LinoSPAD2 tally in its metadata")
    return lino.Tally(**json.loads(raw))


def read_published_calibration(csv_path) -> np.ndarray:
    """The board's published TDC calibration: (256, 140) float64 cumulative code times, ps.

    Accepts the daplis layout (header row ``,0,...,139`` and the pixel index as first
    column) and the bare 256 x 140 numbers. Raises :class:`Linospad2Error` naming the file
    for a wrong shape, a non-number, an index that is not 0..255, or a row that is not a
    cumulative time within one clock period (decreasing, or outside 0..2500 ps).
    """
    where = str(csv_path)
    try:
        with open(csv_path, newline="") as f:
            rows = [r for r in csv.reader(f) if r and any(cell.strip() for cell in r)]
    except UnicodeDecodeError as exc:
        raise Linospad2Error(f"{where}: not a text CSV ({exc})") from None
    if not rows:
        raise Linospad2Error(f"{where}: empty calibration file")
    header = rows[0]
    if header[0].strip() == "" or not _is_number(header[0]):
        expected = [str(k) for k in range(lino.N_FINE)]
        if [c.strip() for c in header[1:]] != expected:
            raise Linospad2Error(f"{where}: header should be ',0,1,...,{lino.N_FINE - 1}' "
                                 f"({lino.N_FINE} codes), found {len(header) - 1} columns "
                                 f"{header[1:4]}...")
        rows = rows[1:]
    widths = {len(r) for r in rows}
    if len(rows) != lino.N_PIXEL or len(widths) != 1 or \
            widths.pop() not in (lino.N_FINE, lino.N_FINE + 1):
        raise Linospad2Error(
            f"{where}: expected {lino.N_PIXEL} pixel rows of {lino.N_FINE} codes (plus an "
            f"optional index column), found {len(rows)} rows of "
            f"{sorted({len(r) for r in rows})} columns")
    try:
        data = np.array([[float(c) for c in r] for r in rows], np.float64)
    except ValueError as exc:
        raise Linospad2Error(f"{where}: not a number: {exc}") from None
    if data.shape[1] == lino.N_FINE + 1:
        if not np.array_equal(data[:, 0], np.arange(lino.N_PIXEL)):
            raise Linospad2Error(f"{where}: first column should be the pixel index 0..255")
        data = data[:, 1:]
    if not np.all(np.isfinite(data)):
        bad = np.argwhere(~np.isfinite(data))[0].tolist()
        raise Linospad2Error(f"{where}: non-finite value at pixel {bad[0]}, code {bad[1]}")
    if np.any(np.diff(data, axis=1) < 0):
        p = int(np.flatnonzero(np.any(np.diff(data, axis=1) < 0, axis=1))[0])
        raise Linospad2Error(f"{where}: pixel {p}'s code times decrease: not a cumulative "
                             "calibration table")
    if data.min() < 0 or data.max() > lino.CLOCK_PS * (1 + 1e-9):
        raise Linospad2Error(f"{where}: code times outside 0..{lino.CLOCK_PS:g} ps "
                             f"({data.min():g}..{data.max():g})")
    return data


def _is_number(s: str) -> bool:
    try:
        float(s)
    except ValueError:
        return False
    return True


def published_name(path) -> dict:
    """Daughterboard, motherboard and firmware from a daplis file name
    ``TDC_<db>_<mb>_<fw>.csv``, when it has that form (else an empty dict).

    >>> published_name("x/TDC_A5_#36_2212b.csv")
    {'daughterboard': 'A5', 'motherboard': '#36', 'firmware': '2212b'}
    """
    parts = Path(path).stem.split("_")
    if len(parts) == 4 and parts[0] == "TDC":
        return dict(zip(("daughterboard", "motherboard", "firmware"), parts[1:], strict=True))
    return {}


def broken_lines(path, words_per_line: int = lino.WORDS_PER_LINE,
                 cycles: int = 64) -> tuple[int, int]:
    """``(broken, lines)`` over the first ``cycles`` whole cycles of ``path``: the lines
    whose valid words do not come first (an invalid word before a valid one), which a
    LinoSPAD2 file never has and another file read as one has in nearly every line. What
    ``--format linospad2`` on a file that is not one is refused by."""
    n_cycles, _ = file_cycles(path, words_per_line)
    n = min(n_cycles, cycles)
    if n == 0:
        return 0, 0
    with open(path, "rb") as f:
        w = _native(np.fromfile(f, dtype=_LE_U32, count=n * lino.LINES * words_per_line))
    valid = (w.reshape(n * lino.LINES, words_per_line) & lino.VALID_BIT) != 0
    return int(np.count_nonzero((~valid[:, :-1] & valid[:, 1:]).any(axis=1))), n * lino.LINES
