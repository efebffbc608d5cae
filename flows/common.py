"""What every flow shares: scenes with overrides, simulated captures cached on their inputs
(by Prefect, keyed on what their words depend on), run directories, one campaign at a time
per output directory, a bounded cache, and the report task (the only task that retries: it
does I/O only)."""

from __future__ import annotations

import contextlib
import copy
import datetime as dt
import fcntl
import hashlib
import json
import os
import re
import secrets
import shutil
import socket
import time
import tomllib
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path
from typing import Annotated, Any, Literal

from prefect import get_run_logger, task
from prefect.cache_policies import NO_CACHE, CachePolicy
from pydantic import Field

from pipeline.io.atomic import atomic_path
from pipeline.io.caldir import software_version
from pipeline.io.capture import Capture
from pipeline.offline.simulate import simulate_capture
from pipeline.report.report import write_report
from schemas.errors import TcspcError
from stages.models.scene import scene_from_dict
from stages.ranging import ESTIMATORS

ROOT = Path(__file__).resolve().parents[1]
#: a range estimator's name as a flow parameter: an unknown one is refused before the run
Estimator = Literal[ESTIMATORS]  # type: ignore[valid-type]
SCENES = ROOT / "scenes"

# Parameter types: Prefect validates a flow's parameters against its signature before the
# run starts (and a deployment's server refuses a run whose parameters break the schema),
# so a constraint written here is an error naming the parameter at run creation.
PositiveInt = Annotated[int, Field(gt=0)]
NonNegativeInt = Annotated[int, Field(ge=0)]
PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegativeFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]

#: how long a simulated capture may take before its task fails (Prefect's timeout_seconds)
SIMULATE_TIMEOUT_S = 3600


class FlowBusy(TcspcError, RuntimeError):
    """Another run holds the output directory's lock past the wait allowed."""


def scene_dict(name_or_path: str, **overrides) -> dict:
    """A scene file (a name under ``scenes/`` or a path) as a dict, with ``overrides``:
    ``n_pixels``, ``lux`` (every ambient source), ``distance_m`` and ``t_laser_win_ns``."""
    path = Path(name_or_path)
    if not path.suffix:
        path = SCENES / f"{name_or_path}.toml"
    raw = tomllib.loads(path.read_text())
    raw.setdefault("name", path.stem)
    raw = copy.deepcopy(raw)
    if overrides.get("n_pixels") is not None:
        n = int(overrides["n_pixels"])
        raw.setdefault("sensor", {})["n_pixels"] = n  # hot pixels beyond n drop out
        for t in raw.get("targets", []):
            t["pixels"] = [min(t["pixels"][0], n - 1), min(t["pixels"][1], n - 1)]
    if overrides.get("lux") is not None:
        for a in raw.get("ambient", []):
            a["lux"] = float(overrides["lux"])
    if overrides.get("distance_m") is not None:
        for t in raw.get("targets", []):
            t["distance_m"] = float(overrides["distance_m"])
    if overrides.get("t_laser_win_ns") is not None:
        raw.setdefault("gate", {})["t_laser_win_ns"] = float(overrides["t_laser_win_ns"])
    scene_from_dict(raw, str(path))  # validate now, naming the file
    return raw


@cache
def _model_source_hash() -> str:
    h = hashlib.sha256()
    for p in sorted((ROOT / "stages").rglob("*.py")):
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def code_version() -> str:
    """The software's version and its models' source: part of every cache key, so changed
    code never reuses a stale result."""
    return f"{software_version()}+{_model_source_hash()}"


def content_key(**inputs) -> str:
    """A cache key over ``inputs`` (JSON-able) and :func:`code_version`."""
    blob = json.dumps({**inputs, "code": code_version()}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


def capture_key(scene: dict, cycles: int, seed: int, chip_seed: int) -> str:
    """The cache key of a simulated capture: everything its words depend on, including
    the simulator's source, so a changed model never reuses a stale capture."""
    return content_key(scene=scene, cycles=cycles, seed=seed, chip_seed=chip_seed)


def file_identity(c) -> list:
    """What identifies a capture's data without reading it: each file's path, size and
    modification time (a daemon's journal run: every segment's)."""
    paths = getattr(c, "paths", None) or [Path(str(c))]
    out = []
    for p in paths:
        p = Path(p)
        st = p.stat() if p.exists() else None
        out.append([str(p.resolve()), st.st_size if st else None,
                    st.st_mtime_ns if st else None])
    return out


@dataclass
class Stored(CachePolicy):
    """Prefect's cache, keyed on a task's inputs and the code version, for a task whose
    result names a directory it writes: ``where(inputs)`` gives ``(key, directory)``, and
    the directory is part of the key (the result is a path into it). A cached result whose
    directory was pruned since is remade by :func:`remade_if_gone`."""

    where: Callable[[dict], tuple[str, Path]] | None = None

    def compute_key(self, task_ctx, inputs: dict[str, Any], flow_parameters: dict[str, Any],
                    **kwargs) -> str | None:
        key, path = self.where(inputs)
        place = hashlib.sha256(str(path.resolve()).encode()).hexdigest()[:12]
        return f"tcspc-{key}-{place}"


def remade_if_gone(result, path: str | Path, task_, *args):
    """``result`` of ``task_(*args)``, or the task run again past its cache when ``path``
    (what the result points at) is gone: a cache entry pruned after its result was
    recorded."""
    if Path(path).exists():
        return result
    get_run_logger().info("%s: cache entry gone; remaking it", path)
    return task_.with_options(refresh_cache=True)(*args)


def simulated(futures: list, args: list) -> list[str]:
    """The captures of ``simulate.submit(*a) for a in args``, each remade if pruned."""
    return [remade_if_gone(p, Path(p).with_suffix(".json"), simulate, *a)
            for p, a in zip([f.result() for f in futures], args, strict=True)]


def _capture_dir(inputs: dict) -> tuple[str, Path]:
    key = capture_key(inputs["scene"], inputs["cycles"], inputs.get("seed", 0),
                      inputs.get("chip_seed", 1))
    return key, Path(inputs["cache_dir"]) / key


def _simulate_name() -> str:
    from prefect.runtime import task_run

    p = task_run.parameters
    scene = p["scene"]
    lux = sorted({a.get("lux") for a in scene.get("ambient", []) if "lux" in a})
    light = f" at {lux[0]:g} lux" if len(lux) == 1 else ""
    dist = sorted({t.get("distance_m") for t in scene.get("targets", [])})
    where = f" at {dist[0]:g} m" if len(dist) == 1 and scene["name"] != "delay" else ""
    return f"simulate {scene['name']}{light}{where} ({p['cycles']:,} cycles)"


@task(cache_policy=Stored(where=_capture_dir), persist_result=True,
      task_run_name=_simulate_name, timeout_seconds=SIMULATE_TIMEOUT_S)
def simulate(scene: dict, cycles: int, cache_dir: str, seed: int = 0,
             chip_seed: int = 1) -> str:
    """A simulated capture of ``scene``; reused when one with the same inputs exists (the
    words depend only on them): Prefect shows the task Cached. Written atomically: a
    failure (or a kill) leaves no capture behind, only a temporary the next run removes."""
    key = capture_key(scene, cycles, seed, chip_seed)
    where = Path(cache_dir) / key
    path = where / scene["name"]
    if (where / f"{scene['name']}.json").exists():  # made, but its result not recorded
        Capture(path, strict=True)
        get_run_logger().info("reusing %s", path)
        return str(path)
    with atomic_path(where) as tmp:
        tmp.mkdir(parents=True)
        simulate_capture(scene_from_dict(scene, scene["name"]), cycles, tmp / scene["name"],
                         seed=seed, chip_seed=chip_seed)
    return str(path)


#: set by `tcspc flow serve` (its ``roots``): the folders a served run may use, joined by
#: os.pathsep; a run's paths elsewhere are refused (anyone who can create a run on the
#: server chooses its parameters)
ROOTS_ENV = "TCSPC_FLOW_ROOTS"


class OutsideRoots(TcspcError, ValueError):
    """A served flow run's path outside the roots its operator configured."""


def check_roots(**paths) -> None:
    """Refuse (one line naming the parameter) any of ``paths`` (name=path, None skipped)
    that does not resolve under a root of $TCSPC_FLOW_ROOTS; nothing when it is unset (a
    run started by `tcspc flow run`: the operator's own command line)."""
    roots = [Path(r).resolve() for r in os.environ.get(ROOTS_ENV, "").split(os.pathsep) if r]
    if not roots:
        return
    for name, path in paths.items():
        if path is not None and not any(Path(path).resolve().is_relative_to(r)
                                        for r in roots):
            raise OutsideRoots(f"{name} = {str(path)!r}: outside the roots this server "
                               f"takes paths under ({', '.join(map(str, roots))}); refused")


def new_run_dir(out: str | Path, flow: str, **inputs) -> Path:
    """``OUT/runs/<UTC time>-<random>``: one directory per run, never reused. ``flow.txt``
    names the flow and the Prefect flow run that wrote it. A served run's ``out`` or any of
    its ``inputs`` (parameter name=path, None skipped) outside the configured roots is
    refused (:func:`check_roots`) before anything is read or written."""
    check_roots(out=out, **inputs)
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    run = Path(out) / "runs" / f"{stamp}-{secrets.token_hex(3)}"
    run.mkdir(parents=True)
    info = flow_run_info()
    (run / "flow.txt").write_text(f"{flow}\n{info['id']} {info['name']}\n")
    return run


def run_namer(kind: str, sources: dict[str, str]) -> Callable[[], str]:
    """A ``flow_run_name`` for Prefect: ``<kind> <UTC date> <what it ran on>``, the source
    named by the first parameter of ``sources`` (name -> label) that is set, else the
    pixel count (``campaign 2026-11-27 128px``, ``sweep 2026-11-27 on captures``)."""

    def name() -> str:
        from prefect.runtime import flow_run

        p = flow_run.parameters
        src = next((label for key, label in sources.items() if p.get(key)),
                   f"{p.get('n_pixels', 128)}px")
        return f"{kind} {dt.datetime.now(dt.UTC):%Y-%m-%d} {src}"

    return name


def flow_run_info() -> dict:
    """The Prefect flow run this code runs in: id, name and where the UI shows it."""
    from prefect.runtime import flow_run

    return {"id": str(flow_run.id or ""), "name": flow_run.name or "",
            "url": flow_run.ui_url or ""}


# ---- one campaign at a time; what a killed run leaves behind ------------------------------

@contextlib.contextmanager
def exclusive(out: str | Path, wait_s: float, log=None,
              on_wait: Callable[[bool], None] | None = None) -> Iterator[list[dict]]:
    """Hold ``OUT/.lock`` (an advisory file lock, which the kernel releases when its holder
    dies, even by ``kill -9``), waiting up to ``wait_s`` for another run to finish. Yields
    the records (flow run id, name, pid, host) of the runs that died here without ending,
    for the caller to mark Crashed: the previous holder when it died holding the lock, and
    runs killed while they waited for it (a waiter says so in ``OUT/.lock.wait-PID`` while
    it waits). ``on_wait(True)`` is called when the wait starts, ``on_wait(False)`` when
    it ends (to show the run waiting, not Running). Raises :class:`FlowBusy` naming the
    holder on timeout."""
    path = Path(out) / ".lock"
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    me = {**flow_run_info(), "pid": os.getpid(), "host": socket.gethostname()}
    waiting = path.with_name(f".lock.wait-{os.getpid()}")
    try:
        deadline, said = time.monotonic() + wait_s, False
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                holder = _read_holder(fd)
                if time.monotonic() >= deadline:
                    raise FlowBusy(f"{out} is busy: run {holder.get('name', '?')} (pid "
                                   f"{holder.get('pid', '?')} on {holder.get('host', '?')}) "
                                   f"still holds it after {wait_s:g} s") from None
                if not said:
                    waiting.write_text(json.dumps(me))
                    if log:
                        log.info("waiting for run %s (pid %s) to release %s",
                                 holder.get("name", "?"), holder.get("pid", "?"), out)
                    if on_wait:
                        on_wait(True)
                    said = True
                time.sleep(0.2)
        waiting.unlink(missing_ok=True)
        if said and on_wait:
            on_wait(False)
        before = _read_holder(fd)
        dead = ([before] if before.get("id") else []) + _dead_waiters(path, me["host"])
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps({**me, "since": dt.datetime.now(dt.UTC).isoformat(
            timespec="seconds")}).encode(), 0)
        try:
            yield dead
        finally:
            os.ftruncate(fd, 0)  # released cleanly: nobody to mark crashed
    finally:
        waiting.unlink(missing_ok=True)
        os.close(fd)  # releases the lock


#: the name of the (Running) state a flow run shows while it waits for the lock
AWAITING_LOCK = "AwaitingLock"


def show_waiting(waiting: bool) -> None:
    """The current flow run's state named ``AwaitingLock`` while it waits for an output
    directory's lock, back to ``Running`` when it holds it (both of type Running: the
    run is alive and counts against its timeout; the name says what it does). Outside a
    flow run, or when the API refuses, nothing."""
    from prefect.client.schemas.objects import StateType
    from prefect.runtime import flow_run
    from prefect.states import State

    if not flow_run.id:
        return
    from prefect import get_client

    name = AWAITING_LOCK if waiting else "Running"
    with contextlib.suppress(Exception), get_client(sync_client=True) as client:
        client.set_flow_run_state(flow_run.id, State(
            type=StateType.RUNNING, name=name,
            message="waiting for another run to release the output directory's lock"
            if waiting else None), force=True)


def tag_run(*tags: str) -> None:
    """Add ``tags`` to the current flow run (what the UI filters on and automations match
    as ``prefect.tag.<tag>``); outside a flow run, nothing."""
    from prefect.runtime import flow_run

    if not flow_run.id:
        return
    from prefect import get_client

    with get_client(sync_client=True) as client:
        fr = client.read_flow_run(flow_run.id)
        client.update_flow_run(fr.id, tags=sorted({*fr.tags, *tags}))


def _dead_waiters(lock: Path, host: str) -> list[dict]:
    """The records of runs on this host that were killed while waiting for ``lock``
    (their ``.lock.wait-PID`` left behind, their process gone), removed as they are read."""
    from pipeline.view.status import pid_alive

    dead = []
    for p in lock.parent.glob(".lock.wait-*"):
        try:
            rec = json.loads(p.read_text())
        except (OSError, ValueError):
            rec = {}
        if rec.get("host", host) == host and pid_alive(rec.get("pid")) is False:
            p.unlink(missing_ok=True)
            if rec.get("id"):
                dead.append({**rec, "waiting": True})
    return dead


def _read_holder(fd: int) -> dict:
    try:
        return json.loads(os.pread(fd, 4096, 0) or b"{}")
    except ValueError:
        return {}


def mark_crashed(run_id: str, why: str) -> bool:
    """Mark the flow run ``run_id`` and its unfinished task runs Crashed (when the API
    still shows them running: a process killed outright never says so itself). A flow run
    Prefect already marked final (``serve``'s runner marks its killed child Crashed) still
    has its task runs marked: they would show Running forever. True when something was
    marked."""
    if not run_id:
        return False
    from uuid import UUID

    from prefect import get_client
    from prefect.client.schemas.filters import FlowRunFilter, TaskRunFilter
    from prefect.exceptions import ObjectNotFound
    from prefect.states import Crashed

    with get_client(sync_client=True) as client:
        try:
            fr = client.read_flow_run(UUID(run_id))
        except (ObjectNotFound, ValueError):
            return False
        if fr.state is None:
            return False
        marked = False
        tasks = client.read_task_runs(flow_run_filter=FlowRunFilter(id={"any_": [fr.id]}),
                                      task_run_filter=TaskRunFilter())
        for t in tasks:
            if t.state is not None and not t.state.is_final():
                client.set_task_run_state(t.id, Crashed(message=why), force=True)
                marked = True
        if not fr.state.is_final():
            client.set_flow_run_state(fr.id, Crashed(message=why), force=True)
            marked = True
    return marked


_LEFTOVER = re.compile(r"^\..+\.(tmp|old)-(\d+)$|^\..+\.link-[0-9a-f]+$")


def clean_leftovers(*dirs: str | Path, log=None) -> list[str]:
    """Remove what killed runs left in ``dirs``: atomic writes' temporaries
    (``.NAME.tmp-PID``, ``.NAME.old-PID``) whose process is gone, and stray links. Returns
    what was removed."""
    from pipeline.view.status import pid_alive

    gone = []
    for d in dirs:
        d = Path(d)
        if not d.is_dir():
            continue
        for p in d.iterdir():
            m = _LEFTOVER.match(p.name)
            if not m or (m.group(2) and pid_alive(int(m.group(2)))):
                continue
            if p.is_dir() and not p.is_symlink():
                shutil.rmtree(p, ignore_errors=True)
            else:
                p.unlink(missing_ok=True)
            gone.append(str(p))
    if log and gone:
        log.info("removed %d leftover(s) of killed runs: %s", len(gone), ", ".join(gone))
    return gone


def prune_cache(cache_dir: str | Path, max_gb: float, max_age_days: float,
                keep: set[str] = frozenset(), log=None) -> list[str]:
    """Bound the capture cache: drop entries last used more than ``max_age_days`` ago, then
    the least recently used until the rest fits in ``max_gb``; never one in ``keep`` (this
    run's). An entry is a directory under ``cache_dir`` (its mtime: when last used)."""
    d = Path(cache_dir)
    if not d.is_dir():
        return []
    entries = []
    for p in d.iterdir():
        if p.name.startswith(".") or not p.is_dir():
            continue
        size = sum(f.stat().st_size for f in p.rglob("*") if f.is_file())
        entries.append((p.stat().st_mtime, size, p))
    entries.sort()  # oldest first
    now, total = time.time(), sum(e[1] for e in entries)
    dropped = []
    for mtime, size, p in entries:
        if p.name in keep:
            continue
        if now - mtime > max_age_days * 86400 or total > max_gb * 1e9:
            shutil.rmtree(p, ignore_errors=True)
            total -= size
            dropped.append(p.name)
    if log and dropped:
        log.info("cache %s: dropped %d entr%s (older than %g days or over %g GB)", d,
                 len(dropped), "y" if len(dropped) == 1 else "ies", max_age_days, max_gb)
    return dropped


def touch(path: str | Path) -> None:
    """Mark a cache entry used now (what :func:`prune_cache` orders by)."""
    with contextlib.suppress(OSError):
        os.utime(path)


@task(retries=2, retry_delay_seconds=1, cache_policy=NO_CACHE)
def report(path: str, title: str, sections: list[tuple[str, str]]) -> str:
    """Write a run's Markdown report atomically (I/O only, so it may retry)."""
    return str(write_report(path, title, sections))
