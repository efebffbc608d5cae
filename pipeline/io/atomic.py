"""Write-then-rename, so a failed run never leaves a half-written output in place."""

from __future__ import annotations

import contextlib
import os
import shutil
from collections.abc import Iterator
from functools import cache
from pathlib import Path

from schemas.errors import TcspcError

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


# --- outputs, checked at the door (docs/design.md "Outputs: never lost, never silently
# replaced") -----------------------------------------------------------------------------

#: the first bytes of each kind of file a command writes, to know an existing file's kind
_MAGIC = {"parquet": b"PAR1", "png": b"\x89PNG", "hdf5": b"\x89HDF"}
#: room kept free beyond an output's expected size (the file system's own needs, logs)
HEADROOM_BYTES = 64 << 20


class OutputError(TcspcError, ValueError):
    """An output refused before any work: it names the user's path and why."""


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB", "PB"):
        if n < 1000 or unit == "PB":
            return f"{n:.3g} {unit}"
        n /= 1000
    return f"{n:.3g} PB"  # pragma: no cover


def _kind_of(path: Path) -> str:
    """``dir``, ``capture`` (a tcspc-raw sidecar), a magic kind (parquet, png, hdf5),
    ``empty`` or ``other``."""
    if path.is_dir():
        return "dir"
    try:
        with open(path, "rb") as fh:
            head = fh.read(512)
    except OSError:
        return "other"
    if not head:
        return "empty"
    for kind, magic in _MAGIC.items():
        if head.startswith(magic):
            return kind
    if b'"tcspc-raw"' in head:
        return "capture"
    return "other"


def _schema_of(path: Path) -> str | None:
    """The ``tcspc.schema`` name of an existing parquet file (None: none, or unreadable)."""
    try:
        import pyarrow.parquet as pq

        meta = pq.read_schema(path).metadata or {}
    except Exception:  # noqa: BLE001 - a damaged file is "another kind" below
        return None
    name = meta.get(b"tcspc.schema")
    return name.decode() if name else None


def _existing_ancestor(path: Path) -> Path:
    p = path.absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_output(path: str | os.PathLike, kind: str = "file", *, overwrite: bool = False,
                 option: str = "--out", schema: str | tuple[str, ...] | None = None,
                 fmt: str | None = None, expected_bytes: float = 0,
                 contents: tuple[str, ...] = ()) -> Path:
    """Refuse an output before any work: the policy of every command that writes.

    ``kind`` is what the command writes at ``path``: ``file`` (``fmt``: parquet, png or
    hdf5, else read from the path's suffix; ``schema``: the tcspc schema a parquet file
    holds, or the schemas it may hold), ``capture`` (``NAME.bin`` +
    ``NAME.json``) or ``dir`` (a directory the command fills; ``contents``: the names that
    make it one of this command's, such as a calibration's ``tdc.parquet``).

    - A path that cannot be written (under a file, in a directory without write
      permission) is refused.
    - An existing output of another kind (a directory for a file, a ranges file for
      histograms, a PNG for a parquet file, a directory that is not the command's) is
      refused always: nothing replaces what it does not know.
    - An existing output of the same kind is replaced only with ``overwrite``
      (``--overwrite``), and then in one rename (:func:`atomic_path`).
    - ``expected_bytes`` more than the free space of its file system (less a margin) is
      refused, with the numbers.

    Returns ``path`` as a Path; raises :class:`OutputError` naming ``option`` and the path.
    """
    p = Path(path)
    where = f"{option} {p}"
    if not str(path).strip():
        raise OutputError(f"{option}: an empty path")
    targets = [p]
    if kind == "capture":
        from pipeline.io.capture import capture_paths

        targets = list(capture_paths(p))
    for t in targets:
        base = _existing_ancestor(t.parent)
        if not base.is_dir():
            raise OutputError(f"{where}: cannot be written: {base} is a file, not a "
                              "directory; nothing done")
        if not os.access(base, os.W_OK | os.X_OK):
            raise OutputError(f"{where}: cannot be written: {base} is not writable; "
                              "nothing done")
        if t.is_symlink() and not t.exists():
            raise OutputError(f"{where}: {t} is a broken symbolic link; nothing done")
        if not t.exists():
            continue
        found = _kind_of(t)
        if kind == "dir":
            if found != "dir":
                raise OutputError(f"{where}: a file; {option} takes a directory (not "
                                  "replaced)")
            names = {c.name for c in t.iterdir()}
            if not names:
                continue
            if contents and not names & set(contents):
                raise OutputError(f"{where}: a directory that holds other files "
                                  f"(none of {', '.join(contents)}): not replaced; give an "
                                  "empty or new directory")
        elif found == "dir":
            raise OutputError(f"{where}: {'a directory' if t == p else f'{t} is a directory'}"
                              f"; {option} takes a file path")
        elif kind == "capture":
            if t.suffix == ".json" and found not in ("capture", "empty"):
                raise OutputError(f"{where}: {t} exists and is not a capture's sidecar: "
                                  "not replaced")
        else:
            want = fmt or ("parquet" if schema else None) or {
                ".parquet": "parquet", ".png": "png", ".h5": "hdf5",
                ".hdf5": "hdf5"}.get(t.suffix.lower())
            if want and found not in (want, "empty"):
                raise OutputError(f"{where}: exists and is not a {want} file: not "
                                  "replaced")
            if schema and found == "parquet":
                held = _schema_of(t)
                schema = (schema,) if isinstance(schema, str) else schema
                if held not in schema:
                    what = f"a {held} table" if held else "a parquet table not of this tool"
                    raise OutputError(f"{where}: holds {what}, not "
                                      f"{' or '.join(schema)}: not replaced")
        if not overwrite:
            raise OutputError(f"{where}: {'' if t == p else f'{t} '}exists; give --overwrite "
                              "to replace it")
    if expected_bytes > 0:
        base = _existing_ancestor(p.parent)
        free = shutil.disk_usage(base).free
        if expected_bytes + HEADROOM_BYTES > free:
            raise OutputError(f"{where}: needs ~{_size(expected_bytes)}, {_size(free)} free "
                              f"on {base}; nothing written")
    return p
