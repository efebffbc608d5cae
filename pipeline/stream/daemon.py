"""``tcspc daemon``: the whole stream graph from a TOML topology, under a supervisor.

    source (sim | capture | udp) --TDC ranges--> histogram x workers --> range --> sink

Every stage is its own process (``tcspc stage ...``), so the graph can also be started by
hand across hosts. The supervisor

- starts the stages (sink first, source last), logs each to ``STATE/logs/NAME.log``;
- restarts a stage that dies, after an exponential backoff (``restart_backoff_s`` doubling
  per restart in the window, up to ``restart_backoff_max_s``), at most ``restarts`` times
  per stage in any ``restart_window_s``: the source resumes after what its journal holds,
  a histogram worker from its checkpoint and the journal;
- ends a stage whose upstream has finished but whose stop message was lost with a killed
  process (SIGTERM: it drains what is in flight, then finishes);
- collects the stages' heartbeats (PUB/SUB) into ``STATE/status.json`` once a second, for
  ``tcspc status``;
- at the end reconciles the datasets with the journal: a measurement lost in flight with a
  killed range or sink stage is recomputed from the journaled words (the same code, the
  same numbers), then writes the run's accounting beside the datasets.

The topology file (all keys but ``[source]`` optional)::

    [daemon]
    state = "data/daemon"        # journal/, checkpoints/, quarantine/, logs/, status.json
    run = "street"               # run id (default: the source's name and the UTC time)
    restarts = 10                # per stage in any restart_window_s; one more death in the
                                 # window and the daemon stops the graph and fails
    restart_window_s = 600       # the budget's window (a stage that dies once an hour for
                                 # a weekend is restarted every time)
    restart_backoff_s = 0.5      # wait before a restart, doubling with each restart in
    restart_backoff_max_s = 30   # the window, up to this
    journal_keep_gb = 50         # prune the oldest consumed segments beyond this (default:
                                 # keep all; a week-long run needs a bound)
    journal_compression = "zstd" # zstd (default: ~6 % of the raw bytes in photon-starving
                                 # light; `zstd -d` gives the raw capture) or "none"
    metrics = "ipc://..."        # default ipc://STATE/sock/metrics
    hwm = 4                      # ZeroMQ high-water mark, messages per socket
    curve = "auto"               # ZeroMQ CURVE (keys in STATE/curve): "auto" turns it on
                                 # when any endpoint is tcp:// to a non-loopback address;
                                 # true / false force it

    [source]
    kind = "sim"                 # sim | capture | udp
    scene = "scenes/street.toml" # sim: scene, cycles, seed, chip_seed, rate (words/s)
    capture = "data/raw/street"  # capture: the capture to replay, rate, repeat (times)
    bind = "127.0.0.1:9000"      # udp: where to listen, idle (s) to end the run

    [histogram]
    workers = 2                  # fan-out by TDC range
    measurement_cycles = 20000   # one histogram (and range) per this many cycles
    calibration = "data/calibration/current"   # artifact bounds (else none are applied)
    n_tdc = 128                  # udp only (sim and capture know theirs)

    [range]                      # leave out: histograms only
    calibration = "data/calibration/current"
    estimator = "ml"

    [sink]
    out = "data/stream"

Endpoints default to ``ipc://STATE/sock/NAME``; give ``endpoint`` (or ``endpoints``, one
per worker) in a section to use ``tcp://`` instead.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import signal
import subprocess
import sys
import threading
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import zmq

from pipeline.io.atomic import atomic_path
from pipeline.stream.wire import TOKEN_ENV
from schemas.errors import TcspcError

SOURCE_KINDS = ("sim", "capture", "udp")
GRACE_S = 3.0  # after its upstream finished, a stage gets this long to stop by itself


class TopologyError(TcspcError, ValueError):
    """A topology file that cannot run (names the file, the key and the problem)."""


@dataclass
class Topology:
    path: str
    state: Path
    run: str
    restarts: int
    metrics: str
    hwm: int
    source: dict
    histogram: dict
    range: dict | None
    sink: dict
    n_tdc: int
    journal_keep_gb: float | None = None
    journal_compression: str = "zstd"
    restart_window_s: float = 600.0
    restart_backoff_s: float = 0.5
    restart_backoff_max_s: float = 30.0
    curve: str | bool = "auto"

    def endpoints(self) -> list[str]:
        """Every endpoint of the graph (for the CURVE decision)."""
        eps = [self.metrics, self.endpoint(self.sink, "sink")]
        eps += [self.endpoint(self.histogram, f"histogram-{i}", i)
                for i in range(self.workers)]
        if self.range:
            eps.append(self.endpoint(self.range, "range"))
        return eps

    @property
    def curve_on(self) -> bool:
        from pipeline.stream.curve import needs_curve

        return self.curve is True or (self.curve == "auto" and needs_curve(self.endpoints()))
    date: str = field(default_factory=lambda: dt.date.today().isoformat())

    @property
    def workers(self) -> int:
        return int(self.histogram.get("workers", 1))

    def endpoint(self, section: dict, name: str, i: int | None = None) -> str:
        if i is not None and "endpoints" in section:
            return section["endpoints"][i]
        if "endpoint" in section and i is None:
            return section["endpoint"]
        return f"ipc://{self.state.resolve()}/sock/{name}"


_KNOWN = {
    "daemon": {"state", "run", "restarts", "metrics", "hwm", "journal_keep_gb",
               "journal_compression", "restart_window_s", "restart_backoff_s",
               "restart_backoff_max_s", "curve"},
    "source": {"kind", "scene", "cycles", "seed", "chip_seed", "rate", "capture", "bind",
               "idle", "n_tdc", "repeat", "reorder_window", "max_jump_cycles"},
    "histogram": {"workers", "measurement_cycles", "calibration", "n_tdc", "endpoints"},
    "range": {"calibration", "estimator", "endpoint"},
    "sink": {"out", "endpoint"},
}


def load_topology(path: str | Path | None, run: str | None = None,
                  overrides: dict | None = None) -> Topology:
    """Read and check a topology file (None: the embedded default, the street scene)."""
    where = str(path) if path else "<default topology>"
    if path:
        try:
            raw = tomllib.loads(Path(path).read_text())
        except FileNotFoundError:
            raise TopologyError(f"{path}: topology file not found") from None
        except tomllib.TOMLDecodeError as exc:
            raise TopologyError(f"{path}: not valid TOML: {exc}") from None
    else:
        raw = default_topology()
    for key, sub in (overrides or {}).items():
        raw.setdefault(key, {}).update(sub)
    unknown = sorted(set(raw) - set(_KNOWN))
    if unknown:
        raise TopologyError(f"{where}: unknown sections {unknown}; known: {sorted(_KNOWN)}")
    for sec, keys in _KNOWN.items():
        extra = sorted(set(raw.get(sec, {})) - keys)
        if extra:
            raise TopologyError(f"{where} [{sec}]: unknown keys {extra}; known: {sorted(keys)}")
    d, src = raw.get("daemon", {}), raw.get("source")
    if not src:
        raise TopologyError(f"{where}: a [source] section is needed")
    kind = src.get("kind")
    if kind not in SOURCE_KINDS:
        raise TopologyError(f"{where} [source] kind {kind!r}: use one of {SOURCE_KINDS}")
    need = {"sim": "scene", "capture": "capture", "udp": "bind"}[kind]
    if need not in src:
        raise TopologyError(f"{where} [source]: kind {kind!r} needs {need!r}")
    hist = dict(raw.get("histogram", {}))
    n_tdc = _source_n_tdc(src, hist, where)
    workers = int(hist.get("workers", 1))
    if not 1 <= workers <= n_tdc:
        raise TopologyError(f"{where} [histogram] workers = {workers}: use 1..{n_tdc}")
    if "endpoints" in hist and len(hist["endpoints"]) != workers:
        raise TopologyError(f"{where} [histogram]: {len(hist['endpoints'])} endpoints for "
                            f"{workers} workers")
    rng = raw.get("range")
    if rng is not None and "calibration" not in rng:
        raise TopologyError(f"{where} [range]: needs a calibration directory")
    for sec in (hist, rng or {}):
        cal = sec.get("calibration")
        if cal and not (Path(cal) / "tdc.parquet").exists():
            raise TopologyError(f"{where}: calibration {cal!r} is not a calibration directory "
                                "(run `tcspc flow run calibration_campaign` first)")
    state = Path(d.get("state", "data/daemon"))
    run = run or d.get("run") or (
        f"{Path(src.get('scene') or src.get('capture') or 'udp').stem}-"
        f"{dt.datetime.now(dt.UTC).strftime('%Y%m%dT%H%M%SZ')}")
    metrics = d.get("metrics") or f"ipc://{state.resolve()}/sock/metrics"
    for ep in [metrics, *(hist.get("endpoints") or [])]:
        _check_endpoint(ep, where)
    from pipeline.stream.wire import ID_PATTERN

    if not ID_PATTERN.fullmatch(run):
        raise TopologyError(f"{where}: run id {run!r}: use 1..64 of [A-Za-z0-9._-] (it "
                            "becomes a directory name)")
    budget = {k: float(d.get(k, default)) for k, default in (
        ("restart_window_s", 600.0), ("restart_backoff_s", 0.5),
        ("restart_backoff_max_s", 30.0))}
    if any(v < 0 for v in budget.values()) or int(d.get("restarts", 10)) < 0:
        raise TopologyError(f"{where} [daemon]: restarts and restart times must be >= 0")
    return Topology(where, state, run, int(d.get("restarts", 10)), metrics,
                    int(d.get("hwm", 4)), src, hist, rng,
                    raw.get("sink", {"out": "data/stream"}), n_tdc,
                    float(d["journal_keep_gb"]) if "journal_keep_gb" in d else None,
                    _journal_compression(d.get("journal_compression", "zstd"), where),
                    **budget, curve=_curve(d.get("curve", "auto"), where))


def _curve(value, where: str) -> str | bool:
    if value not in ("auto", True, False):
        raise TopologyError(f"{where}: [daemon] curve must be \"auto\", true or false, "
                            f"found {value!r}")
    return value


def _journal_compression(name, where: str) -> str:
    if name not in ("zstd", "none"):
        raise TopologyError(f"{where}: [daemon] journal_compression must be \"zstd\" or "
                            f"\"none\", found {name!r}")
    return name


def _check_endpoint(ep: str, where: str) -> None:
    if not ep.startswith(("ipc://", "tcp://", "inproc://")):
        raise TopologyError(f"{where}: endpoint {ep!r}: use ipc://PATH or tcp://HOST:PORT")


def _source_n_tdc(src: dict, hist: dict, where: str) -> int:
    if src["kind"] == "sim":
        from stages.models.scene import load_scene

        return load_scene(src["scene"]).sensor.n_pixels
    if src["kind"] == "capture":
        from pipeline.io.capture import Capture

        return Capture(src["capture"]).meta.n_tdc
    n = src.get("n_tdc") or hist.get("n_tdc")
    if not n:
        raise TopologyError(f"{where}: a udp source needs n_tdc (in [source] or [histogram])")
    return int(n)


def default_topology() -> dict:
    root = Path(__file__).resolve().parents[2]
    return {"daemon": {"state": "data/daemon"},
            "source": {"kind": "sim", "scene": str(root / "scenes" / "street.toml"),
                       "cycles": 100_000, "seed": 1},
            "histogram": {"workers": 2, "measurement_cycles": 20_000},
            "sink": {"out": "data/stream"}}


# ------------------------------------------------------------------------- the graph

@dataclass
class Proc:
    name: str
    argv: list[str]
    upstream: list[str]
    popen: subprocess.Popen | None = None
    restarts: int = 0
    finished: bool = False
    restart_times: list[float] = field(default_factory=list)  #: within the budget window
    restart_at: float | None = None   #: a restart waiting out its backoff
    exit_codes: list[int] = field(default_factory=list)
    upstream_done_at: float | None = None
    last_received: int | None = None
    terminated: bool = False


def _tcspc(*args) -> list[str]:
    return [sys.executable, "-m", "pipeline.cli", *map(str, args)]


def tdc_ranges(topo: Topology) -> list[tuple[int, int]]:
    from pipeline.stream.fanout import equal_ranges

    return equal_ranges(topo.n_tdc, topo.workers)


def build(topo: Topology) -> list[Proc]:
    """The stage processes of the topology, sink first."""
    st, run = topo.state, topo.run
    journal, ckpt, quar = st / "journal", st / "checkpoints" / run, st / "quarantine" / run
    m = ("--metrics", topo.metrics)
    ranges = tdc_ranges(topo)
    hist_eps = [topo.endpoint(topo.histogram, f"histogram-{i}", i) for i in range(len(ranges))]
    sink_ep = topo.endpoint(topo.sink, "sink")
    after_hist = sink_ep
    hist_names = [f"histogram-{i}" for i in range(len(ranges))]

    def accept(*names):  # the step ids a stage takes messages from
        return [x for n in names for x in ("--accept", n)]

    procs = [Proc("sink", _tcspc("stage", "sink", "--pull", sink_ep, "--out", topo.sink["out"],
                                 "--quarantine", quar / "sink", "--workers",
                                 1 if topo.range else len(ranges), *m,
                                 *accept(*(["range"] if topo.range else []), *hist_names)),
                  ["range"] if topo.range else [f"histogram-{i}" for i in range(len(ranges))])]
    if topo.range:
        after_hist = topo.endpoint(topo.range, "range")
        procs.append(Proc("range", _tcspc(
            "stage", "range", "--pull", after_hist, "--push", sink_ep, "--calibration",
            topo.range["calibration"], "--estimator", topo.range.get("estimator", "ml"),
            "--workers", len(ranges), "--quarantine", quar / "range", *m,
            *accept(*hist_names)),
            [f"histogram-{i}" for i in range(len(ranges))]))
    mc = topo.histogram.get("measurement_cycles")
    cal = topo.histogram.get("calibration")
    for i, (a, b) in enumerate(ranges):
        procs.append(Proc(f"histogram-{i}", _tcspc(
            "stage", "histogram", "--pull", hist_eps[i], "--push", after_hist,
            "--n-tdc", topo.n_tdc, "--tdc-range", f"{a}:{b}",
            *(("--measurement-cycles", mc) if mc else ()),
            *(("--calibration", cal) if cal else ()),
            "--quarantine", quar / f"histogram-{i}", "--checkpoint", ckpt / f"histogram-{i}.npz",
            "--journal", journal, "--run", run, "--name", f"histogram-{i}",
            "--date", topo.date, *m, *accept("source", "ingest")), ["source"]))
    src = topo.source
    common = [*(x for ep in hist_eps for x in ("--push", ep)), "--run", run,
              "--journal", journal, "--journal-compression", topo.journal_compression,
              "--split", ",".join(f"{a}:{b}" for a, b in ranges),
              "--date", topo.date, *m]
    if src["kind"] == "sim":
        argv = _tcspc("stage", "source-sim", src["scene"], "--cycles",
                      src.get("cycles", 40_000), "--seed", src.get("seed", 0), "--chip-seed",
                      src.get("chip_seed", 1), *common,
                      *(("--rate", src["rate"]) if src.get("rate") else ()))
    elif src["kind"] == "capture":
        argv = _tcspc("stage", "source-capture", src["capture"], *common,
                      "--repeat", src.get("repeat", 1),
                      *(("--rate", src["rate"]) if src.get("rate") else ()))
    else:
        argv = _tcspc("stage", "ingest-udp", "--bind", src["bind"], *common, "--quarantine",
                      quar / "ingest", *(("--idle", src["idle"]) if src.get("idle") else ()),
                      "--n-tdc", topo.n_tdc,
                      *(x for k in ("reorder_window", "max_jump_cycles") if k in src
                        for x in (f"--{k.replace('_', '-')}", src[k])))
    procs.append(Proc("source", argv, []))
    return procs


def _die_with_parent() -> None:
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


def run_token(state: Path, run: str) -> tuple[Path, str]:
    """The run's token: random, in ``STATE/tokens/RUN.token`` (mode 0600, its directory
    0700), made once per run and kept (a restarted daemon's stages and the old ones agree).
    Every stage puts it in the headers it sends and checks it in those it takes."""
    import secrets

    d = state / "tokens"
    d.mkdir(parents=True, exist_ok=True)
    os.chmod(d, 0o700)
    path = d / f"{run}.token"
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        os.chmod(path, 0o600)
        token = path.read_text().strip()
        if len(token) >= 32:
            return path, token
        fd = os.open(path, os.O_WRONLY | os.O_TRUNC, 0o600)  # empty or cut short: anew
    token = secrets.token_hex(32)
    with os.fdopen(fd, "w") as fh:
        fh.write(token + "\n")
    return path, token


def check_record(rec: dict, token: str | None) -> bool:
    """A heartbeat record that carries the run's token (any record when none is set)."""
    import hmac

    if token is None:
        return True
    got = rec.get("token")
    return isinstance(got, str) and hmac.compare_digest(got.encode(), token.encode())


class Supervisor:
    def __init__(self, topo: Topology, log=print, poll_s: float = 0.2):
        self.topo, self.log, self.poll_s = topo, log, poll_s
        self.procs = build(topo)
        self.by_name = {p.name: p for p in self.procs}
        self.stop = threading.Event()
        self.metrics: dict[str, dict] = {}
        self.started = time.time()
        self.failed: str | None = None
        self.pruned = 0
        self._spans = None
        self.forged_heartbeats = 0
        self._status_failing = False
        for d in ("logs", "sock", "journal", f"checkpoints/{topo.run}"):
            (topo.state / d).mkdir(parents=True, exist_ok=True)
        self.token_file, self.token = run_token(topo.state, topo.run)
        self.curve_dir = None
        if topo.curve_on:
            from pipeline.stream.curve import ensure_keys

            self.curve_dir = ensure_keys(topo.state)

    # -------------------------------------------------------------- processes
    def _start(self, p: Proc) -> None:
        log = open(self.topo.state / "logs" / f"{p.name}.log", "ab")
        try:
            log.write(f"--- {dt.datetime.now(dt.UTC).isoformat()} start "
                      f"(restart {p.restarts}): {' '.join(p.argv)}\n".encode())
            log.flush()
        except OSError:
            pass  # a full state disk: the stage starts all the same
        # the run's token by file (never on a command line, where `ps` shows it)
        env = {**os.environ, "PYTHONUNBUFFERED": "1", TOKEN_ENV: str(self.token_file)}
        if self.curve_dir is not None:
            from pipeline.stream.curve import CURVE_ENV

            env[CURVE_ENV] = str(self.curve_dir)
        p.popen = subprocess.Popen(p.argv, stdout=log, stderr=subprocess.STDOUT, env=env,
                                   preexec_fn=_die_with_parent)
        log.close()

    def _check(self) -> bool:
        """One supervision step; True when the graph has finished."""
        now = time.time()
        for p in self.procs:
            if p.finished or p.popen is None:
                continue
            code = p.popen.poll()
            if code is None:
                if p.upstream and all(self.by_name[u].finished for u in p.upstream):
                    got = self.metrics.get(p.name, {}).get("received")
                    if p.upstream_done_at is None or got != p.last_received:
                        p.upstream_done_at = now  # still taking messages: not stuck
                        p.last_received = got
                    if now - p.upstream_done_at > GRACE_S and not p.terminated:
                        # its stop was lost with a killed process: let it drain and finish
                        self.log(f"{p.name}: upstream finished and nothing taken for "
                                 f"{GRACE_S:.0f} s; SIGTERM (it drains, then finishes)")
                        p.popen.send_signal(signal.SIGTERM)
                        p.terminated = True
                continue
            if p.restart_at is not None:  # dead, its restart waiting out the backoff
                if self.stop.is_set() and p.name == "source":
                    p.finished, p.restart_at = True, None  # shutting down: no new source
                elif now >= p.restart_at:
                    p.restart_at = None
                    self._start(p)
                continue
            p.exit_codes.append(code)
            if code == 0 or (p.terminated and code == -signal.SIGTERM):
                # (a SIGTERM we sent that landed as the process was already exiting, past
                # its handler, still means "finished as asked")
                p.finished = True
                self.log(f"{p.name}: finished")
                continue
            if self.stop.is_set() and p.name == "source":
                p.finished = True  # shutting down: the run ends here, no new source
                self.log(f"{p.name}: ended (exit {code}) during shutdown")
                continue
            p.restart_times = [t for t in p.restart_times
                               if now - t < self.topo.restart_window_s]
            if len(p.restart_times) >= self.topo.restarts:
                self.failed = (f"{p.name} died (exit {code}) {len(p.restart_times) + 1} "
                               f"times within {self.topo.restart_window_s:.0f} s; giving up "
                               f"(see {self.topo.state / 'logs' / (p.name + '.log')})")
                self.log(self.failed)
                return True
            backoff = min(self.topo.restart_backoff_max_s,
                          self.topo.restart_backoff_s * 2 ** len(p.restart_times))
            p.restart_times.append(now)
            p.restarts += 1
            p.terminated, p.upstream_done_at = False, None
            p.restart_at = now + backoff
            self.log(f"{p.name}: died (exit {code}); restart {p.restarts} in {backoff:.1f} s "
                     f"({len(p.restart_times)} of {self.topo.restarts} in "
                     f"{self.topo.restart_window_s:.0f} s)")
        return all(p.finished for p in self.procs)

    def shutdown(self) -> None:
        """Graceful stop: the source first (it ends the run cleanly), the rest drain."""
        src = self.by_name["source"]
        if src.popen and src.popen.poll() is None and not src.terminated:
            src.popen.send_signal(signal.SIGTERM)  # once: it ends the run after its batch
            src.terminated = True

    def kill_all(self) -> None:
        for p in self.procs:
            if p.popen and p.popen.poll() is None:
                p.popen.kill()
                p.popen.wait()

    # -------------------------------------------------------------- metrics
    def _collect(self) -> None:
        ctx = zmq.Context.instance()
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.SUBSCRIBE, b"")
        sub.setsockopt(zmq.LINGER, 0)
        from pipeline.stream import curve
        from pipeline.stream.stage import bind

        if self.curve_dir is not None:
            curve.serve(sub, self.curve_dir)
        bind(sub, self.topo.metrics)
        try:
            while not self.stop.is_set():
                if sub.poll(200):
                    try:
                        rec = json.loads(sub.recv())
                        if not check_record(rec, self.token):
                            self.forged_heartbeats += 1  # no token: not one of ours
                            continue
                        rec.pop("token", None)
                        prev = self.metrics.get(rec["stage"])
                        if prev and prev.get("pid") == rec.get("pid"):
                            dt_s = max(rec["t"] - prev["t"], 1e-6)
                            for k in ("words", "words_total"):
                                if k in rec and k in prev:
                                    rec["rate_words_s"] = (rec[k] - prev[k]) / dt_s
                        self.metrics[rec["stage"]] = rec
                    except (ValueError, KeyError, TypeError):
                        continue  # a malformed record is not worth a crash
        finally:
            sub.close()

    def status(self) -> dict:
        now = time.time()
        stages = {}
        for p in self.procs:
            m = dict(self.metrics.get(p.name, {}))
            alive = p.popen is not None and p.popen.poll() is None
            stages[p.name] = {
                "pid": p.popen.pid if p.popen else None, "alive": alive,
                "finished": p.finished, "restarts": p.restarts,
                "heartbeat_age_s": round(now - m["t"], 2) if "t" in m else None,
                "health": ("finished" if p.finished else
                           "restarting" if p.restart_at is not None else
                           "paused" if alive and m.get("state") == "paused" else
                           "down" if not alive else
                           "ok" if "t" in m and now - m["t"] < 5 else "silent"),
                **{k: v for k, v in m.items() if k not in ("stage", "pid", "t")}}
        depth = {}
        for p in self.procs:  # messages sent upstream and not yet taken (approximate)
            got = stages[p.name].get("received")
            sent = sum(stages[u].get("sent", 0) for u in p.upstream)
            if p.upstream and got is not None:
                depth[p.name] = max(0, sent - got)
        return {"run": self.topo.run, "topology": self.topo.path, "updated": now,
                "started": self.started, "state": "failed" if self.failed else "running",
                "forged_heartbeats": self.forged_heartbeats,
                "paused": {name: s.get("reason") for name, s in stages.items()
                           if s["health"] == "paused"},
                "stages": stages, "queue_depth": depth}

    def _write_status(self, extra: dict | None = None) -> None:
        try:
            with atomic_path(self.topo.state / "status.json") as tmp:
                tmp.write_text(json.dumps({**self.status(), **(extra or {})}, indent=1,
                                          default=str))
        except OSError as exc:  # a full state disk must not kill the supervisor
            if not self._status_failing:
                self.log(f"status.json not written: {exc}")
            self._status_failing = True
        else:
            self._status_failing = False

    def _consumed_word(self) -> int:
        """The run's word index every histogram worker has checkpointed past."""
        from pipeline.stream.stage import load_checkpoint

        least = None
        for i, (a, b) in enumerate(tdc_ranges(self.topo)):
            path = self.topo.state / "checkpoints" / self.topo.run / f"histogram-{i}.npz"
            try:
                st = load_checkpoint(path)
            except (OSError, ValueError):  # being replaced right now: try next time
                return 0
            if st is None:
                return 0
            cycles = int(st["counters"][2]) // (b - a)
            least = cycles if least is None else min(least, cycles)
        return (least or 0) * self.topo.n_tdc

    def _prune(self) -> None:
        if self.topo.journal_keep_gb is None:
            return
        from pipeline.stream.journal import IndexSpans, prune

        if self._spans is None:
            self._spans = IndexSpans(self.topo.state / "journal", self.topo.run)
        gone = prune(self.topo.state / "journal", self.topo.run,
                     int(self.topo.journal_keep_gb * 1e9), self._consumed_word(),
                     self._spans.update())
        self.pruned += len(gone)

    # -------------------------------------------------------------- run
    def run(self) -> dict:
        collector = threading.Thread(target=self._collect, daemon=True)
        collector.start()
        time.sleep(0.2)
        for p in self.procs:
            self._start(p)
        self.log(f"run {self.topo.run}: {len(self.procs)} stages started "
                 f"({self.topo.workers} histogram workers); state in {self.topo.state}")
        last = 0.0
        try:
            while not self._check():
                if self.stop.is_set():
                    self.shutdown()
                if time.time() - last > 1.0:
                    self._write_status()
                    self._prune()
                    last = time.time()
                time.sleep(self.poll_s)
        finally:
            if self.failed:
                self.kill_all()
            self.stop.set()
            collector.join(timeout=2)
        result = {"run": self.topo.run, "failed": self.failed,
                  "restarts": {p.name: p.restarts for p in self.procs if p.restarts},
                  "journal_segments_pruned": self.pruned}
        if not self.failed:
            try:
                result["reconciled"] = reconcile(self.topo)
                result["accounting"] = accounting(self.topo, self.metrics,
                                                  result["reconciled"])
            except Exception as exc:  # the run must end with a state, never "running"
                self.failed = f"reconciling the run failed: {type(exc).__name__}: {exc}"
                result["failed"] = self.failed
                self.log(self.failed)
        corrupt = (result.get("reconciled") or {}).get("corrupt_words", 0)
        self._write_status({"state": "failed" if self.failed else "finished",
                            "result": result,
                            **({"journal_corrupt_words": corrupt} if corrupt else {})})
        return result


# ------------------------------------------------------------------ reconcile, accounting

def _dataset_parts(out: Path, schema: str, run: str) -> dict[tuple[int, int], Path]:
    parts = {}
    for p in out.glob(f"{schema}/date=*/run={run}/part-*.parquet"):
        _, k, t = p.stem.split("-")
        parts[(int(k), int(t[1:]))] = p
    return parts


def reconcile(topo: Topology) -> dict:
    """Recompute from the journal every (measurement, TDC range) the datasets lack; a
    measurement is words [k M N, (k + 1) M N) of the run whatever happened to the stream,
    so the recomputed one is the one an uninterrupted run would have written."""
    from pipeline.stream.fanout import worker_reader
    from pipeline.stream.journal import pruned_words, read_range, run_end
    from pipeline.stream.stage import ParquetSink
    from stages.artifact import ArtifactBounds
    from stages.stream import HistogramCore

    journal = topo.state / "journal"
    total = run_end(journal, topo.run)
    if total is None:
        return {"checked": False, "why": "the journal has no end (the source did not finish)"}
    n = topo.n_tdc
    cycles = total // n
    mc = topo.histogram.get("measurement_cycles") or max(cycles, 1)
    n_meas = max(1, -(-cycles // mc))
    out = Path(topo.sink["out"])
    have_h = _dataset_parts(out, "histograms", topo.run)
    have_r = _dataset_parts(out, "ranges", topo.run) if topo.range else None
    bounds_all = None
    if topo.histogram.get("calibration"):
        from pipeline.io.caldir import read_bounds

        bounds_all = read_bounds(topo.histogram["calibration"], n)
    ranger = None
    if topo.range:
        from pipeline.io.caldir import load_calibration
        from pipeline.offline.ranging import RangeCore

        ranger = RangeCore(load_calibration(topo.range["calibration"]),
                           topo.range.get("estimator", "ml"))
    sink = ParquetSink(out)
    redone, unrecoverable, corrupt_meas = [], [], []
    corrupt_chunks: dict[int, list] = {}  # first word -> [first, words, reason]
    withheld = 0
    window_ns = None
    for (a, b) in tdc_ranges(topo):
        for k in range(n_meas):
            if (k, a) in have_h and (have_r is None or (k, a) in have_r):
                continue
            if pruned_words(journal, topo.run, k * mc * n, min((k + 1) * mc, cycles) * n):
                unrecoverable.append([k, a])  # its words were pruned (journal_keep_gb)
                continue
            bad = []
            for _ in read_range(journal, topo.run, k * mc * n, min((k + 1) * mc, cycles) * n,
                                lambda f, w, why, bad=bad: bad.append([f, w, why])):
                pass  # a measurement's words are checked whole before any is used
            if bad:
                # a corrupt chunk's words are never data: the measurement is withheld
                corrupt_meas.append([k, a])
                for c in bad:
                    corrupt_chunks[c[0]] = c
                if (k, a) not in have_h:  # (a histogram already written is classified)
                    withheld += (min((k + 1) * mc, cycles) - k * mc) * (b - a)
                continue
            bounds = (ArtifactBounds(bounds_all.n_min[a:b], bounds_all.n_max[a:b],
                                     bounds_all.source) if bounds_all else None)
            core = HistogramCore(b - a, bounds, tdc_offset=a,
                                 measurement_cycles=topo.histogram.get("measurement_cycles"))
            core.measurement = k
            w = b - a
            lo = k * mc * w
            hi = min((k + 1) * mc, cycles) * w
            core.next_word = lo
            if window_ns is None:
                window_ns = _journal_window_ns(journal, topo.run)
            gate = _journal_gate_ns(journal, topo.run)
            msgs = []
            for f, words in worker_reader(lambda s, e: read_range(journal, topo.run, s, e),
                                          n, (a, b))(lo, hi):
                msgs += core.process({"run": topo.run, "first_word": f, "seq": k,
                                      "t_laser_win_ns": gate, "window_ns": window_ns,
                                      "date": topo.date}, _words_batch(words))
            if hi < (k + 1) * mc * w:
                msgs += core.finish({"run": topo.run})
            for head, batch in msgs:
                sink.process(head, batch)
                if ranger is not None:
                    for h2, b2 in ranger.process(head, batch)[1:]:
                        sink.process(h2, b2)
            redone.append([k, a])
    return {"checked": True, "measurements": n_meas, "tdc_ranges": len(tdc_ranges(topo)),
            "recomputed": redone, "unrecoverable": unrecoverable, "corrupt": corrupt_meas,
            "corrupt_chunks": sorted(corrupt_chunks.values()),
            "corrupt_words": sum(c[1] for c in corrupt_chunks.values()),
            "withheld_words": withheld}


def _words_batch(words):
    import pyarrow as pa

    from schemas.words import RAW_WORDS

    return pa.record_batch([pa.array(words)], schema=RAW_WORDS.schema)


def _journal_meta(journal: Path, run: str) -> dict:
    for side in sorted(journal.glob(f"{run}-*.json")):
        return json.loads(side.read_text())
    return {}


def _journal_window_ns(journal: Path, run: str) -> float:
    return float(_journal_meta(journal, run).get("window_ns", 80.0))


def _journal_gate_ns(journal: Path, run: str) -> float:
    return float(_journal_meta(journal, run).get("t_laser_win_ns", 140.0))


def accounting(topo: Topology, metrics: dict[str, dict], reconciled: dict | None = None
               ) -> dict:
    """Words in (journaled) = hit + no_hit + artifact + invalid_phase + malformed (from the
    histograms dataset, each measurement once) + words withheld (measurements that a
    corrupt journal chunk kept from being recomputed: ``corrupt_words`` of them in the
    corrupt chunks themselves); messages and datagrams rejected by reason (quarantined) per
    stage; datagrams lost (sequence gaps), duplicated and late. Written to
    ``OUT/accounting/run=RUN.json``."""
    import polars as pl

    from pipeline.stream.journal import journaled_total, run_end
    from schemas.words import WORD_CLASSES

    out = Path(topo.sink["out"])
    parts = sorted(_dataset_parts(out, "histograms", topo.run).values())
    cols = [f"n_{c}" for c in WORD_CLASSES]
    classes = dict.fromkeys(WORD_CLASSES, 0)
    if parts:
        sums = pl.scan_parquet(parts).select([pl.col(c).sum() for c in cols]).collect()
        classes = {c: int(sums[f"n_{c}"][0]) for c in WORD_CLASSES}
    journaled = journaled_total(topo.state / "journal", topo.run)
    span = run_end(topo.state / "journal", topo.run) or 0
    rejected = {name: m.get("rejected", {}) for name, m in metrics.items() if m.get("rejected")}
    rec = reconciled or {}
    withheld = int(rec.get("withheld_words", 0))
    src = metrics.get("source", {})
    result = {"run": topo.run, "words_in": journaled, "classes": classes,
              "classified": sum(classes.values()),
              "corrupt": int(rec.get("corrupt_words", 0)), "withheld": withheld,
              "corrupt_measurements": rec.get("corrupt", []),
              "balanced": sum(classes.values()) + withheld == journaled,
              "rejected_messages": rejected,
              "lost_datagrams": src.get("lost_datagrams", 0),
              "duplicate_datagrams": src.get("duplicates", 0),
              "late_datagrams": src.get("late", 0),
              "quarantine_dropped": {name: m["quarantine_dropped"] for name, m in
                                     metrics.items() if m.get("quarantine_dropped")},
              "checkpoints_discarded": {name: m["checkpoints_discarded"] for name, m in
                                        metrics.items() if m.get("checkpoints_discarded")},
              "words_in_gaps": span - journaled,
              "measurements_files": len(parts)}
    path = out / "accounting" / f"run={topo.run}.json"
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(result, indent=1))
    result["path"] = str(path)
    return result
