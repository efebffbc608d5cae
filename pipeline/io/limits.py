"""Limits on what a file may make this software allocate, and the bounded readers that
apply them (a small or sparse file must not claim gigabytes: issue 36, point 6).

Every size read from a file is checked against the file's real size and against one of the
limits here before anything is allocated; each limit is far above what the instruments and
the daemon write (docs/operations.md, "Hostile input").
"""

from __future__ import annotations

import os
import stat
import tomllib

from schemas.errors import TcspcError

#: a configuration file (a topology, a serve config, the page's JSON): real ones are a
#: few KiB
MAX_CONFIG_BYTES = 1 << 20
#: problems listed in one error; the rest are counted in its last line
MAX_PROBLEMS = 20


class FileTooLarge(TcspcError, ValueError):
    """A file, or a size it declares, is beyond a stated limit (names both)."""


def read_bounded(path: str | os.PathLike, limit: int = MAX_CONFIG_BYTES,
                 what: str = "file") -> bytes:
    """The bytes of a regular file of at most ``limit`` bytes (FileTooLarge otherwise, or
    for a FIFO or device, which could block or never end). OSError as open raises it."""
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    with os.fdopen(fd, "rb") as fh:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise FileTooLarge(f"{path}: not a regular file; a {what} is a file")
        if st.st_size > limit:
            raise FileTooLarge(f"{path}: {st.st_size} bytes, more than a {what} may hold "
                               f"({limit} bytes)")
        data = fh.read(limit + 1)
    if len(data) > limit:  # (grew while read)
        raise FileTooLarge(f"{path}: more than a {what} may hold ({limit} bytes)")
    return data


def loads_toml(text: str, where: str) -> dict:
    """``tomllib.loads`` of at most :data:`MAX_CONFIG_BYTES` characters, a nesting too deep
    for the interpreter's stack refused in one line (no RecursionError); tomllib's own
    errors pass through."""
    if len(text) > MAX_CONFIG_BYTES:
        raise FileTooLarge(f"{where}: {len(text)} characters, more than a configuration file "
                           f"may hold ({MAX_CONFIG_BYTES})")
    try:  # (tomllib has no depth limit: it recurses per level of nesting)
        return tomllib.loads(text)
    except RecursionError:
        raise FileTooLarge(f"{where}: arrays or tables nested too deeply to read") from None


def load_toml(path: str | os.PathLike, what: str = "configuration file") -> dict:
    """A TOML file of at most :data:`MAX_CONFIG_BYTES` as a dict. Raises OSError (as open),
    UnicodeDecodeError, tomllib.TOMLDecodeError or FileTooLarge."""
    return loads_toml(read_bounded(path, MAX_CONFIG_BYTES, what).decode("utf-8"), str(path))


def capped(problems: list[str], limit: int = MAX_PROBLEMS) -> str:
    """Problems as lines, the first ``limit`` of the distinct ones and a count of the
    rest (a file of 200 k unknown keys gives 21 lines, not 46 MB)."""
    lines = list(dict.fromkeys(problems))
    if len(lines) <= limit:
        return "\n".join(lines)
    return "\n".join(lines[:limit] + [f"... and {len(lines) - limit} more problems"])


__all__ = ["MAX_CONFIG_BYTES", "MAX_PROBLEMS", "FileTooLarge",
           "read_bounded", "loads_toml", "load_toml", "capped"]
