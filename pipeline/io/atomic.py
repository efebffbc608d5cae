"""Write-then-rename, so a failed run never leaves a half-written output in place."""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from functools import cache
from pathlib import Path

_AT_FDCWD = -100
_RENAME_EXCHANGE = 2


@cache
def _renameat2():
    """libc's renameat2 (Linux >= 3.15, glibc >= 2.28), or None where there is none."""
    import ctypes  # (here: ctypes.util's import is 10-30 ms of every command's start)
    import ctypes.util

    try:
        fn = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6", use_errno=True).renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                   ctypes.c_uint]
    return fn


def exchange(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """Swap two existing paths in one step (``renameat2(RENAME_EXCHANGE)``): no moment
    without either. False where the system cannot (another OS, or a file system without
    it); the caller then falls back to renames."""
    fn = _renameat2()
    if fn is None:
        return False
    if fn(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    import ctypes

    err = ctypes.get_errno()
    if err in (22, 38, 95):  # EINVAL, ENOSYS, EOPNOTSUPP: not here
        return False
    raise OSError(err, os.strerror(err), str(a), None, str(b))


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling of ``path``; rename it onto ``path`` if the block succeeds.

    Works for files and directories. On error the temporary is removed and ``path`` is
    left as it was. A directory is swapped in one step where the system can exchange two
    paths (Linux), else by two renames (a moment without ``path``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    _remove(tmp)
    try:
        yield tmp
        if tmp.is_file():
            with open(tmp, "rb") as fh:
                os.fsync(fh.fileno())
        if path.is_dir() and not path.is_symlink() and tmp.is_dir():
            if exchange(tmp, path):
                shutil.rmtree(tmp)  # the old directory, now under the temporary's name
            else:
                old = path.with_name(f".{path.name}.old-{os.getpid()}")
                os.replace(path, old)
                os.replace(tmp, path)
                shutil.rmtree(old)
        else:
            os.replace(tmp, path)
    finally:
        _remove(tmp)


def point_link(link: str | os.PathLike, target: str | os.PathLike) -> Path | None:
    """Make ``link`` a symlink to ``target`` (relative, so the tree can move) without a
    moment when ``link`` is missing: a new link renamed over the old one, or exchanged with
    a directory that stood there (returned, for the caller to keep or remove; else None)."""
    import secrets

    link = Path(link)
    new = link.with_name(f".{link.name}.link-{secrets.token_hex(4)}")
    os.symlink(os.path.relpath(Path(target).resolve(), link.parent.resolve()), new)
    try:
        if link.is_dir() and not link.is_symlink():
            if not exchange(new, link):
                old = link.with_name(f".{link.name}.old-{os.getpid()}")
                os.replace(link, old)
                os.replace(new, link)
                return old
            return new  # the old directory, now under the new link's name
        os.replace(new, link)
        return None
    finally:
        if new.is_symlink():
            new.unlink()


def _remove(p: Path) -> None:
    if p.is_dir() and not p.is_symlink():
        shutil.rmtree(p)
    elif p.exists() or p.is_symlink():
        p.unlink()
