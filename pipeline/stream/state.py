"""The daemon's state directory, taken at start: the daemon's own, private, locked.

``open_state`` runs before anything is started or written:

- the directory is created mode 0700, or an existing one is taken only when this user owns
  it and neither group nor others may write it (then made 0700: sockets, logs, tokens,
  keys and status are private whatever the umask);
- a lock (``STATE/daemon.lock``, ``fcntl`` record lock, released by the kernel when the
  process dies however it dies) refuses a second daemon on the same state, naming the
  first one's pid;
- a symbolic link anywhere in it, or an entry another user owns, is refused by name
  (planted before the start, it would let that user choose what the daemon truncates,
  writes or chmods); after the check nobody else can add one (0700).

``check_resources`` then probes what the stages will need (the UDP port, the page's port,
the tcp:// endpoints, the ipc:// path lengths, the output directory), so a resource a stage
cannot get fails the daemon at start with its reason instead of a restart loop.
"""

from __future__ import annotations

import errno
import os
import socket
import stat
from pathlib import Path

from schemas.errors import TcspcError

LOCK_NAME = "daemon.lock"
#: the longest ipc:// path the kernel takes (sun_path is 108 bytes with its NUL on Linux)
IPC_PATH_MAX = 107


class StateError(TcspcError, RuntimeError):
    """A state directory or a resource the daemon cannot take (names it and why)."""


class StateLock:
    """The held lock of a state directory (``release`` or the process's death frees it)."""

    def __init__(self, path: Path, fd: int):
        self.path, self.fd = path, fd

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def __del__(self):
        self.release()


def open_nofollow(path: Path, flags: int, mode: int = 0o600) -> int:
    """``os.open`` that refuses a symbolic link at ``path`` (StateError naming it)."""
    try:
        return os.open(path, flags | os.O_NOFOLLOW | os.O_CLOEXEC, mode)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise StateError(f"{path}: a symbolic link where the daemon writes a file; "
                             "refused (remove it)") from None
        raise


def check_ancestors(path: Path, label: str = "state directory") -> None:
    """Refuse ``path`` when a folder above it could be renamed or replaced by another
    account: one owned by a user other than root or this one, or writable by others
    without the sticky bit (/tmp's mode 1777 is fine: nobody may rename what is ours
    there). Such a folder's owner could swap the whole directory mid-run."""
    uid = os.geteuid()
    p = Path(os.path.abspath(path)).parent
    for d in (p, *p.parents):
        try:
            st = os.stat(d)
        except FileNotFoundError:
            continue  # (made by us: mkdir below)
        if st.st_uid not in (0, uid):
            raise StateError(f"{path}: inside {d}, which uid {st.st_uid} owns (it could "
                             f"swap the {label} mid-run); refused: use a folder of your own")
        if st.st_mode & 0o022 and not st.st_mode & stat.S_ISVTX:
            raise StateError(f"{path}: inside {d}, which others may write (mode "
                             f"{stat.S_IMODE(st.st_mode):o}, no sticky bit: they could swap "
                             f"the {label} mid-run); refused")


def make_private(state: Path, label: str = "state directory") -> None:
    """``state`` created 0700, or an existing one taken only when this user owns it and
    others may not write it (then made 0700), its folders above checked
    (:func:`check_ancestors`)."""
    check_ancestors(state, label)
    _make_private(state, label)


def _make_private(state: Path, label: str = "state directory") -> None:
    uid = os.geteuid()
    if state.is_symlink() and os.lstat(state).st_uid != uid:
        raise StateError(f"{state}: a symbolic link owned by uid {os.lstat(state).st_uid}, "
                         f"not by this user; refused as a {label}")
    try:
        st = os.stat(state)
    except FileNotFoundError:
        state.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.mkdir(state, 0o700)
        except FileExistsError:
            pass
        st = os.stat(state)
    if not stat.S_ISDIR(st.st_mode):
        raise StateError(f"{state}: not a directory; refused as a {label}")
    if st.st_uid != uid:
        raise StateError(f"{state}: owned by uid {st.st_uid}, not by this user (uid {uid}); "
                         f"refused as a {label}")
    if st.st_mode & 0o022:
        raise StateError(f"{state}: group- or world-writable (mode "
                         f"{stat.S_IMODE(st.st_mode):o}); refused as a {label} "
                         "(`chmod 700` it if it is yours)")
    os.chmod(state, 0o700)


def refuse_links(state: Path) -> None:
    """Every symbolic link, or entry of another user, in the state tree (one error)."""
    uid, bad = os.geteuid(), []
    for root, dirs, files in os.walk(state):
        for name in dirs + files:
            p = Path(root) / name
            st = os.lstat(p)
            if stat.S_ISLNK(st.st_mode):
                bad.append(f"{p}: a symbolic link")
            elif st.st_uid != uid:
                bad.append(f"{p}: owned by uid {st.st_uid}")
        dirs[:] = [d for d in dirs if not os.path.islink(os.path.join(root, d))]
    if bad:
        raise StateError(f"{state}: refused as a state directory (the daemon writes only "
                         "its own files, never through a link):\n" + "\n".join(bad[:20])
                         + (f"\n... and {len(bad) - 20} more" if len(bad) > 20 else ""))


def open_state(state: str | Path) -> StateLock:
    """Take ``state`` for this daemon: private, locked, free of links (module docstring)."""
    import fcntl

    state = Path(state)
    make_private(state)
    path = state / LOCK_NAME
    fd = open_nofollow(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except OSError:
        holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
        os.close(fd)
        raise StateError(f"{state}: in use by daemon pid {holder} (it holds {path}); one "
                         "daemon per state directory: stop it, or give another "
                         "[daemon] state") from None
    os.ftruncate(fd, 0)
    os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
    lock = StateLock(path, fd)
    try:
        refuse_links(state)
    except StateError:
        lock.release()
        raise
    return lock


# ------------------------------------------------------------------------ output tree
def _check_dir_stat(st: os.stat_result, where, label: str) -> None:
    uid = os.geteuid()
    if not stat.S_ISDIR(st.st_mode):
        raise StateError(f"{where}: not a directory (a link or a file where the {label} "
                         "has a folder); refused")
    if st.st_uid != uid:
        raise StateError(f"{where}: owned by uid {st.st_uid}, not by this user (uid {uid}); "
                         f"refused in the {label}")
    if st.st_mode & 0o022:
        raise StateError(f"{where}: group- or world-writable (mode "
                         f"{stat.S_IMODE(st.st_mode):o}); refused in the {label} (others "
                         "could plant links or swap files there; `chmod go-w` it)")


def check_output_dir(out: str | Path, label: str = "output directory") -> None:
    """The output tree taken as the state directory is (issue 36): made if missing, then
    refused unless this user owns it, others may not write it, it is no symbolic link,
    no folder above it belongs to another account, and no entry at its top (a dataset's
    folder, ``accounting``) is a link or another user's. Datasets may stay readable by
    others (0755): only writing is kept to the owner."""
    out = Path(out)
    check_ancestors(out, label)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise StateError(f"{out}: cannot make the {label}: {exc.strerror}") from None
    _check_dir_stat(os.lstat(out), out, label)
    with os.scandir(out) as it:
        for e in it:
            st = e.stat(follow_symlinks=False)
            if stat.S_ISLNK(st.st_mode):
                raise StateError(f"{e.path}: a symbolic link in the {label}; refused "
                                 "(the daemon writes its datasets and accounting itself)")
            if stat.S_ISDIR(st.st_mode):
                _check_dir_stat(st, e.path, label)


def write_under(root: str | Path, rel: str | Path, data: bytes | memoryview,
                label: str = "output directory") -> Path:
    """Write ``data`` to ``root/rel`` atomically without following a link anywhere: each
    folder opened from its checked parent's descriptor (``O_NOFOLLOW``, made 0755 when
    missing, refused when not this user's or writable by others), the bytes written to an
    ``O_EXCL | O_NOFOLLOW`` temporary, fsynced and renamed in that folder. A link or a
    file planted at the temporary's or a folder's name is refused, never followed."""
    root, rel = Path(root), Path(rel)
    root.mkdir(parents=True, exist_ok=True)  # (then checked as every folder below it)
    flags = os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(root, flags)
    except OSError as exc:
        raise StateError(f"{root}: cannot open the {label}: {exc.strerror}") from None
    try:
        _check_dir_stat(os.fstat(fd), root, label)
        where = root
        for part in rel.parts[:-1]:
            where = where / part
            try:
                os.mkdir(part, 0o755, dir_fd=fd)
            except FileExistsError:
                pass
            try:
                sub = os.open(part, flags, dir_fd=fd)
            except OSError as exc:
                raise StateError(f"{where}: cannot open a folder of the {label} "
                                 f"({exc.strerror}; a link is never followed)") from None
            os.close(fd)
            fd = sub
            _check_dir_stat(os.fstat(fd), where, label)
        name = rel.name
        tmp = f".{name}.tmp-{os.getpid()}-{os.urandom(4).hex()}"
        try:
            out = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW
                          | os.O_CLOEXEC, 0o644, dir_fd=fd)
        except OSError as exc:
            raise StateError(f"{where / tmp}: cannot create a temporary in the {label}: "
                             f"{exc.strerror}") from None
        try:
            view = memoryview(data).cast("B")
            while view.nbytes:
                view = view[os.write(out, view):]
            os.fsync(out)
        except BaseException:
            os.close(out)
            os.unlink(tmp, dir_fd=fd)
            raise
        os.close(out)
        os.replace(tmp, name, src_dir_fd=fd, dst_dir_fd=fd)  # (a link at name: replaced)
        return root / rel
    finally:
        os.close(fd)


# ------------------------------------------------------------------------ resources
def _probe(family: int, kind: int, host: str, port: int) -> str | None:
    """Why (host, port) cannot be bound, or None when it can (the probe is closed)."""
    try:
        infos = socket.getaddrinfo(host, port, family, kind)
    except socket.gaierror as exc:
        return f"cannot resolve {host!r}: {exc.strerror}"
    fam, _, _, _, addr = infos[0]
    with socket.socket(fam, kind) as s:
        if kind == socket.SOCK_STREAM:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as a server does
        try:
            s.bind(addr)
        except OSError as exc:
            return exc.strerror or str(exc)
    return None


def _host_port(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host.strip("[]"), int(port)


def bound_endpoints(topo) -> list[tuple[str, str]]:
    """(who, endpoint) of every endpoint a stage of ``topo`` binds (its input)."""
    out = [("the daemon's metrics", topo.metrics), ("sink", topo.endpoint(topo.sink, "sink"))]
    out += [(f"histogram-{i}", topo.endpoint(topo.histogram, f"histogram-{i}", i))
            for i in range(topo.workers)]
    if topo.range:
        out.append(("range", topo.endpoint(topo.range, "range")))
    from pipeline.stream.sidecar import status_endpoint

    out.append(("the status publisher", status_endpoint(topo.state)))
    return out


def check_resources(topo) -> None:
    """Every resource a stage will need, probed now; one StateError listing each one that
    cannot be had (nothing has been started)."""
    problems = []
    for who, ep in bound_endpoints(topo):
        if ep.startswith("ipc://"):
            path = ep[len("ipc://"):]
            if len(path.encode()) > IPC_PATH_MAX:
                problems.append(f"{who}: {ep}: the ipc path is {len(path.encode())} bytes, "
                                f"the kernel takes {IPC_PATH_MAX} (the state directory "
                                f"{str(topo.state.resolve())!r} is "
                                f"{len(str(topo.state.resolve()))} characters: use a "
                                "shorter [daemon] state, or tcp:// endpoints)")
        elif ep.startswith("tcp://"):
            host, port = _host_port(ep[len("tcp://"):])
            why = _probe(socket.AF_UNSPEC, socket.SOCK_STREAM,
                         "0.0.0.0" if host == "*" else host, port)
            if why:
                problems.append(f"{who}: cannot bind {ep}: {why}")
    src = topo.source
    if src["kind"] == "udp":
        host, port = _host_port(src["bind"])
        why = _probe(socket.AF_INET, socket.SOCK_DGRAM, host, port)
        if why:
            problems.append(f"source: cannot listen for datagrams on {src['bind']} "
                            f"([source] bind): {why}")
    if topo.view is not None and topo.view.get("port", 5006):
        bind, port = topo.view.get("bind", "127.0.0.1"), topo.view.get("port", 5006)
        why = _probe(socket.AF_UNSPEC, socket.SOCK_STREAM, bind, port)
        if why:
            problems.append(f"view: cannot listen on {bind}:{port} ([view] port): {why} "
                            "(another `tcspc view`? another port, or port = 0 for any)")
    out = Path(topo.sink["out"])
    try:
        check_output_dir(out, "[sink] out")
    except StateError as exc:
        problems.append(f"sink: {exc}")
    try:
        out.mkdir(parents=True, exist_ok=True)
        fd = os.open(out / f".tcspc-probe-{os.getpid()}", os.O_WRONLY | os.O_CREAT
                     | os.O_EXCL | os.O_NOFOLLOW, 0o600)
        os.close(fd)
        os.unlink(out / f".tcspc-probe-{os.getpid()}")
    except OSError as exc:
        problems.append(f"sink: cannot write the datasets in {str(out)!r} ([sink] out): "
                        f"{exc.strerror or exc}")
    if problems:
        raise StateError(f"{topo.path}: the daemon cannot start; nothing was started:\n"
                         + "\n".join(problems))
