"""``tcspc daemon``: the whole stream graph from a TOML topology, under a supervisor.

    source (sim | capture | udp) --TDC ranges--> histogram x workers --> range --> sink

Every stage is its own process (``tcspc stage ...``), so the graph can also be started by
hand across hosts. The daemon forks them from a server that imported their modules once
(``pipeline.stream.forkstart``; ``[daemon] fork_server = false``: a new interpreter each).
The supervisor

- starts the stages (sink first, source last), logs each to ``STATE/logs/NAME.log``;
- restarts a stage that dies, after an exponential backoff (``restart_backoff_s`` doubling
  per restart not yet earned back, up to ``restart_backoff_max_s``), within a restart
  budget that is a rate (``pipeline.stream.budget``: ``restarts`` back to back, one earned
  back per ``restart_refill_s``): the source resumes after what its journal holds, a
  histogram worker from its checkpoint and the journal;
- ends a stage whose upstream has finished but whose stop message was lost with a killed
  process (SIGTERM: it drains what is in flight, then finishes);
- collects the stages' heartbeats (PUB/SUB) into ``STATE/status.json`` once a second, for
  ``tcspc status``;
- at the end reconciles the datasets with the journal: a measurement lost in flight with a
  killed range or sink stage is recomputed from the journaled words (the same code, the
  same numbers), then writes the run's accounting beside the datasets.

The topology file (all keys but ``[source]`` optional; every key's type and range is
declared in ``pipeline.stream.topology``, and the whole file is checked before anything
starts, as are the state directory and the resources: ``pipeline.stream.state``)::

    [daemon]
    state = "data/daemon"        # journal/, checkpoints/, quarantine/, logs/, status.json
    run = "street"               # run id (default: the source's name and the UTC time)
    restarts = 10                # a stage's restart budget: 10 back to back; a death with
                                 # the budget spent stops the graph and fails the run
    restart_refill_s = 60        # one restart earned back per 60 s (a stage dying once a
                                 # minute for a week is restarted every time)
    restart_backoff_s = 0.5      # wait before a restart, doubling with each restart not
    restart_backoff_max_s = 30   # yet earned back, up to this
    heartbeat_deadline_s = 60    # a live stage with no heartbeat this long is frozen
                                 # (SIGSTOPped, wedged): SIGKILLed, restarted, counted
    journal_keep_gb = 50         # prune the oldest consumed segments beyond this (default:
                                 # keep all; a week-long run needs a bound)
    journal_compression = "zstd-nohit" # (default: ~7 % of the raw bytes in photon-starving
                                 # light; `tcspc journal export` gives the raw capture),
                                 # "zstd" (`zstd -d` gives it) or "none"
    metrics = "ipc://..."        # default ipc://STATE/sock/metrics
    hwm = 4                      # ZeroMQ high-water mark, messages per socket
    curve = "auto"               # ZeroMQ CURVE (keys in STATE/curve): "auto" turns it on
                                 # when any endpoint is tcp:// (loopback too: any local
                                 # account reaches it); true / false force it

    [source]
    kind = "sim"                 # sim | capture | udp | file
    scene = "scenes/street.toml" # sim: scene, cycles, seed, chip_seed, rate (words/s)
    capture = "data/raw/street"  # capture: the capture to replay, rate, repeat (times)
    bind = "127.0.0.1:9000"      # udp: where to listen, idle (s) to end the run;
    gate_ps = 140000             # udp: the run's gate and its first datagram's sequence
    first_seq = 0                # number (else a quorum of agreeing datagrams sets them)
    peers = ["192.168.1.10"]     # udp: the senders read, HOST or HOST:PORT (else the run
                                 # locks onto the sender of its reference)
    file = "run.ptu"             # file: a PTU T3 or LinoSPAD2 file, rate (records/s),
                                 # format (default: from the content), firmware; one
                                 # histogram worker, one measurement, no [range]
    wire = "sparse"              # sim, capture, udp: how words go to the workers: "sparse"
                                 # (the words that are not plain no_hit words; default) or
                                 # "words"

    [histogram]
    workers = 2                  # fan-out by TDC range
    measurement_cycles = 20000   # one histogram (and range) per this many cycles
    calibration = "data/calibration/current"   # artifact bounds (without one: a capture's
                                 # are estimated from it at start; sim and udp need it or
    artifacts = "count-as-hits"  # this, which counts their artifact words as hits)
    n_tdc = 128                  # udp only (sim and capture know theirs)

    [range]                      # leave out: histograms only
    calibration = "data/calibration/current"
    estimator = "ml"
    spatial = false              # true: ranged with the neighbours as the geometry's image
                                 # (geometry = ..., else [sink] geometry); the workers'
    hold = 8                     # parts of a measurement gathered first, this many held
                                 # (leave out: 2 hwm + 1 batches' measurements + 2 hwm)

    [sink]
    out = "data/stream"

    [view]                       # leave out: no web page; with it, `tcspc view` runs
    port = 5006                  # beside the graph (restarted if it dies, ended with the
    bind = "127.0.0.1"           # daemon): loopback by default, a token in the URL
    layout = "16x8"              # elsewhere (STATE/view.url); the array's columns x rows

    [metrics]                    # leave out: none; with it, Prometheus metrics on this port
    port = 9108                  # (127.0.0.1, or host = ...; a bearer token from
                                 # STATE/metrics.token): pipeline.stream.exporter
    [log]
    format = "json"              # JSON lines (ts, level, stage, msg); default "text"

The daemon publishes each status it writes on ``ipc://STATE/sock/status`` (PUB) for the
web page (``pipeline.stream.sidecar``). Under systemd (``Type=notify``) it sends READY=1,
WATCHDOG=1 from its supervision loop, STATUS= and STOPPING=1 (``pipeline.stream.notify``).

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
from dataclasses import dataclass, field
from pathlib import Path

import zmq

from pipeline.io.atomic import atomic_path
from pipeline.stream.bounds import bounds_file, ensure_bounds
from pipeline.stream.forkstart import die_with_parent
from pipeline.stream.journal import stream_ended
from pipeline.stream.reconcile import accounting, reconcile
from pipeline.stream.sidecar import Sidecar, status_pub, view_args
from pipeline.stream.topology import (
    GRACE_S,
    STARTUP_S,
    Topology,
    range_hold,
    spatial_geometry,
    tdc_ranges,
)
from pipeline.stream.wire import TOKEN_ENV

#: After a signal to the daemon, a stage whose upstream ended gets this long to stop by
#: itself before its SIGTERM (the whole stop stays within ~3 s)
STOP_GRACE_S = 0.5

# ------------------------------------------------------------------------- the graph


@dataclass
class Proc:
    name: str
    argv: list[str]
    upstream: list[str]
    popen: subprocess.Popen | None = None
    restarts: int = 0
    finished: bool = False
    budget: object = None   #: its RestartBudget (made at its first death)
    restart_at: float | None = None   #: a restart waiting out its backoff
    exit_codes: list[int] = field(default_factory=list)
    upstream_done_at: float | None = None
    last_received: tuple | None = None
    terminated: bool = False
    started_at: float = 0.0
    frozen: int = 0   #: times SIGKILLed for missing its heartbeat deadline (then restarted)


def _tcspc(*args) -> list[str]:
    return [sys.executable, "-m", "pipeline.cli", *map(str, args)]


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
                                 *accept(*(["range"] if topo.range else []), *hist_names),
                                 *_cloud_args(topo.sink)),
                  ["range"] if topo.range else [f"histogram-{i}" for i in range(len(ranges))])]
    if topo.range:
        after_hist = topo.endpoint(topo.range, "range")
        procs.append(Proc("range", _tcspc(
            "stage", "range", "--pull", after_hist, "--push", sink_ep, "--calibration",
            topo.range["calibration"], "--estimator", topo.range.get("estimator", "ml"),
            "--max-returns", topo.range.get("max_returns", 3),
            "--workers", len(ranges), "--quarantine", quar / "range", *m,
            *spatial_args(topo), *accept(*hist_names)),
            [f"histogram-{i}" for i in range(len(ranges))]))
    src = topo.source
    mc = topo.histogram.get("measurement_cycles")
    cal = topo.histogram.get("calibration")
    est = bounds_file(topo)  # no calibration, a capture: the capture's own (ensure_bounds)
    for i, (a, b) in enumerate(ranges):
        procs.append(Proc(f"histogram-{i}", _tcspc(
            "stage", "histogram", "--pull", hist_eps[i], "--push", after_hist,
            "--n-tdc", topo.n_tdc, "--tdc-range", f"{a}:{b}",
            *(("--measurement-cycles", mc) if mc else ()),
            *(("--calibration", cal) if cal else ()),
            *(("--bounds", est) if est else ()),
            "--quarantine", quar / f"histogram-{i}", "--checkpoint", ckpt / f"histogram-{i}.npz",
            "--journal", journal, "--run", run, "--name", f"histogram-{i}",
            "--date", topo.date, *m, *accept("source", "ingest"),
            *(("--instrument-file", src["file"], "--format", src["format"], "--firmware",
               src.get("firmware", "2212b")) if src["kind"] == "file" else ())), ["source"]))
    common = [*(x for ep in hist_eps for x in ("--push", ep)), "--run", run,
              "--journal", journal, "--journal-compression", topo.journal_compression,
              "--split", ",".join(f"{a}:{b}" for a, b in ranges),
              "--date", topo.date, *m]
    wire_form = ("--wire", src.get("wire") or "sparse")
    if src["kind"] == "sim":
        argv = _tcspc("stage", "source-sim", src["scene"], "--cycles",
                      src.get("cycles", 40_000), "--seed", src.get("seed", 0), "--chip-seed",
                      src.get("chip_seed", 1), *common, *wire_form,
                      *(("--rate", src["rate"]) if src.get("rate") else ()))
    elif src["kind"] == "file":
        argv = _tcspc("stage", "source-file", src["file"], *common, "--format", src["format"],
                      "--firmware", src.get("firmware", "2212b"),
                      *(("--rate", src["rate"]) if src.get("rate") else ()))
    elif src["kind"] == "capture":
        argv = _tcspc("stage", "source-capture", src["capture"], *common, *wire_form,
                      "--repeat", src.get("repeat", 1),
                      *(("--rate", src["rate"]) if src.get("rate") else ()))
    else:
        argv = _tcspc("stage", "ingest-udp", "--bind", src["bind"], *common, *wire_form,
                      "--quarantine",
                      quar / "ingest", *(("--idle", src["idle"]) if src.get("idle") else ()),
                      "--n-tdc", topo.n_tdc,
                      *(x for k in ("reorder_window", "max_jump_cycles", "gate_ps",
                                      "first_seq") if k in src
                        for x in (f"--{k.replace('_', '-')}", src[k])),
                      *(x for p in src.get("peers") or () for x in ("--peer", p)))
    procs.append(Proc("source", argv, []))
    return procs


def run_token(state: Path, run: str) -> tuple[Path, str]:
    """The run's token: random, in ``STATE/tokens/RUN.token`` (mode 0600, its directory
    0700), made once per run and kept (a restarted daemon's stages and the old ones agree).
    Every stage puts it in the headers it sends and checks it in those it takes."""
    from pipeline.stream.exporter import secret_token

    d = state / "tokens"
    d.mkdir(parents=True, exist_ok=True)
    os.chmod(d, 0o700)
    path = d / f"{run}.token"
    return path, secret_token(path)


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
        # the state is taken first (private, locked, no links), then every resource a stage
        # needs is probed: either fails here, with the reason, before anything is started
        from pipeline.stream.state import check_resources, open_state

        self.lock = open_state(topo.state)
        try:
            from pipeline.stream.runrecord import take

            # a resume: the run's partition, refused if what a measurement is changed
            self.record = take(topo)
            if self.record.get("state") == "finished":
                return  # a finished run started again: run() says so, nothing is redone
            check_resources(topo)
            from pipeline.stream.opsview import OpsView

            # totals, metrics server ([metrics]), systemd notifications (issue 38.8)
            self.ops = OpsView(topo, log)
            # what the run's words are classified with, said at start (the capture's own
            # bounds are estimated here, before any stage starts)
            self.bounds = ensure_bounds(topo, log)
        except Exception:
            if getattr(self, "ops", None) is not None:
                self.ops.close()  # (its port: nothing was started)
            self.lock.release()
            raise
        log(f"artifact bounds: {self.bounds}")
        self.procs = build(topo)
        self.by_name = {p.name: p for p in self.procs}
        self.stop = threading.Event()
        self.ended = threading.Event()  #: the graph has ended: the collector stops
        self._listening = threading.Event()  #: the collector's SUB is bound
        self.interrupted: str | None = None  #: the signal that stopped the run (SIGINT, ..)
        self.metrics: dict[str, dict] = {}
        self.started = time.time()
        self.failed: str | None = None
        self.pruned = 0
        self._durable = 0  #: measurements known to be on disk (see _durable_word)
        self._spans = None
        self.forged_heartbeats = 0
        self._status_failing = False
        self._paused: set[str] = set()  #: stages paused at the last status (logged)
        self._status_msg: bytes | None = None  #: the last status, for the status PUB
        args = view_args(topo)  # the web page's server ([view]), beside the graph
        self.view = None if args is None else Sidecar(
            Proc("view", _tcspc(*args), []), self._start, log, topo.state / "logs" / "view.log")
        for d in ("logs", "sock", "journal", f"checkpoints/{topo.run}"):
            (topo.state / d).mkdir(parents=True, exist_ok=True)
        self.token_file, self.token = run_token(topo.state, topo.run)
        self.curve_dir = None
        if topo.curve_on:
            from pipeline.stream.curve import ensure_keys

            self.curve_dir = ensure_keys(topo.state)

    def interrupt(self, signum: int) -> None:
        """A signal to the daemon: stop the run in order (it stays resumable)."""
        if not self.by_name["source"].finished:  # (after the source's end: nothing to stop)
            self.interrupted = self.interrupted or signal.Signals(signum).name
        self.stop.set()

    # -------------------------------------------------------------- processes
    def _start(self, p: Proc) -> None:
        from pipeline.stream.state import open_nofollow

        log = os.fdopen(open_nofollow(self.topo.state / "logs" / f"{p.name}.log",
                                      os.O_WRONLY | os.O_APPEND | os.O_CREAT), "ab")
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
        else:  # ([daemon] curve = false: the operator's choice, which a stage refuses alone)
            env["TCSPC_INSECURE"] = "1"
        p.started_at = time.time()
        if self.topo.fork_server and p.argv[1:3] == ["-m", "pipeline.cli"]:
            from pipeline.stream.forkstart import StageProcess

            log.close()  # (the stage opens it itself, the same checked way)
            p.popen = StageProcess(p.argv, env, str(self.topo.state / "logs" /
                                                    f"{p.name}.log"), p.name)
            return
        # its own process group: a Ctrl-C at the terminal reaches the daemon only, which
        # stops the graph in order (the source first, the rest drain)
        p.popen = subprocess.Popen(p.argv, stdout=log, stderr=subprocess.STDOUT, env=env,
                                   preexec_fn=die_with_parent, process_group=0)
        log.close()

    def _check(self) -> bool:
        """One supervision step; True when the graph has finished."""
        now = time.time()
        self._kill_frozen(now)
        for p in self.procs:
            if p.finished or p.popen is None:
                continue
            code = p.popen.poll()
            if code is None:
                if p.upstream and all(self.by_name[u].finished for u in p.upstream):
                    # progress: messages taken or words folded in (a restarted worker
                    # backfilling from the journal takes no message), or, blocked on a
                    # slower consumer, messages sent or the consumer taking any (it waits
                    # its turn: ended then, what it had not sent was lost to the stream),
                    # as this process incarnation reports them; one not heard from yet is
                    # starting up
                    m = self.metrics.get(p.name, {})
                    heard = m.get("pid") == p.popen.pid
                    got = ((m.get("received"), m.get("words_total"), m.get("sent"),
                            *(self.metrics.get(q.name, {}).get("received")
                              for q in self.procs if p.name in q.upstream
                              and m.get("state") == "blocked")) if heard else None)
                    starting = (not heard and now - p.started_at < STARTUP_S
                                and not self.stop.is_set())  # (a stop: nothing to wait on)
                    # a stage paused on a full disk is waiting, not stuck: ended now, what
                    # it holds would be written by the reconciliation onto the same disk
                    paused = heard and m.get("state") == "paused"
                    # one that reported "finished" has taken its stops and sent its own:
                    # it waits (bounded) for its consumer to hang up, and a SIGTERM there
                    # would cut that wait short (pipeline.stream.hangup)
                    ending = heard and m.get("state") == "finished"
                    if p.upstream_done_at is None or got != p.last_received or starting \
                            or paused or ending:
                        p.upstream_done_at = now  # still working: not stuck
                        p.last_received = got
                    grace = self._grace()
                    if now - p.upstream_done_at > grace and not p.terminated:
                        # its stop was lost with a killed process: let it drain and finish
                        self.log(f"{p.name}: upstream ended and nothing taken for "
                                 f"{grace:g} s; SIGTERM (it drains, then finishes)")
                        p.popen.send_signal(signal.SIGTERM)
                        p.terminated = True
                continue
            if p.restart_at is not None:  # dead, its restart waiting out the backoff
                if self.stop.is_set() and p.name == "source":
                    p.finished, p.restart_at = True, None  # shutting down: no new source
                elif now >= p.restart_at or self.stop.is_set():
                    # (a stop does not wait out the backoff: the source, stopping after
                    # its batch, waits on this stage's queue, and so would the stop)
                    p.restart_at = None
                    self._start(p)
                continue
            p.exit_codes.append(code)
            if code == 0 or (p.terminated and code == -signal.SIGTERM):
                # (a SIGTERM we sent that landed as the process was already exiting, past
                # its handler, still means "finished as asked")
                p.finished = True
                self.log(f"{p.name}: " + (f"stopped ({self.interrupted})" if self.interrupted
                                          else "finished"))
                continue
            if self.stop.is_set() and p.name == "source":
                p.finished = True  # shutting down: the run ends here, no new source
                self.log(f"{p.name}: ended (exit {code}) during shutdown")
                continue
            if p.name == "source" and stream_ended(self.topo.state / "journal",
                                                   self.topo.run):
                # it had journaled the stream's end (the journal is the truth, not a last
                # heartbeat the collector may have missed) and died after, lingering over
                # what it sent: a source restarted there would take up a run that has ended
                # (a UDP one waits for datagrams that never come); the workers end on the
                # journal's end if its stops were lost with it
                p.finished = True
                self.log(f"{p.name}: ended (exit {code}) after it finished the run (its end "
                         "journaled); not restarted")
                continue
            budget = self._budget(p)  # a token bucket: a rate (pipeline.stream.budget)
            spent = budget.spent()
            if not budget.take():
                self.failed = (f"{p.name} died (exit {code}) with its restart budget spent "
                               f"({budget.describe()}; {p.restarts} restarts); giving up "
                               f"(see {self.topo.state / 'logs' / (p.name + '.log')})")
                self.log(self.failed)
                return True
            backoff = min(self.topo.restart_backoff_max_s,
                          self.topo.restart_backoff_s * 2 ** spent)
            p.restarts += 1
            p.terminated, p.upstream_done_at = False, None
            p.restart_at = now + backoff
            self.log(f"{p.name}: died (exit {code}); restart {p.restarts} in {backoff:.1f} s "
                     f"({budget.available():.1f} of {budget.burst} left, one more every "
                     f"{budget.refill_s:g} s)")
        return all(p.finished for p in self.procs)

    def _budget(self, p: Proc):
        from pipeline.stream.budget import RestartBudget

        if p.budget is None:
            p.budget = RestartBudget(self.topo.restarts, self.topo.restart_refill_s)
        return p.budget

    def _grace(self) -> float:
        """How long a stage whose upstream finished may take nothing before its SIGTERM:
        ``GRACE_S``, or ``STOP_GRACE_S`` once the daemon is stopping (a stop in <= 3 s)."""
        return STOP_GRACE_S if self.stop.is_set() else GRACE_S

    def _silence(self, p: Proc, now: float) -> tuple[float, str]:
        """How long live stage ``p`` has sent no heartbeat, and its last reported state. A
        stage reports from its own loop, also while it waits on a full consumer ("blocked")
        or a full disk ("paused"): only a stage that stopped running stops reporting. One
        not heard from yet (this process) is starting up: counted from ``STARTUP_S``."""
        m = self.metrics.get(p.name, {})
        if m.get("pid") == p.popen.pid and "t" in m:
            return now - m["t"], str(m.get("state", "running"))
        return now - p.started_at - STARTUP_S, "starting"

    def _kill_frozen(self, now: float) -> None:
        """Heartbeat deadline: a live stage silent for ``heartbeat_deadline_s`` is frozen
        (SIGSTOPped, wedged in a call): a SIGTERM never reaches it, so it is SIGKILLed, and
        the restart path restarts it (counted in its restarts and in ``frozen``). The stages
        waiting on it keep reporting "blocked" and are left alone."""
        deadline = self.topo.heartbeat_deadline_s
        for p in self.procs:
            if p.finished or p.popen is None or p.restart_at is not None \
                    or p.popen.poll() is not None:
                continue
            silent, state = self._silence(p, now)
            if silent <= deadline or state == "finished":
                continue
            p.frozen += 1
            self.log(f"{p.name}: no heartbeat for {silent:.1f} s (deadline {deadline:.0f} s, "
                     f"last state {state}, pid {p.popen.pid}): frozen; SIGKILL and restart")
            try:
                os.kill(p.popen.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass  # it ended meanwhile: the restart path sees its exit
            p.popen.wait()

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
        try:
            bind(sub, self.topo.metrics)
        finally:
            self._listening.set()
        pub, sent = status_pub(ctx, self.topo.state, self.log), None
        try:
            while not self.ended.is_set():  # (after a stop too: the stages still report)
                if pub is not None and self._status_msg is not sent:
                    sent = self._status_msg  # (this thread owns the PUB socket)
                    try:
                        pub.send(sent, zmq.NOBLOCK)
                    except zmq.ZMQError:
                        pass  # nobody listening, or a slow page: the next one will do
                if sub.poll(200):
                    try:
                        rec = json.loads(sub.recv())
                        if not check_record(rec, self.token):
                            self.forged_heartbeats += 1  # no token: not one of ours
                            continue
                        rec.pop("token", None)
                        self.ops.totals.observe(rec)  # (run totals: a new pid folds in)
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
            if pub is not None:
                pub.close()

    def status(self) -> dict:
        now = time.time()
        stages = {}
        for p in self.procs:
            m = dict(self.metrics.get(p.name, {}))
            alive = p.popen is not None and p.popen.poll() is None
            stages[p.name] = {
                "pid": p.popen.pid if p.popen else None, "alive": alive,
                "finished": p.finished, "restarts": p.restarts, "frozen": p.frozen,
                "heartbeat_age_s": round(now - m["t"], 2) if "t" in m else None,
                "health": ("finished" if p.finished else
                           "restarting" if p.restart_at is not None else
                           "paused" if alive and m.get("state") == "paused" else
                           "down" if not alive else
                           "frozen" if ("t" in m and now - m["t"] >
                                        self.topo.heartbeat_deadline_s) else
                           "waiting" if "t" in m and now - m["t"] < 5
                           and m.get("state") == "blocked" else
                           "ok" if "t" in m and now - m["t"] < 5 else "silent"),
                **{k: v for k, v in m.items() if k not in ("stage", "pid", "t")}}
        depth = {}
        for p in self.procs:  # messages sent upstream and not yet taken (approximate)
            got = stages[p.name].get("received")
            sent = sum(stages[u].get("sent", 0) for u in p.upstream)
            if p.upstream and got is not None:
                depth[p.name] = max(0, sent - got)
        return {"run": self.topo.run, "topology": self.topo.path, "updated": now,
                "started": self.started, "pid": os.getpid(),
                "state": "failed" if self.failed else "running",
                "forged_heartbeats": self.forged_heartbeats,
                "paused": {name: s.get("reason") for name, s in stages.items()
                           if s["health"] == "paused"},
                "stages": stages, "queue_depth": depth}

    def _write_status(self, extra: dict | None = None) -> None:
        status = {**self.status(), **(extra or {})}
        self.ops.update(self, status)  # totals saved; metrics; systemd's STATUS=
        paused = status.get("paused") or {}
        for name in sorted(set(paused) ^ self._paused):  # a full disk is said, in the log
            self.log(f"{name}: paused ({paused[name]})" if name in paused else
                     f"{name}: resumed")
        self._paused = set(paused)
        try:
            text = json.dumps(status, indent=1, default=str)
            self._status_msg = text.encode()
            write_status_file(self.topo.state / "status.json", text)
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
        return min((least or 0) * self.topo.n_tdc, self._durable_word())

    def _durable_word(self) -> int:
        """The run's word index below which every measurement is on disk in the sink's
        datasets (histograms, and ranges when ranged), for every TDC range. A worker that
        checkpointed past a measurement has only *sent* it: a range or sink stage killed
        with it in flight loses it, and the end-of-run reconciliation recomputes it from
        the journal, so retention must not prune those words before they are written.
        (A run without measurement_cycles is one measurement: nothing is durable before
        its end, and nothing is pruned.)"""
        mc = self.topo.histogram.get("measurement_cycles")
        if not mc:
            return 0
        out = Path(self.topo.sink["out"])
        parts = [out / s / f"date={self.topo.date}" / f"run={self.topo.run}"
                 for s in ("histograms", *(["ranges"] if self.topo.range else []))]
        firsts = [a for a, _ in tdc_ranges(self.topo)]
        k = self._durable
        while all((d / f"part-{k:06d}-t{a:03d}.parquet").exists()
                  for d in parts for a in firsts):
            k += 1
        self._durable = k
        return k * int(mc) * self.topo.n_tdc

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
        from pipeline.stream.journal import reopen
        from pipeline.stream.runrecord import end

        if self.record.get("state") == "finished":
            self.log(f"run {self.topo.run}: already finished; its accounting stands "
                     f"(see {self.topo.state / 'runs' / (self.topo.run + '.json')})")
            self.lock.release()
            return {**self.record["result"], "already_finished": True}
        if stream_ended(self.topo.state / "journal", self.topo.run):
            # the source's stream ended and was journaled whole (a daemon killed during its
            # reconciliation, or after its source's end): nothing more will come, so no
            # source (a UDP ingest would wait for datagrams for ever); the stages finish
            # the run from the journal, then it is reconciled as any run
            self.by_name["source"].finished = True
            self.log(f"run {self.topo.run}: its source's stream had ended (the journal's "
                     "end); finishing the run from the journal")
        elif reopen(self.topo.state / "journal", self.topo.run):  # before any stage starts
            self.log(f"run {self.topo.run}: resuming after an earlier stop")
        collector = threading.Thread(target=self._collect, daemon=True)
        collector.start()
        self._listening.wait(2.0)  # (the first heartbeats find the collector bound)
        if self.view is not None:
            self._start(self.view.proc)
        for p in self.procs:
            if not p.finished:
                self._start(p)
        self.log(f"run {self.topo.run}: {sum(p.popen is not None for p in self.procs)} "
                 "stages started "
                 f"({self.topo.workers} histogram workers); state in {self.topo.state}")
        last = 0.0
        try:
            while not self._check():
                if self.stop.is_set():
                    self.shutdown()
                if time.time() - last > 1.0:
                    self._write_status()
                    self._prune()
                    if self.view is not None:
                        self.view.keep()
                    last = time.time()
                self.ops.tick(self)  # WATCHDOG=1 (only while this loop runs); READY=1
                time.sleep(self.poll_s)
        finally:
            self.ops.stopping()
            if self.failed:
                self.kill_all()
            self.stop.set()
            self.ended.set()
            collector.join(timeout=2)
        result = {"run": self.topo.run, "failed": self.failed,
                  "interrupted": self.interrupted,
                  "restarts": {p.name: p.restarts for p in self.procs if p.restarts},
                  "frozen": {p.name: p.frozen for p in self.procs if p.frozen},
                  "journal_segments_pruned": self.pruned,
                  "totals": self.ops.totals.totals(self.procs)}  # (across daemon restarts)
        if not self.failed:
            try:
                result["reconciled"] = reconcile(self.topo)
                for part in result["reconciled"].get("rebuilt", []):
                    self.log(f"rebuilt from the journal: {part['file']} ({part['why']})")
                if result["reconciled"].get("spatial_reranged"):
                    self.log("ranged again whole from the journal (a worker's part had not "
                             "reached the range stage): measurements "
                             f"{result['reconciled']['spatial_reranged'][:8]}")
                result["accounting"] = accounting(  # (rejections: the run's totals)
                    self.topo, self.ops.totals.merged(self.metrics), result["reconciled"],
                    self.bounds)
            except Exception as exc:  # the run must end with a state, never "running"
                self.failed = f"reconciling the run failed: {type(exc).__name__}: {exc}"
                result["failed"] = self.failed
                self.log(self.failed)
        else:  # a failed run: what was done and what is missing is written all the same
            try:
                result["accounting"] = accounting(
                    self.topo, self.ops.totals.merged(self.metrics), None, self.bounds)
                acc = result["accounting"]
                self.log(f"run {self.topo.run}: failed; {acc['classified']:,} of "
                         f"{acc['words_in']:,} journaled words in the datasets "
                         f"({acc['path']})")
            except Exception as exc:
                self.log(f"run {self.topo.run}: no accounting ({type(exc).__name__}: {exc})")
        result["problems"] = [] if self.failed else problems(result)
        result["state"] = run_state(result)
        for line in result["problems"]:
            self.log(f"run {self.topo.run}: {line}")
        corrupt = (result.get("reconciled") or {}).get("corrupt_words", 0)
        self._write_status({"state": result["state"], "result": result,
                            "problems": result["problems"],
                            **({"journal_corrupt_words": corrupt} if corrupt else {})})
        if self.view is not None:
            self.view.end()
        try:
            end(self.topo, result)
        except OSError as exc:  # (a full state disk: the run's result is still printed)
            self.log(f"run {self.topo.run}: its record not updated ({exc})")
        self.lock.release()
        return result


STATUS_SLACK = 8192  #: status.json's padding: room to be rewritten in place on a full disk


def write_status_file(path: Path, text: str) -> None:
    """status.json, replaced atomically, padded with spaces (JSON ignores them) so that on
    a full state disk, when no new file can be made, it is rewritten in place within the
    blocks it already has: the status a full disk makes ("paused") is never hidden behind
    the last one written before it."""
    try:
        with atomic_path(path) as tmp:
            tmp.write_text(text + "\n" + " " * STATUS_SLACK)
        return
    except OSError as exc:
        from pipeline.stream.journal import is_disk_full

        if not is_disk_full(exc):
            raise
        fd = os.open(path, os.O_WRONLY | os.O_NOFOLLOW)
        try:
            size = os.fstat(fd).st_size
            if len(text) + 1 > size:
                raise
            os.pwrite(fd, (text + "\n").ljust(size).encode(), 0)
        finally:
            os.close(fd)


# ------------------------------------------------------------------ the run's verdict

#: The daemon's exit status per end state (``interrupted``: 128 + the signal).
EXIT_CODES = {"finished": 0, "failed": 1, "incomplete": 3}


def problems(result: dict) -> list[str]:
    """What keeps a run's datasets from being the whole run: one line per problem, naming
    the numbers that disagree (empty: the datasets are the journal, every word in)."""
    out = []
    rec, acc = result.get("reconciled") or {}, result.get("accounting") or {}
    if not rec.get("checked", False):
        out.append(f"reconciliation skipped: {rec.get('why', 'not run')}")
    if acc and not acc.get("balanced", False):
        diff = acc['words_in'] - acc['classified'] - acc['withheld']
        why = ("journaled words in no part: a measurement missing" if diff > 0 else
               "the parts hold more words than the journal: a measurement counted twice or "
               "a part of another topology beside the run's")
        out.append(f"unbalanced: words journaled {acc['words_in']:,} != classified "
                   f"{acc['classified']:,} + withheld {acc['withheld']:,} (difference "
                   f"{diff:+,}: {why})")
    for key, what in (("unrecoverable", "unrecoverable (their journal words were pruned)"),
                      ("corrupt", "withheld (a corrupt journal chunk)")):
        if rec.get(key):
            out.append(f"{len(rec[key])} measurement(s) {what}: [measurement, first TDC] "
                       f"{rec[key][:8]}")
    if rec.get("spatial_incomplete"):
        out.append(f"{len(rec['spatial_incomplete'])} measurement(s) ranged with the "
                   f"neighbours without some workers' parts (not in the journal either): "
                   f"{rec['spatial_incomplete'][:8]}")
    if acc.get("words_in_gaps", 0) or acc.get("lost_datagrams", 0) or acc.get(
            "ring_dropped_datagrams", 0):
        out.append(f"input lost before the journal: {acc.get('lost_datagrams', 0):,} "
                   f"datagrams, {acc.get('words_in_gaps', 0):,} words in gaps, "
                   f"{acc.get('ring_dropped_datagrams', 0):,} datagrams dropped by the "
                   f"ingest's full ring")
    if acc.get("conflicting_datagrams", 0):
        out.append(f"{acc['conflicting_datagrams']:,} conflicting datagram(s): a sequence "
                   f"number and cycle taken before came again with other bytes")
    if acc.get("stream_restarts"):
        out.append(f"the UDP stream restarted {len(acc['stream_restarts'])} time(s) (an FPGA "
                   f"reset or a sequence jump; journaled, measured on in a new segment): "
                   f"{[(e['event'], e['at_cycle']) for e in acc['stream_restarts'][:4]]}")
    second = sorted(n for n, b in (acc.get("other_senders") or {}).items()
                    if b.get("consistent"))
    if second and not acc.get("peers"):
        out.append(f"a second sender sent a consistent stream: {', '.join(second)}; the run "
                   f"took {acc.get('sender')}'s (set [source] peers to say which is the "
                   f"run's)")
    return out


def run_state(result: dict) -> str:
    """``failed``, ``interrupted`` (a signal stopped it: resume with the same --run),
    ``incomplete`` (it ended, but with :func:`problems`) or ``finished``."""
    if result.get("failed"):
        return "failed"
    if result.get("interrupted"):
        return "interrupted"
    return "incomplete" if result.get("problems") else "finished"


def exit_code(result: dict) -> int:
    state = result.get("state") or run_state(result)
    if state == "interrupted":
        return 128 + int(getattr(signal, result["interrupted"], signal.SIGINT))
    return EXIT_CODES[state]


# ------------------------------------------------------------------ reconcile, accounting


def spatial_args(topo: Topology) -> list:
    """The range stage's spatial options."""
    g = spatial_geometry(topo)
    return [] if g is None else ["--spatial", "--geometry", g, "--hold", range_hold(topo)]


def _cloud_args(sink: dict) -> list:
    """The sink stage's point-cloud options (``[sink] pointcloud``, ``geometry``)."""
    if not sink.get("pointcloud"):
        return []
    return ["--pointcloud", sink["pointcloud"], "--geometry", sink.get("geometry", "")]


def reconcile_offline(topo: Topology) -> dict:
    """`tcspc reconcile`: finish or check run ``topo.run`` from its journal and datasets
    with no daemon running (issue 38.7): the datasets reconciled with the journal as the
    daemon does at a run's end (a measurement missing or partial rebuilt from the
    journal, one counted twice replaced), the accounting written
    (``OUT/accounting/run=RUN.json``), the run's record updated. Idempotent: a second call
    finds nothing to rebuild and writes the same accounting; a daemon killed while
    reconciling leaves what this finishes. The stages' own counts (datagrams lost,
    rejections) come from ``status.json`` where it is this run's, and from the run totals
    the daemon kept; otherwise only the journal against the datasets is checked (said in
    ``notes``). An interrupted run stays interrupted (resume it with the daemon).
    Raises StateError while a daemon holds the state, or for a run with no journal."""
    from pipeline.stream.exporter import RunTotals
    from pipeline.stream.runrecord import end
    from pipeline.stream.state import StateError, open_state

    journal = topo.state / "journal"
    if not (journal / f"{topo.run}.index.jsonl").is_file():
        raise StateError(f"run {topo.run}: no journal in {journal} (a run of this topology's "
                         "[daemon] state?)")
    lock = open_state(topo.state)
    try:
        rec = {}
        try:
            rec = json.loads((topo.state / "runs" / f"{topo.run}.json").read_text())
        except (OSError, ValueError):
            pass  # (a run from before run records: its date from the topology)
        if rec.get("date"):
            topo.date = rec["date"]
        prev = rec.get("result") or {}
        metrics, notes = {}, []
        try:
            status = json.loads((topo.state / "status.json").read_text())
        except (OSError, ValueError):
            status = {}
        if status.get("run") == topo.run and isinstance(status.get("stages"), dict):
            metrics = {name: dict(st) for name, st in status["stages"].items()}
        else:
            notes.append("the stages' counts (datagrams lost, rejections) are not this run's "
                         "in status.json: only the journal against the datasets is checked")
        result = {"run": topo.run, "failed": None, "interrupted": prev.get("interrupted"),
                  "reconciled_offline": True, "restarts": prev.get("restarts", {}),
                  "frozen": prev.get("frozen", {}), "notes": notes}
        result["reconciled"] = reconcile(topo)
        bounds = (prev.get("accounting") or {}).get("artifact_bounds")
        result["accounting"] = accounting(topo, RunTotals(topo.state, topo.run).merged(
            metrics), result["reconciled"], bounds)
        result["problems"] = problems(result)
        result["state"] = run_state(result)
        if rec:
            end(topo, result)
        return result
    finally:
        lock.release()
