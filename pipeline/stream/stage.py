"""The one ZeroMQ runner every stage uses, and the stream's sources and sinks.

A stage binds its PULL input and connects its PUSH output (so stages can start in any
order), with high-water marks so a slow stage pushes back. Bad messages are counted by
reason and written to a quarantine directory, never raised. SIGTERM/SIGINT finish the
message in hand, flush the core and pass a stop on.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
import time
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import zmq

from pipeline.io.atomic import atomic_path
from pipeline.stream import wire
from pipeline.stream.hangup import END_WAIT_S, Consumers
from pipeline.stream.metrics import Metrics
from pipeline.stream.state import write_under
from schemas.errors import Rejected, TcspcError
from schemas.outputs import HISTOGRAMS, RANGES

DEFAULT_HWM = 4
QUARANTINE_MAX_FILES = 1000        #: messages kept per stage and run (the excess is counted)
QUARANTINE_MAX_BYTES = 256 << 20   #: bytes kept per stage and run
QUARANTINE_KEEP_BYTES = 1 << 20    #: of one message, the first this many bytes are kept


class _GaveUp(Exception):
    """A stop came while waiting for a full disk."""


def _log(msg: str) -> None:
    """A line in the stage's log; a full disk must not turn a log line into a crash."""
    try:
        print(msg, file=sys.stderr, flush=True)
    except OSError:
        pass


class CheckpointError(TcspcError, ValueError):
    """A checkpoint that cannot be trusted (truncated, bit-flipped, not ours)."""


class EndpointInUse(TcspcError, OSError):
    """An ipc:// endpoint another live process is bound to."""


@dataclass
class StageStats:
    received: int = 0
    sent: int = 0
    rejected: Counter = field(default_factory=Counter)
    blocked_s: float = 0.0   #: time spent waiting to send (back-pressure from downstream)
    checkpoints_discarded: int = 0
    quarantine_dropped: int = 0  #: rejected messages counted but not kept (quarantine full)
    checkpoint_failures: int = 0  #: checkpoints a full disk refused (skipped)
    paused_s: float = 0.0        #: time waiting for a full disk
    unwritten: int = 0           #: messages given up on a full disk at a signal (journaled)
    unacknowledged: int = 0      #: consumers that did not hang up after the stop (hangup)

    def fields(self, core=None) -> dict:
        out = {"received": self.received, "sent": self.sent,
               "rejected": dict(self.rejected), "blocked_s": round(self.blocked_s, 3),
               "checkpoints_discarded": self.checkpoints_discarded,
               "quarantine_dropped": self.quarantine_dropped,
               "checkpoint_failures": self.checkpoint_failures,
               "paused_s": round(self.paused_s, 1), "unwritten": self.unwritten,
               "unacknowledged": self.unacknowledged}
        for name in ("words_total", "measurement", "gap_words", "backfilled", "duplicates",
                     "incomplete_frames", "held_frames"):
            if hasattr(core, name):
                out[name] = int(getattr(core, name))
        by_class = getattr(core, "words_by_class", None)
        if by_class is not None and (classes := by_class()) is not None:
            out["classes"] = classes  # (a histogram worker: the live words by class)
        return out


def _socket(ctx: zmq.Context, kind: int, hwm: int,
            max_bytes: int | None = wire.MAX_MESSAGE_BYTES) -> zmq.Socket:
    s = ctx.socket(kind)
    s.setsockopt(zmq.LINGER, 2000)
    s.setsockopt(zmq.SNDHWM, hwm)
    s.setsockopt(zmq.RCVHWM, hwm)
    if max_bytes is not None and kind in (zmq.PULL, zmq.SUB):
        # ZeroMQ refuses a larger frame as it arrives (and drops that peer's connection),
        # so an oversized message is never buffered; wire.decode checks the total
        s.setsockopt(zmq.MAXMSGSIZE, max_bytes)
    return s


END_LINGER_MS = 10_000  #: at a stage's end, how long its last messages may take to go


def own_context(context: zmq.Context | None) -> tuple[zmq.Context, bool]:
    """The given context, or one of the stage's own (True): ended by :func:`end_context`."""
    return (context, False) if context is not None else (zmq.Context(), True)


def end_context(ctx: zmq.Context) -> None:
    """End a stage's own context once its sockets are closed. ZeroMQ sends from a
    background thread: a process that exits without this loses what is still queued in
    it; ``term()`` returns once that is written to the connection or the sockets' linger
    has run out. Written is not read: over ipc:// what the consumer has not read is lost
    when the sender closes, so a sender first waits for its consumer to hang up
    (:mod:`pipeline.stream.hangup`)."""
    from pipeline.stream.curve import release

    release(ctx)
    ctx.term()


def bind(sock: zmq.Socket, endpoint: str) -> None:
    """Bind ``endpoint``; an ipc:// path left by a dead process is removed first, one a live
    process listens on is refused (libzmq would silently take it over, orphaning it)."""
    if endpoint.startswith("ipc://"):
        import socket as pysocket

        path = Path(endpoint[len("ipc://"):])
        if path.exists() or path.is_symlink():
            probe = pysocket.socket(pysocket.AF_UNIX, pysocket.SOCK_STREAM)
            probe.settimeout(1.0)
            try:
                probe.connect(str(path))
            except (ConnectionRefusedError, FileNotFoundError, OSError):
                path.unlink(missing_ok=True)  # stale: nobody holds it
            else:
                raise EndpointInUse(f"{endpoint}: a live process is bound there (another "
                                    "stage or an orphan of a killed daemon); not taking it")
            finally:
                probe.close()
        path.parent.mkdir(parents=True, exist_ok=True)
    from pipeline.stream import curve

    curve.serve(sock)  # with $TCSPC_CURVE_DIR: encrypted, authorized clients only
    sock.bind(endpoint)


def connect(sock: zmq.Socket, endpoint: str) -> None:
    """Connect ``endpoint`` (as a CURVE client with $TCSPC_CURVE_DIR)."""
    from pipeline.stream import curve

    curve.client(sock)
    sock.connect(endpoint)


class Quarantine:
    """Rejected input kept for inspection, bounded: at most ``max_files`` messages and
    ``max_bytes`` per directory (a stage of a run); beyond that a message is counted in
    ``dropped`` and not written. Counts persist across a restart (read back from the
    directory)."""

    def __init__(self, qdir: str | Path | None, max_files: int = QUARANTINE_MAX_FILES,
                 max_bytes: int = QUARANTINE_MAX_BYTES):
        self.dir = Path(qdir) if qdir else None
        self.max_files, self.max_bytes = max_files, max_bytes
        self.kept = self.bytes = self.dropped = 0
        if self.dir is not None and self.dir.exists():
            bins = list(self.dir.glob("*.bin"))
            self.kept = len(bins)
            self.bytes = sum(p.stat().st_size for p in bins)
            drop = self.dir / "dropped.json"
            if drop.exists():
                try:
                    self.dropped = int(json.loads(drop.read_text())["dropped"])
                except (ValueError, KeyError, TypeError):
                    self.dropped = 0

    def put(self, reason: str, data: bytes, **meta) -> bool:
        """Keep ``data`` (its first QUARANTINE_KEEP_BYTES) with its reason; False when the
        quarantine is full and it was only counted."""
        if self.dir is None:
            return False
        raw = data[:QUARANTINE_KEEP_BYTES]
        if self.kept >= self.max_files or self.bytes + len(raw) > self.max_bytes:
            self.dropped += 1
            with atomic_path(self.dir / "dropped.json") as tmp:
                tmp.write_text(json.dumps({"dropped": self.dropped}))
            return False
        self.dir.mkdir(parents=True, exist_ok=True)
        n = self.kept + self.dropped + 1
        (self.dir / f"{n:06d}.bin").write_bytes(raw)
        (self.dir / f"{n:06d}.json").write_text(json.dumps({"reason": reason, "bytes":
                                                            len(data), **meta}))
        self.kept += 1
        self.bytes += len(raw)
        return True


def _quarantine(q: Quarantine, reason: str, frames) -> None:
    """Keep the first QUARANTINE_KEEP_BYTES of a rejected message: only those bytes are
    copied (a message of many large frames is not joined into one more copy of itself)."""
    views = [memoryview(f.buffer if hasattr(f, "buffer") else f) for f in frames]
    head, left = [], QUARANTINE_KEEP_BYTES
    for v in views:
        if left <= 0:
            break
        head.append(bytes(v[:left]))
        left -= len(head[-1])
    q.put(reason, b"".join(head), frames=len(frames), bytes=sum(v.nbytes for v in views))


def _digest(state: dict) -> bytes:
    import hashlib

    import numpy as np

    h = hashlib.sha256()
    for k in sorted(state):
        a = np.ascontiguousarray(state[k])
        h.update(f"{k}|{a.dtype.str}|{a.shape}|".encode())
        h.update(memoryview(a).cast("B"))
    return h.digest()


def save_checkpoint(path: Path, state: dict) -> None:
    """A core's snapshot as .npz (arrays only, written atomically; never pickled), with a
    SHA-256 of its arrays (``_sha256``) so a damaged file is known as such."""
    import numpy as np

    digest = np.frombuffer(_digest(state), np.uint8)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(fh, **state, _sha256=digest)


def load_checkpoint(path: Path) -> dict | None:
    """The snapshot in ``path`` (None: no file). A file that does not read back whole or
    whose arrays do not match their checksum raises CheckpointError (a checkpoint written
    before checksums were added is taken on the zip's own CRCs)."""
    import numpy as np

    if not path.exists():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            state = {k: z[k] for k in z.files}
    except Exception as exc:  # noqa: BLE001 (zipfile raises anything on a damaged file:
        # BadZipFile, NotImplementedError for a flipped method field, struct.error, ...)
        raise CheckpointError(f"{path}: unreadable checkpoint ({type(exc).__name__}: "
                              f"{exc})") from None
    digest = state.pop("_sha256", None)
    if digest is not None and digest.tobytes() != _digest(state):
        raise CheckpointError(f"{path}: checkpoint checksum mismatch (bit flip or torn "
                              "write)")
    return state


def run_stage(core, pull: str, push: str | None = None, *, hwm: int = DEFAULT_HWM,
              quarantine: str | Path | None = None, stop: threading.Event | None = None,
              poll_ms: int = 200, context: zmq.Context | None = None,
              checkpoint: str | Path | None = None, checkpoint_every_s: float = 1.0,
              run_ended=None, idle_after_s: float = 2.0, expect_stops: int = 1,
              metrics: str | None = None, name: str | None = None,
              drain_ms: int = 1000, token: str | None = None,
              max_bytes: int = wire.MAX_MESSAGE_BYTES,
              quarantine_max_files: int = QUARANTINE_MAX_FILES,
              quarantine_max_bytes: int = QUARANTINE_MAX_BYTES,
              senders: list[str] | None = None,
              end_wait_s: float = END_WAIT_S) -> StageStats:
    """Run ``core`` between ``pull`` (bound) and ``push`` (connected) until a stop message,
    a signal or ``stop`` is set. Returns the counts.

    With ``checkpoint``, a stateful core (``snapshot``/``restore``) is restored from that
    file at start, saved at most every ``checkpoint_every_s`` seconds (a checkpoint is an
    fsync; an older one only means more words refolded from the journal after a restart)
    and at the end, so a restarted stage
    resumes where its checkpoint left it (the core skips what it already folded in and
    fills gaps from the journal). ``run_ended()`` returns the run's total words once its
    source has finished (from the journal), else None: after ``idle_after_s`` without a
    message it lets a restarted stage finish even if the source's stop was lost with the
    process that was killed. On SIGTERM/SIGINT (or ``stop``) the stage drains: it takes
    messages until none has come for ``drain_ms``, then finishes. ``expect_stops``: upstream
    workers feeding this stage (a fan-out joins here), each ending with a stop (one counted
    per sending step). ``metrics``: endpoint for heartbeats. ``token``: the run's token
    (default: from $TCSPC_TOKEN_FILE); with one, a message without it is rejected
    (``bad_token``) and every message sent carries it. A checkpoint that cannot be trusted
    is set aside (``.bad``) with its reason on stderr, and the core rebuilds from the
    journal. ``senders``: the step ids this stage takes messages from (None: any); a
    message from another is rejected (``unknown_sender``). At its end, after its stop, it
    waits up to ``end_wait_s`` for its consumer to hang up (its acknowledgement: ZeroMQ's
    ipc transport loses what a consumer has not read when the sender closes, whatever the
    linger; :mod:`pipeline.stream.hangup`); one that does not is counted in
    ``unacknowledged``."""
    ctx, own = own_context(context)
    stats = StageStats()
    token = token if token is not None else wire.load_token()
    q = Quarantine(quarantine, quarantine_max_files, quarantine_max_bytes)
    stop = stop or threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    ckpt = Path(checkpoint) if checkpoint else None
    if ckpt is not None:
        fresh = core.snapshot()
        try:
            state = load_checkpoint(ckpt)
            if state is not None:
                core.restore(state)
        except (CheckpointError, KeyError, ValueError, TypeError) as exc:
            # the journal holds every word: the fresh core refolds them (its backfill)
            core.restore(fresh)
            _log(f"checkpoint discarded, rebuilding from the journal: {exc}")
            ckpt.replace(ckpt.with_suffix(ckpt.suffix + ".bad"))
            stats.checkpoints_discarded += 1
    saved_at = time.monotonic()
    idle = 0.0
    rx = _socket(ctx, zmq.PULL, hwm, max_bytes)
    bind(rx, pull)
    tx = consumers = None
    if push:
        tx = _socket(ctx, zmq.PUSH, hwm)
        consumers = Consumers([tx])  # (watched from before it connects)
        connect(tx, push)
    last = {"run": "run", "seq": 0}
    beat = Metrics(metrics, name or core.step_id, ctx, token=token)
    stopped_by: set[str] = set()
    given_up: list = []  # non-empty once a signal gave up on an unresponsive consumer
    gone = [False]  # the consumer hung up after the stop: nothing left to linger over

    def deliver(frames) -> bool:
        """Send, waiting while downstream is full (back-pressure); after a signal, a
        downstream that takes nothing for ``drain_ms`` is given up on (a stage restarted
        after its consumer finished would otherwise block for ever): the message is
        counted as unwritten, and its words are in the journal for the end of the run."""
        if given_up and stop.is_set() and not tx.poll(0, zmq.POLLOUT):
            stats.unwritten += 1
            return False
        t0 = time.perf_counter()
        waited = 0
        try:
            while not tx.poll(200, zmq.POLLOUT):
                waited += 200
                if consumers is not None:
                    consumers.keep()
                beat.beat(state="blocked", **stats.fields(core))
                if stop.is_set() and (waited >= drain_ms or given_up):
                    given_up.append(True)  # the rest go the same way, without waiting
                    stats.unwritten += 1
                    return False
            tx.send_multipart(frames)
            return True
        finally:
            stats.blocked_s += time.perf_counter() - t0

    def send(messages):
        for head, batch in messages:
            if tx is not None and deliver(wire.encode(head, batch, token)):
                stats.sent += 1

    def reject(exc, frames):
        stats.rejected[exc.reason] += 1
        try:
            _quarantine(q, str(exc), frames)
        except OSError:
            q.dropped += 1  # a full disk: counted, not kept
        stats.quarantine_dropped = q.dropped

    def checkpoint():
        # a checkpoint the disk refuses is skipped: an older one only means more words
        # refolded from the journal after a restart
        try:
            save_checkpoint(ckpt, core.snapshot())
        except OSError as exc:
            stats.checkpoint_failures += 1
            _log(f"checkpoint not saved: {exc}")

    def retry_disk_full(fn, *args):
        """``fn(*args)``, waiting (paused, with back-off) while the disk is full; the stage
        upstream is held back by the high-water marks meanwhile."""
        from pipeline.stream.journal import is_disk_full

        wait = 0.2
        while True:
            try:
                return fn(*args)
            except OSError as exc:
                if not is_disk_full(exc):
                    raise
                if stop.is_set():
                    raise _GaveUp from None
                stats.paused_s += wait
                beat.beat(force=True, state="paused", reason=f"disk full: {exc}",
                          **stats.fields(core))
                time.sleep(wait)
                wait = min(2 * wait, 5.0)

    try:
        while True:
            if consumers is not None:
                consumers.keep()
            beat.beat(state="running", **stats.fields(core))
            if stop.is_set() and not rx.poll(drain_ms):
                # a signal: take what is in flight, then finish; when the run has ended
                # (its journal closed) the words this stage never got (it was stopped
                # across the stream's end, its stop undelivered) come from the journal
                total = run_ended() if run_ended is not None else None
                if total is not None and hasattr(core, "catch_up"):
                    core.catch_up(total)
                break
            if not rx.poll(poll_ms):
                idle += poll_ms / 1000
                if run_ended is not None and idle >= idle_after_s:
                    total = run_ended()
                    if total is not None:
                        if hasattr(core, "catch_up"):
                            core.catch_up(total)
                        break
                continue
            idle = 0.0
            frames = rx.recv_multipart(copy=False)
            stats.received += 1
            try:
                head, batch = wire.decode(frames, core.in_spec, max_bytes, token)
                if senders is not None and head["step"] not in senders:
                    raise wire.WireError("unknown_sender", f"step {head['step']!r} is not "
                                         f"upstream of this stage ({senders})")
            except wire.WireError as exc:
                reject(exc, frames)
                continue
            last = head
            if head["kind"] == "stop":
                stopped_by.add(head["step"])  # a stop repeated by one step counts once
                if len(stopped_by) >= expect_stops:
                    # the stream's end: fold in whatever was lost in flight (journal)
                    total = run_ended() if run_ended is not None else None
                    if total is not None and hasattr(core, "catch_up"):
                        core.catch_up(total)
                    break
                continue
            try:
                out = retry_disk_full(core.process, head, batch)
            except Rejected as exc:  # the core's own refusal (a path outside the sink)
                reject(exc, frames)
                continue
            except _GaveUp:  # a signal while the disk was full: the journal has the words
                stats.unwritten += 1
                continue
            send(out)
            if ckpt is not None and time.monotonic() - saved_at >= checkpoint_every_s:
                checkpoint()
                saved_at = time.monotonic()
        rx.close(linger=0)  # taken all it will: its hang-up lets the senders upstream end
        try:
            send(retry_disk_full(core.finish, last))
        except _GaveUp:
            stats.unwritten += 1
        if ckpt is not None:
            checkpoint()
        if tx is not None:
            stop_head = {"kind": "stop", "schema": core.out_spec.name,
                         "version": core.out_spec.version, "run": last.get("run", "run"),
                         "seq": stats.sent, "step": core.step_id,
                         "rejected": dict(stats.rejected)}
            at_end = consumers.at_end()
            if deliver(wire.encode(stop_head, None, token)):
                # the consumer's hang-up acknowledges the stop: closing before it loses what
                # it has not read yet (hangup.py); after a signal, drain_ms at most
                gone = consumers.wait(at_end, end_wait_s, beat, stop, drain_ms / 1000,
                                      **stats.fields(core))
                stats.unacknowledged = consumers.unacknowledged
                if stats.unacknowledged:
                    _log(f"its consumer at {push} did not hang up within {end_wait_s:g} s "
                         "of its stop; what it has not read may be lost (the journal and the "
                         "run's reconciliation have it)")
        beat.beat(force=True, state="finished", **stats.fields(core))
    finally:
        beat.close()
        rx.close(linger=0)
        if tx is not None:
            consumers.close()
            tx.close(linger=0 if stop.is_set() or gone[0] else END_LINGER_MS)
        if own:
            end_context(ctx)
    return stats


def run_source(batches, push: str | list[str], *, step_id: str, run: str, n_tdc: int,
               t_laser_win_ns: float, hwm: int = DEFAULT_HWM, rate_words_s: float | None = None,
               context: zmq.Context | None = None, journal=None,
               split: list[tuple[int, int]] | None = None, metrics: str | None = None,
               window_ns: float | None = None, date: str | None = None,
               token: str | None = None, stable: int = 0, sparse: bool = False,
               end_wait_s: float = END_WAIT_S) -> int:
    """Send ``(first_word, words)`` batches as raw_words messages, then a stop. Returns the
    words sent. ``rate_words_s`` limits the rate (None: as fast as the consumer takes).
    With a ``journal`` (JournalWriter) every batch is journaled before it is sent. With
    ``split`` (TDC ranges, one per endpoint in ``push``) each batch of whole cycles is cut
    into one sub-batch per range (a fan-out by TDC range). ``words`` are uint32 in either
    byte order (a capture's big-endian words are journaled as they are and swapped into
    the message: :mod:`pipeline.stream.rawwire`). ``stable``: for how many later batches a
    batch's words stay valid (a reader's ring of buffers); from 2 the journal writes them
    without a copy (it is one batch behind), else it takes a copy. ``sparse``: send the
    thesis chip's words as ``raw_sparse`` messages (only the words that are not their
    position's plain no_hit word, with their index: docs/streaming.md "Sparse raw words"),
    made in the one pass that cuts the fan-out's ranges; the journal still takes every
    word. After the stops it waits up to ``end_wait_s`` for each consumer to hang up
    (:mod:`pipeline.stream.hangup`)."""
    import numpy as np

    from pipeline.stream.fanout import TdcSplitter
    from pipeline.stream.rawwire import RawWordsEncoder, sparse_frames, sparse_parts
    from schemas.words import RAW_WORDS

    pushes = [push] if isinstance(push, str) else list(push)
    encoder = RawWordsEncoder()
    splitter = None
    if split is not None:
        if len(split) != len(pushes):
            raise ValueError(f"{len(split)} TDC ranges for {len(pushes)} endpoints")
        splitter = TdcSplitter(n_tdc, split)
    elif len(pushes) != 1:
        raise ValueError("several endpoints need TDC ranges to split by")
    ctx, own = own_context(context)
    token = token if token is not None else wire.load_token()
    txs = [_socket(ctx, zmq.PUSH, hwm) for _ in pushes]
    consumers = Consumers(txs)  # (watched from before they connect)
    for tx, ep in zip(txs, pushes, strict=True):
        connect(tx, ep)
    gone = [False] * len(txs)
    beat = Metrics(metrics, step_id, ctx, token=token)
    halt = threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: halt.set())
    sent, seq, t0, blocked = 0, 0, time.perf_counter(), 0.0
    import datetime as dt

    # the run's date partitions the datasets: fixed at the run's start (the daemon passes
    # it to a restarted source, so a run never straddles two partitions)
    extra = {"date": date or dt.date.today().isoformat(),
             **({"window_ns": window_ns} if window_ns is not None else {})}
    # The journal is written by a thread of its own, one batch ahead: batch i is sent only
    # once its write has returned, but while it is being sent batch i + 1 is written.
    writer = ThreadPoolExecutor(1, "journal") if journal is not None else None
    pending = None  # (messages, journal write) of the batch before

    paused = {}  # the journal writer's "disk full" while it waits (read by this thread)

    def append(first, words, sparse=None):
        # a full disk pauses the run (the source is deterministic: nothing is lost by
        # waiting); a signal while waiting ends it after the last journaled batch
        from pipeline.stream.journal import is_disk_full

        wait = 0.2
        while True:
            try:
                journal.append(first, words, sparse=sparse)
                paused.clear()
                return
            except OSError as exc:
                if not is_disk_full(exc) or halt.is_set():
                    raise
                paused["reason"] = f"disk full: {exc}"
                time.sleep(wait)
                wait = min(2 * wait, 5.0)

    def send_pending():
        nonlocal blocked, pending
        msgs, wrote = pending
        while wrote is not None:
            try:
                wrote.result(timeout=1.0)
                break
            except TimeoutError:
                if paused:
                    beat.beat(force=True, state="paused", reason=paused.get("reason"),
                              sent=seq, words=sent)
        for tx, frames in zip(txs, msgs, strict=True):
            tb = time.perf_counter()
            while not tx.poll(200, zmq.POLLOUT):  # a consumer behind: waiting, alive (the
                consumers.keep()
                beat.beat(state="blocked", sent=seq, words=sent,  # daemon's deadline)
                          blocked_s=round(blocked + time.perf_counter() - tb, 3))
            # the words' frame (0.1-4 MiB) handed to ZeroMQ without a copy: each is a new
            # buffer the source never writes again (pyzmq copies frames under 64 KiB: the
            # header)
            tx.send_multipart(frames, copy=False)
            blocked += time.perf_counter() - tb
        pending = None

    try:
        for first, words in batches:
            if halt.is_set():  # a signal: end the run cleanly after the last whole batch
                break
            if seq == 0:  # the rate's clock starts with the first batch (a simulator's
                t0 = time.perf_counter()  # first one can take seconds: compiling)
            words = np.asarray(words)
            if words.dtype not in (np.dtype("<u4"), np.dtype(">u4")):
                words = words.astype(np.uint32)
            whole, cut = sparse_parts(words, first, n_tdc, split) if sparse else (None, None)
            if writer is not None:  # (a copy unless the words outlive the write)
                # the sparse form is the journal's frame too (one pass over the words)
                wrote = writer.submit(append, first, words if stable >= 2 else
                                      words.astype(">u4"), whole)
            else:
                wrote = None
            parts = splitter.views(first, words) if splitter else [(first, words)]
            if sparse:  # a fan-out's ranges cut from the one pass's result
                parts = [(f, sw) for (f, _), sw in zip(parts, cut, strict=True)]
            msgs = []
            for (f, w), rng in zip(parts, split or [(0, n_tdc)], strict=True):
                head = {"kind": "data", "schema": RAW_WORDS.name,
                        "version": RAW_WORDS.version, "run": run, "seq": seq, "step": step_id,
                        "first_word": int(f), "n_tdc": rng[1] - rng[0],
                        "n_tdc_total": n_tdc, "tdc_range": list(rng),
                        "t_laser_win_ns": t_laser_win_ns, **extra}
                msgs.append(sparse_frames(head, w, token) if sparse else
                            encoder.frames(head, w, token))  # (whole words: one copy)
            if pending is not None:
                send_pending()
            pending = (msgs, wrote)
            if seq == 0:  # in the stage's log: when the run's words began to flow
                _log(f"first batch sent at {time.time():.6f}")
            sent += words.size
            seq += 1
            consumers.keep()
            beat.beat(state="running", sent=seq, words=sent, blocked_s=round(blocked, 3))
            if rate_words_s:
                ahead = sent / rate_words_s - (time.perf_counter() - t0)
                if ahead > 0:
                    time.sleep(ahead)
        if pending is not None:
            send_pending()
        if writer is not None:
            writer.shutdown(wait=True)
            writer = None
        at_end = consumers.at_end()  # (before a consumer can end on the journal's end)
        if journal is not None:  # the run's end is on disk before anyone hears of it
            journal.close(complete=not halt.is_set())  # (a signal: a stop, resumable)
            journal = None
        for tx in txs:
            tx.send_multipart(wire.encode({"kind": "stop", "schema": RAW_WORDS.name,
                                           "version": RAW_WORDS.version, "run": run,
                                           "seq": seq, "step": step_id, "words": sent},
                                          None, token))
        done = {"sent": seq, "words": sent, "blocked_s": round(blocked, 3)}
        beat.beat(force=True, state="finished", **done)
        # each worker's hang-up acknowledges its stop (hangup.py); a signal ended the run,
        # not this wait: the stops of an interrupted run are waited for the same
        gone = consumers.wait(at_end, end_wait_s, beat, **done)
        if consumers.unacknowledged:
            _log(f"{consumers.unacknowledged} of {len(txs)} consumers did not hang up "
                 f"within {end_wait_s:g} s of their stop")
            beat.beat(force=True, state="finished", unacknowledged=consumers.unacknowledged,
                      **done)
    finally:
        if writer is not None:
            writer.shutdown(wait=True)
        if journal is not None:
            journal.close()
        beat.close()
        consumers.close()
        # wait (bounded) for a restarted consumer to take what is queued, the stop included
        for tx, left in zip(txs, gone, strict=True):
            tx.close(linger=0 if left else 60_000)
        if own:
            end_context(ctx)
    return sent


class ParquetSink:
    """Writes each histograms or ranges message as a file of a Hive-partitioned dataset,
    atomically: ``OUT/<schema>/date=YYYY-MM-DD/run=RUN/part-<measurement>-t<first TDC>``.
    The name depends only on the message, so a measurement sent twice (a stage restarted
    between sending and checkpointing) lands on the same file: no double count."""

    in_spec = {HISTOGRAMS.name: HISTOGRAMS, RANGES.name: RANGES}
    out_spec = HISTOGRAMS

    def __init__(self, out: str | Path, step_id: str = "sink", cloud=None):
        self.out = Path(out)
        self.step_id = step_id
        self.files = 0                 #: files written (a count: the daemon runs for weeks)
        self.last: Path | None = None
        #: (format, geometry): each ranges message also as a point cloud (issue 35)
        self.cloud = cloud

    def path(self, header: dict) -> Path:
        """The message's file; a header whose run, date or schema could lead outside the
        output directory is refused (WireError ``bad_path``), whoever sent it."""
        import datetime as dt

        day = header.get("date") or dt.date.today().isoformat()
        first = (header.get("tdc_range") or [0])[0]
        for key, value, pattern in (("schema", header["schema"], wire.ID_PATTERN),
                                    ("run", header["run"], wire.ID_PATTERN),
                                    ("date", day, wire.DATE_PATTERN)):
            if not isinstance(value, str) or not pattern.fullmatch(value):
                raise wire.WireError("bad_path", f"header {key} = {value!r:.80} is not a "
                                                 "safe path component")
        path = (self.out / header["schema"] / f"date={day}" / f"run={header['run']}"
                / f"part-{int(header['seq']):06d}-t{int(first):03d}.parquet")
        root = self.out.resolve()
        if not path.resolve().is_relative_to(root):
            raise wire.WireError("bad_path", f"{path} resolves outside {root}")
        return path

    def process(self, header: dict, batch) -> list:
        import pyarrow as pa
        import pyarrow.parquet as pq

        path = self.path(header)
        table = pa.Table.from_batches([batch])
        meta = {}
        if isinstance(header.get("class_counts"), dict):  # the run's accounting reads it back
            meta[b"tcspc.class_counts"] = json.dumps(header["class_counts"]).encode()
        if header.get("schema") == HISTOGRAMS.name and "measurement_index" in header:
            # what the reconciliation checks against the journal: a measurement partial
            # (the stream stopped inside it) is replaced when the rest arrives
            meta[b"tcspc.measurement"] = json.dumps(
                {k: header[k] for k in ("partial", "cycles", "words") if k in header}).encode()
        if header.get("calibration_id"):  # ranges: the calibration's identity (issue 39)
            meta[b"tcspc.calibration_id"] = str(header["calibration_id"]).encode()
        if isinstance(header.get("lsb_drift"), dict):  # ranges: the stream's LSB tracking
            meta[b"tcspc.lsb_drift"] = json.dumps(header["lsb_drift"]).encode()
        if isinstance(header.get("spatial_missing"), list):  # ranges: a frame ranged
            # without some workers' parts (the reconciliation ranges it again)
            meta[b"tcspc.spatial_missing"] = json.dumps(header["spatial_missing"]).encode()
        if meta:
            table = table.replace_schema_metadata({**(table.schema.metadata or {}), **meta})
        buf = pa.BufferOutputStream()
        pq.write_table(table, buf)
        # (from the output root's descriptor: no link followed, no temporary planted)
        write_under(self.out, path.relative_to(self.out), buf.getvalue())
        self.files += 1
        self.last = path
        if self.cloud is not None and header.get("schema") == RANGES.name:
            self._write_cloud(header, table, path)
        return []

    def _write_cloud(self, header: dict, table, path: Path) -> None:
        """OUT/pointcloud/date=.../run=.../<the parquet file's name>.FMT, the measurement
        stamped at the time it is written (a stream's ranges carry no acquisition time)."""
        import time

        from pipeline.io import pointcloud

        fmt, geom = self.cloud
        rel = path.relative_to(self.out / header["schema"])
        dest = (self.out / "pointcloud" / rel).with_suffix(f".{fmt}")
        names = dict.fromkeys(table.column("measurement").to_pylist())
        now = time.time_ns()
        clouds, _ = pointcloud.clouds(table, geom, {n: now for n in names})
        pointcloud.write(fmt, clouds, geom, dest)
        self.clouds = getattr(self, "clouds", 0) + 1

    def finish(self, header: dict) -> list:
        return []
