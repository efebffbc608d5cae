"""Which kind of file a path is, from its content (``--format`` overrides).

- ``tcspc``: the project's own capture (``NAME.bin`` [.zst, .nhz] with its ``NAME.json``);
- ``ptu``: a PicoQuant PTU file (magic ``PQTTTR``);
- ``linospad2``: LinoSPAD2 raw words (whole cycles of 65 lines x 200 words, and the
  structure :func:`pipeline.io.linospad2.looks_like_linospad2` checks).

The extension is never trusted alone: a renamed file is still recognised, a file that is
none of these is refused with what was checked.
"""

from __future__ import annotations

from pathlib import Path

from schemas.constants import PTU_MAGIC
from schemas.errors import TcspcError

FORMATS = ("tcspc", "ptu", "linospad2")


def is_ptu(path: str | Path) -> bool:
    """True when the file starts with the PTU magic (8 bytes read: telling a format costs
    no import of a reader, and no read of the file)."""
    try:
        with open(path, "rb") as fh:
            return fh.read(8) == PTU_MAGIC
    except OSError:
        return False


class FormatError(TcspcError, ValueError):
    """A file this software cannot tell the format of, or cannot read as the given one."""


def detect_format(path: str | Path) -> str:
    """The format of ``path`` (one of :data:`FORMATS`), from its content."""
    path = Path(path)
    if path.is_file() and is_ptu(path):
        return "ptu"
    from pipeline.io.capture import capture_paths  # (not for a PTU file: its start)

    bin_path, json_path = capture_paths(path)
    if json_path.is_file() and (
            bin_path.is_file() or any(bin_path.with_name(bin_path.name + ext).is_file()
                                   for ext in (".zst", ".nhz"))):
        return "tcspc"
    if path.is_file():
        from pipeline.io.linospad2 import looks_like_linospad2

        if looks_like_linospad2(path):
            return "linospad2"
    if not path.exists():
        raise FormatError(f"{path}: no such file")
    raise FormatError(f"{path}: not a PTU file (no PQTTTR magic), not a tcspc capture (no "
                      "NAME.json beside it) and not LinoSPAD2 raw words (not whole 65 x 200-"
                      "word cycles of that structure); if it is one of those, give --format "
                      f"{'|'.join(FORMATS)}")


def resolve_format(path: str | Path, given: str | None) -> str:
    """``given`` if set (checked against :data:`FORMATS`), else :func:`detect_format`."""
    if given is None:
        return detect_format(path)
    if given not in FORMATS:
        raise FormatError(f"--format must be one of {', '.join(FORMATS)}, found {given!r}")
    return given


def instrument_words(path: str | Path, fmt: str, chunk_words: int = 1 << 20):
    """``(first_word, words)`` of an instrument's file as raw uint32 records in file order
    (PTU: the records after the header; LinoSPAD2: every word), in bounded chunks: what the
    daemon's ``file`` source replays. Trailing bytes that make no whole record are not a
    record; :func:`instrument_truncation` says so."""
    import numpy as np

    if fmt == "ptu":  # the PTU reader's own chunks (the records the header declares)
        from pipeline.io.ptu import iter_chunks

        yield from iter_chunks(path, chunk_words)  # (a reused buffer: use before next)
        return
    start, n = _records(path, fmt)
    if fmt == "linospad2":  # whole cycles only, so any chunk decodes alone
        from stages.instruments.linospad2 import LINES, WORDS_PER_LINE

        per_cycle = LINES * WORDS_PER_LINE
        chunk_words = max(1, chunk_words // per_cycle) * per_cycle
    with open(path, "rb") as f:
        f.seek(start)
        first = 0
        while first < n:
            words = np.fromfile(f, dtype="<u4", count=min(chunk_words, n - first))
            if words.size == 0:
                break
            yield first, words.astype(np.uint32, copy=False)
            first += words.size


def instrument_truncation(path: str | Path, fmt: str) -> str:
    """A one-line account of a truncated file ('' when it is whole): a PTU file holding
    fewer records than its header declares, or bytes that make no whole record or (for
    LinoSPAD2) no whole cycle."""
    if fmt == "ptu":
        from pipeline.io.ptu import read_header

        return read_header(path).truncation
    size = Path(path).stat().st_size
    from stages.instruments.linospad2 import LINES, WORDS_PER_LINE

    over = size % (4 * LINES * WORDS_PER_LINE)
    return (f"{path}: truncated: {over} bytes after the last whole cycle" if over else "")


def instrument_timing_ns(path: str | Path, fmt: str) -> float:
    """The period the file's times are measured in, ns: a PTU's sync period (200 ns at 5
    MHz), LinoSPAD2's 2.5 ns clock; the stream's ``t_laser_win_ns``."""
    if fmt == "ptu":
        from pipeline.io.ptu import read_header

        h = read_header(path)
        return 1e9 / h.sync_rate_hz if h.sync_rate_hz else 1.0
    return 2.5


def _records(path, fmt: str) -> tuple[int, int]:
    """(byte offset of the first record, records to read) of a LinoSPAD2 file."""
    if fmt == "linospad2":
        return 0, Path(path).stat().st_size // 4
    raise FormatError(f"{path}: {fmt!r} is not an instrument format")
