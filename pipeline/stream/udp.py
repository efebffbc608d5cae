"""The ingest: the FPGA's UDP datagrams in, journaled raw-word batches out.

Binds 127.0.0.1 unless told otherwise. Every datagram is accounted for: taken (its words
journaled to capture segments before they are passed on), a duplicate (counted, dropped),
late (it came after its reorder window closed: counted and quarantined), or rejected by
reason and quarantined. UDP reorders and duplicates, so datagrams are reassembled by first
cycle in a bounded reorder window and each cycle is journaled once, in order; cycles no
datagram brought are a gap (counted), and sequence numbers never seen are lost datagrams.
Every header field is bounded against the run: a cycle or sequence number beyond the
window (``max_jump_cycles``, ``max_jump_datagrams``), another TDC count or gate, is a
rejected datagram, never a gap to fill.
"""

from __future__ import annotations

import queue
import select
import socket
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zmq

from pipeline.stream import datagram, wire
from pipeline.stream.journal import JournalWriter
from pipeline.stream.stage import Quarantine, _socket, connect, end_context, own_context
from schemas.words import RAW_WORDS

BATCH_WORDS = 1 << 18  # 1 MiB messages
REORDER_WINDOW = 64            #: datagrams held to put reordered ones back in place
REORDER_LINGER_S = 0.5         #: after the last datagram, wait this long for stragglers
MAX_JUMP_CYCLES = 1 << 20      #: a datagram this far past the run's newest cycle is refused
MAX_JUMP_DATAGRAMS = 1 << 16   #: ... and this far in sequence number
GATE_PS = (1_000, 10_000_000)  #: a gate outside 1 ns .. 10 us is not a gate
RING_DATAGRAMS = 4096          #: received, not yet journaled (<= 256 MiB of datagrams)
RX_BATCH = 64                  #: datagrams one hand-off to the ring carries at most
FLUSH_S = 0.01                 #: a partial batch is journaled and sent after this long
SEND_QUEUE = 64                #: journaled messages waiting for a slow stage downstream
QUORUM = 3                     #: datagrams that must agree before they set the reference
QUORUM_HOLD = 256              #: candidates held while no quorum is reached
RCVBUF_BYTES = 64 << 20        #: the kernel's buffer: ~0.4 s of 40 M words/s off the CPU


def _signed32(d: int) -> int:
    d &= 0xFFFFFFFF
    return d - (1 << 32) if d >= 1 << 31 else d


def max_cycles(n_tdc: int) -> int:
    """The most cycles one datagram of ``n_tdc`` TDCs can hold (a UDP payload)."""
    return max(1, (datagram.MAX_PAYLOAD - datagram.HEADER.size) // (4 * n_tdc))


def consistent(ds: int, dc: int, n_tdc: int) -> bool:
    """Can two datagrams of one stream be ``ds`` sequence numbers and ``dc`` cycles apart?
    Every datagram holds at least one cycle and at most a UDP payload's, so the cycles
    between them are within [|ds|, |ds| max_cycles], on the same side."""
    if ds == 0:
        return dc == 0
    if ds < 0:
        ds, dc = -ds, -dc
    return ds <= dc <= ds * max_cycles(n_tdc)


class Reference:
    """The run's reference (its gate, TDC count, and where sequence numbers and cycles
    stand), never taken from whichever datagram comes first: from the configuration
    (``gate_ps``, ``n_tdc``, ``first_seq``: the run's first datagram is ``first_seq`` at
    cycle 0), from the journal of the run a restarted ingest resumes (``anchor``: the newest
    journaled datagram's sequence number and first cycle), or from a quorum: ``quorum``
    datagrams with the same gate and TDC count whose sequence numbers and cycles could
    belong to one stream (:func:`consistent`), and that agree with the configuration and the
    anchor. Until then datagrams are held (at most QUORUM_HOLD: beyond, the oldest is a
    stray); when the quorum forms, the held datagrams that agree with it are taken in their
    arrival order, the others are strays (counted, quarantined)."""

    def __init__(self, quorum: int = QUORUM, n_tdc: int | None = None,
                 gate_ps: int | None = None, anchor: tuple[int, int] | None = None):
        self.quorum, self.n_tdc, self.gate_ps, self.anchor = quorum, n_tdc, gate_ps, anchor
        self.held: list[tuple[datagram.Datagram, bytes]] = []

    def _fits(self, d: datagram.Datagram) -> bool:
        if (self.n_tdc is not None and d.n_tdc != self.n_tdc) or (
                self.gate_ps is not None and d.t_laser_win_ps != self.gate_ps):
            return False
        if self.anchor is None:
            return True
        seq, cycle = self.anchor
        return consistent(_signed32(d.seq - seq), d.first_cycle - cycle, d.n_tdc)

    @staticmethod
    def agree(a: datagram.Datagram, b: datagram.Datagram) -> bool:
        return (a.n_tdc == b.n_tdc and a.t_laser_win_ps == b.t_laser_win_ps
                and consistent(_signed32(b.seq - a.seq), b.first_cycle - a.first_cycle,
                               a.n_tdc))

    def offer(self, d: datagram.Datagram, data: bytes) -> tuple[list | None, list]:
        """Hold ``d``: ``(taken, strays)``, ``taken`` None while no quorum has formed, else
        the held datagrams (``(d, data)``) that agree with it, in arrival order."""
        strays = []
        if not self._fits(d):
            return None, [(d, data)]
        self.held.append((d, data))
        # distinct datagrams: a stray sent three times is not a quorum
        group = {c[0].seq for c in self.held if self.agree(d, c[0])}
        if len(group) >= self.quorum:
            return self._fix(d)
        if len(self.held) > QUORUM_HOLD:
            strays.append(self.held.pop(0))
        return None, strays

    def settle(self) -> tuple[list, list]:
        """The stream's end without a quorum: the largest group that agrees (the earliest of
        equals) is the run's; the rest are strays."""
        if not self.held:
            return [], []
        best = max(self.held, key=lambda c: len({o[0].seq for o in self.held
                                                  if self.agree(c[0], o[0])}))
        return self._fix(best[0])

    def _fix(self, d: datagram.Datagram) -> tuple[list, list]:
        taken = [c for c in self.held if self.agree(d, c[0])]
        strays = [c for c in self.held if not self.agree(d, c[0])]
        self.held = []
        self.n_tdc, self.gate_ps = d.n_tdc, d.t_laser_win_ps
        return taken, strays


def resume_state(journal: str | Path, run: str) -> dict | None:
    """Where a restarted ingest takes the run up (from the journal's index: each chunk, a
    batch of consecutive datagrams, records their unwrapped sequence numbers: ``seq`` the
    highest, ``seq_cycle`` its first cycle, ``seq_lo`` the lowest, ``datagrams`` how many;
    a chunk of one datagram, as an ingest before batches wrote them, has ``seq`` alone), or
    None for a run not yet journaled by a
    UDP ingest: ``next_cycle`` (the end of the journaled stream), ``seq_lo``/``seq_hi``,
    ``taken`` (datagrams journaled), ``late`` (datagrams that came too late, counted by the
    ingest that journaled the last chunk), ``anchor`` (the newest datagram's sequence number
    and first cycle), ``gap_cycles``, ``n_tdc`` and ``gate_ps`` (the run's meta)."""
    from pipeline.stream.journal import _entries, run_meta

    entries = [e for e in _entries(Path(journal) / f"{run}.index.jsonl")
               if "first_word" in e]
    meta = run_meta(journal, run)
    seqs = [e for e in entries if "seq" in e]
    if not seqs or "n_tdc" not in meta:
        return None
    n = int(meta["n_tdc"])
    top = max(seqs, key=lambda e: e["seq"])
    end = max(e["first_word"] + e["words"] for e in entries)
    return {"next_cycle": end // n, "seq_lo": min(e.get("seq_lo", e["seq"]) for e in seqs),
            "seq_hi": top["seq"], "taken": sum(int(e.get("datagrams", 1)) for e in seqs),
            "late": int(seqs[-1].get("late", 0)),
            "anchor": (top["seq"], top.get("seq_cycle", top["first_word"] // n)),
            "gap_cycles": end // n - sum(e["words"] for e in entries) // n, "n_tdc": n,
            "gate_ps": round(float(meta["t_laser_win_ns"]) * 1000)}


@dataclass
class IngestStats:
    datagrams: int = 0        #: received (every one, whatever became of it)
    accepted: int = 0         #: journaled and passed on
    words: int = 0
    duplicates: int = 0       #: same sequence number and cycles as one already taken
    late: int = 0             #: arrived after its reorder window closed (quarantined)
    lost_datagrams: int = 0   #: sequence numbers never received within the run's span
    gap_cycles: int = 0       #: cycles no datagram brought
    rejected: Counter = field(default_factory=Counter)
    quarantine_dropped: int = 0
    ring_dropped: int = 0     #: received while the ring was full (journal too slow)
    deferred_messages: int = 0  #: journaled, not sent (downstream stalled; it backfills)
    deferred_words: int = 0
    paused_s: float = 0.0     #: time intake waited for a full disk
    unjournaled_words: int = 0  #: taken, but a stop came while the disk was full
    messages: int = 0
    journal: list[str] = field(default_factory=list)  #: segment files written

    def fields(self) -> dict:
        return {"received": self.datagrams, "accepted": self.accepted, "sent": self.messages,
                "words": self.words, "duplicates": self.duplicates, "late": self.late,
                "lost_datagrams": self.lost_datagrams, "gap_cycles": self.gap_cycles,
                "rejected": dict(self.rejected),
                "quarantine_dropped": self.quarantine_dropped,
                "ring_dropped": self.ring_dropped, "deferred_messages": self.deferred_messages,
                "deferred_words": self.deferred_words, "paused_s": round(self.paused_s, 1),
                "unjournaled_words": self.unjournaled_words}


def udp_socket(address: str = "127.0.0.1:0") -> socket.socket:
    """A bound UDP socket; ``host:port`` (port 0 picks a free one). Its kernel receive
    buffer is what carries the stream while the ingest is off the CPU (a loaded machine):
    RCVBUF_BYTES where the process may set it past ``net.core.rmem_max``
    (``SO_RCVBUFFORCE``, CAP_NET_ADMIN), else as much of it as ``rmem_max`` allows."""
    host, port = address.rsplit(":", 1)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.setsockopt(socket.SOL_SOCKET, getattr(socket, "SO_RCVBUFFORCE", 33), RCVBUF_BYTES)
    except OSError:  # (not permitted: the sysctl's limit, docs/operations.md)
        s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RCVBUF_BYTES)
    s.bind((host, int(port)))
    return s


class Reassembler:
    """Datagrams in arrival order in, runs of whole cycles in stream order out.

    Holds up to ``window`` datagrams keyed by first cycle; the one that continues the stream
    is released at once. When the window is full, the hole before the oldest held datagram
    is given up as a gap (its cycles counted) and the stream moves on. Sequence numbers are
    unwrapped (32-bit) against the newest seen; the lost count is the span of sequence
    numbers minus those taken.
    """

    def __init__(self, window: int = REORDER_WINDOW, max_jump_cycles: int = MAX_JUMP_CYCLES,
                 max_jump_datagrams: int = MAX_JUMP_DATAGRAMS):
        if window < 1:
            raise ValueError(f"reorder window must be >= 1 datagram, found {window}")
        self.window, self.max_jump_cycles = window, max_jump_cycles
        self.max_jump_datagrams = max_jump_datagrams
        self.held: dict[int, tuple[int, datagram.Datagram]] = {}  # first cycle -> (seq, d)
        self.next_cycle = 0          #: cycles before this are journaled or given up
        self.newest_cycle = 0        #: end of the newest datagram accepted
        self.seq_lo = self.seq_hi = None  # unwrapped span of accepted sequence numbers
        self.seqs_seen = 0  # taken or late: received, whatever became of it
        self.recent: deque = deque(maxlen=4 * window)  # (seq, first cycle) released
        self.recent_set: set = set()
        self.gap_cycles = 0
        self.newest: tuple[int, int] | None = None  #: (seq, first cycle) of the newest taken

    def resume(self, state: dict) -> None:
        """Take the run up where the journal has it (:func:`resume_state`)."""
        self.next_cycle = self.newest_cycle = state["next_cycle"]
        self.seq_lo, self.seq_hi = state["seq_lo"], state["seq_hi"]
        self.seqs_seen = state["taken"] + state["late"]
        self.gap_cycles = state["gap_cycles"]
        self.newest = state["anchor"]

    def rejoin(self, seq: int, first_cycle: int) -> None:
        """The stream went on while this ingest was down: a quorum of datagrams consistent
        with the journal's newest says where it is now. The cycles in between are a gap and
        their datagrams lost (the sequence span counts them), however long the outage."""
        seq = self._unwrap(seq)
        if first_cycle > self.next_cycle:
            self.gap_cycles += first_cycle - self.next_cycle
            self.next_cycle = self.newest_cycle = first_cycle
        if self.seq_hi is not None and seq - 1 > self.seq_hi:
            self.seq_hi = seq - 1  # (their sequence numbers are a span never received)

    def _unwrap(self, seq: int) -> int:
        if self.seq_hi is None:
            return seq
        d = (seq - self.seq_hi) & 0xFFFFFFFF
        return self.seq_hi + (d - (1 << 32) if d >= 1 << 31 else d)

    def lost(self) -> int:
        if self.seq_hi is None:
            return 0
        return max(0, self.seq_hi - self.seq_lo + 1 - self.seqs_seen)

    def offer(self, d: datagram.Datagram) -> tuple[str, list]:
        """Take one checked datagram: ``("taken" | "duplicate" | "late", released)``,
        ``released`` the datagrams now in stream order. Out-of-window fields raise
        DatagramError."""
        seq = self._unwrap(d.seq)
        if self.seq_hi is not None and abs(seq - self.seq_hi) > self.max_jump_datagrams:
            raise datagram.DatagramError("seq_out_of_window", f"sequence {d.seq} is "
                                         f"{seq - self.seq_hi:+d} from the newest")
        if d.first_cycle - max(self.newest_cycle, self.next_cycle) > self.max_jump_cycles:
            raise datagram.DatagramError("cycle_out_of_window", f"first cycle {d.first_cycle}"
                                         f" is beyond the run's newest {self.newest_cycle} "
                                         f"+ {self.max_jump_cycles}")
        if self.newest is not None and not consistent(seq - self.newest[0], d.first_cycle
                                                      - self.newest[1], d.n_tdc):
            raise datagram.DatagramError("inconsistent", f"sequence {d.seq} at first cycle "
                                         f"{d.first_cycle} cannot follow the run's newest, "
                                         f"{self.newest[0]} at {self.newest[1]}")
        key = (seq, d.first_cycle)
        if key in self.recent_set or (d.first_cycle in self.held
                                      and self.held[d.first_cycle][0] == seq):
            return "duplicate", []
        if d.first_cycle < self.next_cycle:
            if self.seq_lo is not None and self.seq_lo <= seq <= self.seq_hi:
                self.seqs_seen += 1  # it came (too late): not a lost datagram
            return "late", []
        if d.first_cycle in self.held:
            raise datagram.DatagramError("conflict", f"cycle {d.first_cycle} again with "
                                         f"sequence {d.seq}, held with another")
        self.held[d.first_cycle] = (seq, d)
        self.seqs_seen += 1
        self.seq_lo = seq if self.seq_lo is None else min(self.seq_lo, seq)
        self.seq_hi = seq if self.seq_hi is None else max(self.seq_hi, seq)
        self.newest_cycle = max(self.newest_cycle, d.first_cycle + d.n_cycles)
        if self.newest is None or seq > self.newest[0]:
            self.newest = (seq, d.first_cycle)
        out = self._release()
        while len(self.held) > self.window:  # the window is full: give up the hole
            out += self._skip()
        return "taken", out

    def _release(self) -> list:
        out = []
        while self.next_cycle in self.held:
            seq, d = self.held.pop(self.next_cycle)
            out.append((seq, d))
            if len(self.recent) == self.recent.maxlen:
                self.recent_set.discard(self.recent[0])
            self.recent.append((seq, d.first_cycle))
            self.recent_set.add((seq, d.first_cycle))
            self.next_cycle += d.n_cycles
        return out

    def _skip(self) -> list:
        first = min(self.held)
        self.gap_cycles += first - self.next_cycle
        self.next_cycle = first
        return self._release()

    def drain(self) -> list:
        """The run's end: release everything held, the holes counted as gaps."""
        out = []
        while self.held:
            out += self._skip()
        return out


def run_udp_ingest(sock: socket.socket, push: str | list[str], *, run: str = "udp",
                   journal: str | Path | None = None, segment_words: int = 1 << 24,
                   quarantine: str | Path | None = None, stop: threading.Event | None = None,
                   idle_s: float | None = None, context: zmq.Context | None = None,
                   split: list[tuple[int, int]] | None = None, metrics: str | None = None,
                   date: str | None = None, compression: str | None = "zstd",
                   n_tdc: int | None = None, reorder_window: int = REORDER_WINDOW,
                   max_jump_cycles: int = MAX_JUMP_CYCLES,
                   max_jump_datagrams: int = MAX_JUMP_DATAGRAMS,
                   linger_s: float = REORDER_LINGER_S, token: str | None = None,
                   ring_datagrams: int = RING_DATAGRAMS, send_queue: int = SEND_QUEUE,
                   gate_ps: int | None = None, first_seq: int | None = None,
                   quorum: int = QUORUM, rx_batch: int = RX_BATCH,
                   flush_s: float = FLUSH_S, sparse: bool = False) -> IngestStats:
    """Receive until a datagram flagged last (and the reorder window is settled), ``stop``,
    or ``idle_s`` without data.

    ``split``: TDC ranges, one per endpoint of ``push`` (a fan-out by TDC range; datagrams
    hold whole cycles, so every batch splits cleanly). ``n_tdc``: the chip's TDC count
    (None: the first datagram's). ``reorder_window``: datagrams held to undo reordering.
    ``max_jump_cycles`` / ``max_jump_datagrams``: how far past the newest a first cycle or
    sequence number may jump before the datagram is refused. ``token``: the run's token
    (default: $TCSPC_TOKEN_FILE). ``gate_ps``, ``first_seq``: the run's gate and first
    sequence number, when the configuration knows them; otherwise the reference comes from
    a ``quorum`` of datagrams that agree (:class:`Reference`), never from the first one.

    With a journal that already holds the run (a restarted ingest), the run is taken up
    where the journal has it (:func:`resume_state`): its sequence numbers, cycles, gate and
    TDC count; the datagrams that came while the ingest was down are counted as lost and
    their cycles as a gap, exactly, however long it was down.

    Three threads, so receiving never waits for downstream: a receiver reads every datagram
    that is ready (up to ``rx_batch``) and hands them to a ring of ``ring_datagrams`` as one
    list (when full, because the journal cannot keep up, a datagram is counted in
    ``ring_dropped``); this thread checks and reassembles the datagrams one by one, and
    journals the released ones in batches, one journal chunk (and
    one message) per batch of consecutive cycles, of BATCH_WORDS or what came within
    ``flush_s``; a sender passes them on. With a journal, a batch that finds the
    send queue (``send_queue`` messages) full is not sent but counted
    (``deferred_messages``): its words are in the journal, and the worker downstream fills
    the hole from there when the next batch or the stop reaches it. Back-pressure thus
    stops at the journal. Without a journal this thread waits for the sender instead.
    ``sparse``: send each batch as ``raw_sparse`` (docs/streaming.md "Sparse raw words"),
    whose one pass over the words also makes the journal's ``zstd-nohit`` frame."""
    import datetime as dt

    from pipeline.stream.fanout import TdcSplitter
    from pipeline.stream.metrics import Metrics
    from pipeline.stream.rawwire import RawWordsEncoder, sparse_frames, sparse_parts

    ctx, own = own_context(context)
    token = token if token is not None else wire.load_token()
    pushes = [push] if isinstance(push, str) else list(push)
    txs = []
    for ep in pushes:
        tx = _socket(ctx, zmq.PUSH, 4)
        connect(tx, ep)
        txs.append(tx)
    if (split is not None and len(split) != len(txs)) or (split is None and len(txs) != 1):
        raise ValueError("one TDC range per endpoint")
    beat = Metrics(metrics, "source", ctx, token=token)
    date = date or dt.date.today().isoformat()
    stop = stop or threading.Event()
    stats = IngestStats()
    reasm = Reassembler(reorder_window, max_jump_cycles, max_jump_datagrams)
    resumed = resume_state(journal, run) if journal is not None else None
    ref = Reference(quorum, n_tdc, gate_ps)
    if resumed is not None:  # a restarted ingest: the journal is the truth
        reasm.resume(resumed)
        stats.late = resumed["late"]
        n_tdc, gate_ps = resumed["n_tdc"], resumed["gate_ps"]
        ref = Reference(quorum, n_tdc, gate_ps, anchor=resumed["anchor"])
    elif first_seq is not None and n_tdc is not None and gate_ps is not None:
        # the configuration fixes the reference: the run's first datagram, at cycle 0
        reasm.seq_lo, reasm.seq_hi = first_seq, first_seq - 1
        reasm.newest = (first_seq, 0)
        ref = None
    elif first_seq is not None:
        ref.anchor = (first_seq, 0)
    quar = Quarantine(quarantine)
    ring: queue.Queue = queue.Queue()  # lists of datagrams, bounded by ring_fill's count
    ring_fill, ring_lock = [0], threading.Lock()
    sendq: queue.Queue = queue.Queue(maxsize=send_queue)
    halt_rx, abort_tx = threading.Event(), threading.Event()

    def receiver():
        # what is ready, read at once (up to rx_batch; recvmmsg's batching, in Python):
        # one hand-off per list, not per datagram
        size = datagram.MAX_PAYLOAD + 1
        sock.setblocking(False)
        poll = select.poll()
        poll.register(sock, select.POLLIN)
        closed = False
        while not halt_rx.is_set() and not closed:
            try:
                if not poll.poll(200):
                    continue
            except OSError:
                return
            items = []
            try:
                while len(items) < rx_batch:
                    items.append(sock.recv(size))
            except BlockingIOError:
                pass
            except OSError:
                closed = True  # the socket was closed under us: the run is over
            with ring_lock:
                room = max(0, ring_datagrams - ring_fill[0])
                if len(items) > room:
                    stats.ring_dropped += len(items) - room  # (one writer: this thread)
                    items = items[:room]
                ring_fill[0] += len(items)
            if items:
                ring.put(items)

    def sender():
        while True:
            item = sendq.get()
            if item is None:
                return
            for tx, frames in zip(txs, item, strict=True):
                while not tx.poll(200, zmq.POLLOUT):
                    if abort_tx.is_set():
                        return
                tx.send_multipart(frames, zmq.NOBLOCK)

    rx_thread = threading.Thread(target=receiver, name="udp-receive", daemon=True)
    tx_thread = threading.Thread(target=sender, name="udp-send", daemon=True)
    rx_thread.start()
    tx_thread.start()
    pending: list[np.ndarray] = []   # released, consecutive: the next batch's words
    pending_seqs: list[tuple[int, int]] = []  # ... its datagrams' (seq, first cycle)
    pending_first = None
    pending_words = 0
    pending_t0 = 0.0
    next_word = None
    writer: JournalWriter | None = None
    idle = 0.0
    last_end = None   # the cycle after the datagram flagged last, once it came

    encoder = RawWordsEncoder()
    splitter = None  # (made at the first batch: a run's n_tdc may come from the stream)

    def flush():
        # the batch: journaled as one chunk (its index line carries its datagrams' sequence
        # numbers, from which a restarted ingest resumes), then sent
        nonlocal pending, pending_seqs, pending_first, pending_words, splitter
        if not pending:
            return
        # the datagrams' big-endian words, joined by one copy: the journal compresses them
        # as they are, the message swaps and cuts them by TDC range in its one copy
        # (pipeline.stream.rawwire)
        words = pending[0] if len(pending) == 1 else np.concatenate(pending)
        seqs, first = pending_seqs, pending_first
        pending, pending_seqs, pending_first, pending_words = [], [], None, 0
        top = max(seqs)
        extra = {"seq": top[0], "seq_cycle": top[1], "seq_lo": min(seqs)[0],
                 "datagrams": len(seqs), "late": stats.late}
        whole = cut = None
        if sparse:  # one pass: the journal's frame and the messages are made from it
            whole, cut = sparse_parts(words, first, n_tdc, split)
        if journal is not None and not journal_words(first, words, extra, whole):
            stats.unjournaled_words += int(words.size)  # a stop came while the disk was
            return                                       # full: counted, never sent
        stats.words += int(words.size)
        stats.accepted += len(seqs)
        ranges = split or [(0, n_tdc)]
        if split and (splitter is None or splitter.n_tdc != n_tdc):
            splitter = TdcSplitter(n_tdc, split)  # (n_tdc known from the stream)
        parts = splitter.views(first, words) if split else [(first, words)]
        if sparse:
            parts = [(f, sw) for (f, _), sw in zip(parts, cut, strict=True)]
        item = []
        for (f, w), rng in zip(parts, ranges, strict=True):
            head = {"kind": "data", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
                    "run": run, "seq": stats.messages, "step": "ingest",
                    "first_word": int(f), "n_tdc": rng[1] - rng[0], "n_tdc_total": n_tdc,
                    "tdc_range": list(rng), "t_laser_win_ns": gate_ps / 1000, "date": date}
            item.append(sparse_frames(head, w, token) if sparse else
                        encoder.frames(head, w, token))
        if journal is None:
            sendq.put(item)  # nothing to fill a hole from: wait for downstream
        else:
            try:
                sendq.put_nowait(item)
            except queue.Full:  # downstream stalled: the journal has the words
                stats.deferred_messages += 1
                stats.deferred_words += int(words.size)
        stats.messages += 1

    def take(released):
        # released in stream order: batched (each cycle once), journaled and sent by flush
        nonlocal pending_first, pending_words, pending_t0, next_word
        seq, d = released
        first = d.first_cycle * n_tdc
        if next_word is not None and first != next_word:
            flush()  # a gap: the next batch starts where the words do
        if pending_first is None:
            pending_first, pending_t0 = first, time.monotonic()
        pending.append(d.words)
        pending_seqs.append((seq, d.first_cycle))
        pending_words += d.words.size
        next_word = first + d.words.size
        if pending_words >= BATCH_WORDS:
            flush()

    def journal_words(first: int, words: np.ndarray, extra: dict, whole=None) -> bool:
        # a full disk pauses intake here (the receive thread goes on into the ring, whose
        # overflow is counted): retried until there is room, or False at a stop
        from pipeline.stream.journal import is_disk_full

        nonlocal writer
        wait = 0.2
        while True:
            try:
                if writer is None:
                    writer = JournalWriter(journal, run, n_tdc, gate_ps / 1000,
                                           segment_words=segment_words,
                                           compression=compression)
                writer.append(first, words, extra, sparse=whole)  # (resumed from there)
                return True
            except OSError as exc:
                if not is_disk_full(exc):
                    raise
                if stop.is_set():
                    return False
                stats.paused_s += wait
                beat.beat(force=True, state="paused", reason=f"disk full: {exc}",
                          **stats.fields())
                time.sleep(wait)
                wait = min(2 * wait, 5.0)

    def reject(reason: str, detail: str, data: bytes):
        stats.rejected[reason] += 1
        try:
            quar.put(reason, data, detail=detail)
        except OSError:
            quar.dropped += 1  # a full disk: counted, not kept
        stats.quarantine_dropped = quar.dropped

    def offer(d: datagram.Datagram, data: bytes) -> None:
        nonlocal last_end
        try:
            verdict, released = reasm.offer(d)
        except datagram.DatagramError as exc:
            reject(exc.reason, str(exc), data)
            return
        if verdict == "duplicate":
            stats.duplicates += 1
            return
        if verdict == "late":
            stats.late += 1
            reject("late", f"cycles {d.first_cycle}.. came after their window closed "
                           f"(the stream is at {reasm.next_cycle})", data)
            return
        for r in released:
            take(r)
        if d.last:
            last_end = d.first_cycle + d.n_cycles

    def stray(d: datagram.Datagram, data: bytes) -> None:
        reject("stray", f"sequence {d.seq}, first cycle {d.first_cycle}, {d.n_tdc} TDCs, "
                        f"gate {d.t_laser_win_ps} ps: not the run's stream", data)

    def fix(group: list) -> None:
        # the reference is fixed: the held datagrams that agree go in, in arrival order
        nonlocal ref, n_tdc, gate_ps, last_end
        if not group:
            return
        n_tdc, gate_ps = group[0][0].n_tdc, group[0][0].t_laser_win_ps
        if resumed is not None:
            first = min(group, key=lambda c: c[0].first_cycle)[0]
            reasm.rejoin(first.seq, first.first_cycle)
        ref = None
        if last_end == -1:
            last_end = None
        for gd, gdata in group:
            offer(gd, gdata)

    def intake(data: bytes) -> None:
        # one datagram, checked against the run (one at a time: a batch's headers read by
        # numpy at once measured slower than struct's per header at every batch size)
        nonlocal last_end
        try:
            d = datagram.decode(data)
            if n_tdc is not None and d.n_tdc != n_tdc:
                raise datagram.DatagramError("n_tdc_mismatch",
                                             f"{d.n_tdc} TDCs, the run has {n_tdc}")
            if not GATE_PS[0] <= d.t_laser_win_ps <= GATE_PS[1] or (
                    gate_ps is not None and d.t_laser_win_ps != gate_ps):
                raise datagram.DatagramError("bad_gate", f"gate {d.t_laser_win_ps} ps "
                                             f"(run: {gate_ps}, bounds {GATE_PS})")
            if d.n_cycles == 0:
                raise datagram.DatagramError("empty", "no cycles")
        except datagram.DatagramError as exc:
            reject(exc.reason, str(exc), data)
            return
        if ref is not None:  # no reference yet: held until a quorum agrees
            group, strays = ref.offer(d, data)
            for sd, sdata in strays:
                stray(sd, sdata)
            if group is None:
                if d.last and ref.held:
                    last_end = -1  # settle after the linger (below)
                return
            fix(group)
            return
        offer(d, data)

    def complete() -> bool:  # the last datagram and everything before it are in
        return (last_end is not None and last_end >= 0 and reasm.next_cycle >= last_end
                and not reasm.held)

    gave_up = False  # on a stage downstream that took nothing for a minute (a journal)
    try:
        while not stop.is_set():
            stats.gap_cycles, stats.lost_datagrams = reasm.gap_cycles, reasm.lost()
            beat.beat(state="running", **stats.fields())
            if last_end == -1 and idle >= linger_s and ref is not None:
                group, strays = ref.settle()  # a run of fewer datagrams than the quorum
                for sd, sdata in strays:
                    stray(sd, sdata)
                last_end = None
                fix(group)
            if complete():
                break
            waited = time.monotonic()
            try:
                batch = ring.get(timeout=flush_s if pending else 0.2)
            except queue.Empty:
                flush()  # a partial batch waits no longer than flush_s
                idle += time.monotonic() - waited
                if reasm.held and idle >= linger_s:  # a quiet stream: nothing will fill
                    for r in reasm.drain():         # the holes; hold no words back
                        take(r)
                    flush()
                if last_end is not None and last_end >= 0 and idle >= linger_s:
                    break  # stragglers of the run's end did not come: gaps
                if idle_s is not None and idle >= idle_s:
                    break
                continue
            with ring_lock:
                ring_fill[0] -= len(batch)
            idle = 0.0
            stats.datagrams += len(batch)
            for k, data in enumerate(batch):
                if complete():  # the rest came after the run's end: counted, not taken
                    stats.rejected["after_end"] += len(batch) - k
                    break
                intake(data)
            if pending and time.monotonic() - pending_t0 >= flush_s:
                flush()
        if ref is not None:  # the run's end without a quorum: the largest group agreeing
            group, strays = ref.settle()
            for sd, sdata in strays:
                stray(sd, sdata)
            fix(group)
        for r in reasm.drain():
            take(r)
        flush()
        stats.gap_cycles, stats.lost_datagrams = reasm.gap_cycles, reasm.lost()
        if writer is not None:  # the run's end is on disk before anyone hears of it
            writer.close()
            stats.journal = [str(p) for p in writer.segments]
            writer = None
        halt_rx.set()
        rx_thread.join()
        stats.datagrams += ring_fill[0]  # came after the end: counted, not taken
        stats.rejected["after_end"] += ring_fill[0]
        if not stats.rejected["after_end"]:
            del stats.rejected["after_end"]
        stop_head = {
            "kind": "stop", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
            "run": run, "seq": stats.messages, "step": "ingest", "words": stats.words,
            "datagrams": stats.datagrams, "lost_datagrams": stats.lost_datagrams,
            "duplicates": stats.duplicates, "late": stats.late,
            "gap_cycles": stats.gap_cycles, "rejected": dict(stats.rejected)}
        try:  # a stage downstream that takes nothing for a minute is given up on: the
            # daemon ends it, and it fetches the words it lacks from the journal
            sendq.put([wire.encode(stop_head, None, token) for _ in txs], timeout=60)
            sendq.put(None, timeout=60)
        except queue.Full:
            gave_up = journal is not None
        tx_thread.join(timeout=0 if gave_up else 60)
        # with a journal, a sender still stuck after that minute is given up on too: its
        # messages are not lingered over for another minute (the stage is ended and reads
        # the journal). Before batches, few and large messages seldom left it stuck.
        gave_up = journal is not None and (gave_up or tx_thread.is_alive())
        beat.beat(force=True, state="finished", **stats.fields())
    finally:
        halt_rx.set()
        abort_tx.set()
        if tx_thread.is_alive():
            try:
                sendq.put_nowait(None)
            except queue.Full:
                pass
            tx_thread.join(timeout=2)
        if writer is not None:
            writer.close()
            stats.journal = [str(p) for p in writer.segments]
        beat.close()
        for tx in txs:
            tx.close(linger=60_000 if not tx_thread.is_alive() and not gave_up else 0)
        if own and not tx_thread.is_alive():  # (a sender still stuck keeps its sockets)
            end_context(ctx)
    return stats
