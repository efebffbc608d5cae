"""Stage processes forked from a pre-started server, so a stage starts in milliseconds.

A stage started as ``python -m pipeline.cli stage ...`` spends 0.2-0.3 CPU-s importing
numpy, pyarrow, zmq and its own modules before it binds; five of them starting at once on
two cores put the first measurement 1.3-1.9 s after the daemon's start (docs/performance.md,
"Time to the first measurement"). The daemon instead starts one server process when it
starts (multiprocessing's ``forkserver``: a fresh interpreter, no thread and no ZeroMQ
context of the daemon's), which imports those modules once, in parallel with the daemon's
own checks; each stage is then a ``fork()`` of that server running the same command line
(``pipeline.cli.app.main`` with the stage's arguments), with the same environment, log file,
process group and death signal as the exec'd process had.

``[daemon] fork_server = false`` goes back to one exec'd interpreter per stage.

What differs from an exec'd stage: its parent is the server (the server ends with the
daemon, and each stage has SIGKILL as its parent-death signal, so a killed daemon still
leaves no orphan); ``ps`` shows the server's command line, with the stage's name as the
process name (``ps -o pid,comm``; ``status.json`` has every stage's pid).
"""

from __future__ import annotations

import io
import json
import multiprocessing
import os
import runpy
import signal
import subprocess
import sys

#: what the server imports once: what the stages import, every module a forked stage
#: would otherwise import after its fork (CURVE's zmq.auth and the zmq.asyncio with
#: asyncio it imports at its first use, pyzmq's garbage collector of frames sent without
#: a copy, its socket monitor's reader at a stage's end (pipeline.stream.hangup),
#: numpy.ma, rich's emoji table at the first line printed), and not the daemon's
#: own (pipeline.stream.daemon, the topology's pydantic models: 0.1 CPU-s no stage uses,
#: on the way to the first fork; tests/pipeline/stream/test_forkstart.py holds both)
PRELOAD = ["numpy", "numpy.ma", "pyarrow", "pyarrow.ipc", "pyarrow.parquet", "zmq",
           "zmq.auth", "zmq.auth.thread", "zmq.asyncio", "zmq.utils.garbage",
           "zmq.utils.monitor", "zstandard",
           "pipeline.cli.app", "pipeline.cli.stream", "pipeline.stream.stage",
           "pipeline.stream.wire", "pipeline.stream.journal", "pipeline.stream.state",
           "pipeline.stream.fanout", "pipeline.stream.bounds", "pipeline.stream.metrics",
           "pipeline.stream.udp", "pipeline.stream.curve", "pipeline.stream.rawwire",
           "pipeline.io.caldir", "pipeline.io.capture", "stages.stream", "stages.nativecode",
           "rich._emoji_codes", "glob"]
#: and with a range stage in the graph: the ranging, its kernels loaded (forkwarm)
PRELOAD_RANGE = ["pipeline.offline.ranging", "stages.calibration.chip_check",
                 "pipeline.stream.forkwarm"]
#: the range stage's calibration and estimator, for the server's warm-up (forkwarm)
WARM_ENV = "TCSPC_FORK_WARM_RANGE"
#: "1": each forked stage writes in its log, at its end, the modules it imported after its
#: fork (what the server's preload missed: each is imported by every stage, after the
#: fork, on the way to the first measurement)
LATE_IMPORTS_ENV = "TCSPC_FORK_LATE_IMPORTS"


def die_with_parent() -> None:
    """In a stage (between fork and exec): SIGKILL it when the daemon dies, however the
    daemon dies, so a killed daemon leaves no orphan writing to the run (a restarted daemon
    resumes from the journal and the checkpoints, as after any crash). Linux only; the
    signal follows the thread that started the stage, which lives as long as the run."""
    # (nothing here may import or take a lock: other threads may hold them at the fork)
    if _PRCTL is not None:
        _PRCTL(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    if os.getppid() == 1:  # the daemon died before the prctl: do not start at all
        os._exit(1)


def _load_prctl():
    import ctypes

    try:
        return ctypes.CDLL(None).prctl
    except (OSError, AttributeError):
        return None  # not Linux: the journal's lock still keeps a second writer out


_PRCTL = _load_prctl()


_CTX = None


def context(ranging: bool = False):
    """The forkserver context, its preload set (once per process: the first call's)."""
    global _CTX
    if _CTX is None:
        # numpy's OpenBLAS is loaded in the server: one thread, as every `tcspc stage` asks
        # for before numpy loads (docs/performance.md; a user's own setting is kept)
        os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
        _CTX = multiprocessing.get_context("forkserver")
        _CTX.set_forkserver_preload(PRELOAD + (PRELOAD_RANGE if ranging else []))
    return _CTX


def warm(ranging: bool = False) -> None:
    """Start the server now: it imports while the daemon imports and checks its state."""
    from multiprocessing import forkserver

    context(ranging)
    forkserver.ensure_running()


def warm_for(config: str | None) -> None:
    """The daemon's first step: a look at the topology's ``[daemon] fork_server`` and
    ``[range]`` (the file is checked in full after), and the server started to suit."""
    import tomllib

    raw: dict = {"range": {}}  # (the embedded default topology ranges)
    if config:
        try:
            with open(config, "rb") as f:
                raw = tomllib.loads(f.read(1 << 20).decode())
        except (OSError, ValueError):
            return  # (load_topology says what is wrong with it)
    if (raw.get("daemon") or {}).get("fork_server", True) is False:
        return
    rng = raw.get("range")
    if isinstance(rng, dict) and isinstance(rng.get("calibration"), str) \
            and not rng.get("spatial"):  # (the spatial estimator is numpy: nothing to load)
        # the server loads the range stage's kernels too (pipeline.stream.forkwarm)
        os.environ[WARM_ENV] = json.dumps({k: rng[k] for k in
                                           ("calibration", "estimator", "max_returns")
                                           if k in rng})
    warm(ranging="range" in raw)


class StageProcess:
    """A stage forked from the server, with the part of ``subprocess.Popen``'s interface
    the supervisor uses: ``pid``, ``poll``, ``wait``, ``send_signal``, ``kill``."""

    def __init__(self, argv: list[str], env: dict[str, str], log: str, name: str):
        # argv is the exec form, python -m MODULE ARGS: the child runs MODULE with ARGS
        if len(argv) < 3 or argv[1] != "-m":
            raise ValueError(f"not a `python -m MODULE ...` command line: {argv}")
        self.args = argv
        self._p = context().Process(target=_run, args=(argv[2], argv[3:], env, log, name),
                                    name=name)
        self._p.start()
        self.pid: int = self._p.pid
        self.returncode: int | None = None

    def poll(self) -> int | None:
        if self.returncode is None and not self._p.is_alive():
            self.returncode = self._p.exitcode
        return self.returncode

    def wait(self, timeout: float | None = None) -> int:
        self._p.join(timeout)
        if self.poll() is None:
            raise subprocess.TimeoutExpired(self.args, timeout)
        return self.returncode

    def send_signal(self, sig: int) -> None:
        if self.poll() is None:
            try:
                os.kill(self.pid, sig)
            except ProcessLookupError:
                pass  # (it ended between the poll and the signal)

    def kill(self) -> None:
        self.send_signal(signal.SIGKILL)


def _run(module: str, args: list[str], env: dict[str, str], log: str, name: str) -> None:
    """In the forked stage: what an exec'd one would have had, then the command."""
    os.setpgid(0, 0)  # its own process group: a Ctrl-C reaches the daemon only
    # multiprocessing hands each child the write end of the server's keep-alive pipe (so
    # that it could start processes of its own through the server): a stage holding it
    # would keep the server alive after the daemon's death, and the server its stages
    # (their parent-death signal never fires). A stage starts no process: closed.
    from multiprocessing import forkserver

    alive = getattr(forkserver._forkserver, "_forkserver_alive_fd", None)
    if alive is not None:
        os.close(alive)
        forkserver._forkserver._forkserver_alive_fd = None
    from pipeline.stream.state import open_nofollow

    die_with_parent()  # (the server is the parent; it ends with the daemon)
    if _PRCTL is not None:
        _PRCTL(15, name.encode()[:15])  # PR_SET_NAME: `ps -o comm` names the stage
    fd = open_nofollow(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
    for target in (1, 2):
        os.dup2(fd, target)
    os.close(fd)
    # unbuffered, as PYTHONUNBUFFERED=1 gives an exec'd stage
    sys.stdout = io.TextIOWrapper(io.FileIO(1, "w", closefd=False), encoding="utf-8",
                                  write_through=True, line_buffering=True)
    sys.stderr = io.TextIOWrapper(io.FileIO(2, "w", closefd=False), encoding="utf-8",
                                  errors="backslashreplace", write_through=True,
                                  line_buffering=True)
    os.environ.clear()
    os.environ.update(env)
    # what `python -m MODULE ARGS` does, in this process (the daemon's stages:
    # MODULE = pipeline.cli, whose __main__ ends with sys.exit: the exit code stands)
    sys.argv = [module, *args]
    before = set(sys.modules) if env.get(LATE_IMPORTS_ENV) == "1" else None
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    finally:
        if before is not None:  # (a diagnostic: what the server's PRELOAD missed)
            late = sorted(set(sys.modules) - before - {"__main__"})
            print(f"forkstart: imported after the fork: {' '.join(late) or 'nothing'}",
                  file=sys.stderr)
