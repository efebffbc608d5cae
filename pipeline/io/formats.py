"""Which kind of file a path is, from its content (``--format`` overrides).

- ``tcspc``: the project's own capture (``NAME.bin`` [.zst] with its ``NAME.json``);
- ``ptu``: a PicoQuant PTU file (magic ``PQTTTR``);
- ``linospad2``: LinoSPAD2 raw words (whole cycles of 65 lines x 200 words, and the
  structure :func:`pipeline.io.linospad2.looks_like_linospad2` checks).

The extension is never trusted alone: a renamed file is still recognised, a file that is
none of these is refused with what was checked.
"""

from __future__ import annotations

from pathlib import Path

from pipeline.io.capture import capture_paths
from schemas.errors import TcspcError

FORMATS = ("tcspc", "ptu", "linospad2")


class FormatError(TcspcError, ValueError):
    """A file this software cannot tell the format of, or cannot read as the given one."""


def detect_format(path: str | Path) -> str:
    """The format of ``path`` (one of :data:`FORMATS`), from its content."""
    from pipeline.io.linospad2 import looks_like_linospad2
    from pipeline.io.ptu import is_ptu

    path = Path(path)
    if path.is_file() and is_ptu(path):
        return "ptu"
    bin_path, json_path = capture_paths(path)
    if json_path.is_file() and (
            bin_path.is_file() or bin_path.with_name(bin_path.name + ".zst").is_file()):
        return "tcspc"
    if path.is_file() and looks_like_linospad2(path):
        return "linospad2"
    if not path.exists():
        raise FormatError(f"{path}: no such file")
    raise FormatError(f"{path}: not a PTU file (no PQTTTR magic), not a tcspc capture (no "
                      "NAME.json beside it) and not LinoSPAD2 raw words (not whole 65 x 200-"
                      "word cycles of that structure); give --format if you know better")


def resolve_format(path: str | Path, given: str | None) -> str:
    """``given`` if set (checked against :data:`FORMATS`), else :func:`detect_format`."""
    if given is None:
        return detect_format(path)
    if given not in FORMATS:
        raise FormatError(f"--format must be one of {', '.join(FORMATS)}, found {given!r}")
    return given
