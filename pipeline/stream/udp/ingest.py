"""The ingest's loop: a socket in, journaled raw-word batches out (three threads).

Every datagram is accounted for: taken (its words journaled to capture segments before they
are passed on), a duplicate (counted, dropped), late (it came after its reorder window
closed: counted and quarantined), or rejected by reason and quarantined. Every header field
is bounded against the run: another TDC count or gate is a rejected datagram.
"""

from __future__ import annotations

import queue
import select
import socket
import threading
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zmq

from pipeline.stream import datagram, wire
from pipeline.stream.hangup import END_WAIT_S, Consumers
from pipeline.stream.journal import JournalWriter
from pipeline.stream.stage import Quarantine, _socket, connect, end_context, own_context
from pipeline.stream.udp.order import (
    MAX_JUMP_CYCLES,
    MAX_JUMP_DATAGRAMS,
    REORDER_WINDOW,
    Reassembler,
)
from pipeline.stream.udp.reference import QUORUM, QUORUM_HOLD, Reference
from pipeline.stream.udp.resume import resume_state
from pipeline.stream.udp.senders import Senders, parse_peers, sender_name
from schemas.words import RAW_WORDS

BATCH_WORDS = 1 << 18  # 1 MiB messages
REORDER_LINGER_S = 0.5         #: after the last datagram, wait this long for stragglers
GATE_PS = (1_000, 10_000_000)  #: a gate outside 1 ns .. 10 us is not a gate
RING_DATAGRAMS = 4096          #: received, not yet journaled (<= 256 MiB of datagrams)
RX_BATCH = 64                  #: datagrams one hand-off to the ring carries at most
FLUSH_S = 0.01                 #: a partial batch is journaled and sent after this long
SEND_QUEUE = 64                #: journaled messages waiting for a slow stage downstream
RCVBUF_BYTES = 64 << 20        #: the kernel's buffer: ~0.4 s of 40 M words/s off the CPU
BREAK_QUORUM = 8               #: datagrams that must agree before a new stream is a reset


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
    conflicts: int = 0        #: a sequence number and cycle taken before, with other bytes
    #: the FPGA restarted its stream (or its sequence numbers jumped): each a new segment
    resets: list = field(default_factory=list)
    senders: Senders | None = None  #: the run's sender and the others, kept out
    journal: list[str] = field(default_factory=list)  #: segment files written

    def fields(self) -> dict:
        return {"received": self.datagrams, "accepted": self.accepted, "sent": self.messages,
                "words": self.words, "duplicates": self.duplicates, "late": self.late,
                "lost_datagrams": self.lost_datagrams, "gap_cycles": self.gap_cycles,
                "rejected": dict(self.rejected),
                "quarantine_dropped": self.quarantine_dropped,
                "ring_dropped": self.ring_dropped, "deferred_messages": self.deferred_messages,
                "deferred_words": self.deferred_words, "paused_s": round(self.paused_s, 1),
                "unjournaled_words": self.unjournaled_words, "conflicts": self.conflicts,
                "resets": list(self.resets),
                **(self.senders.fields() if self.senders is not None else {})}


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
                   flush_s: float = FLUSH_S, sparse: bool = False,
                   peers: list[str] | None = None,
                   break_quorum: int = BREAK_QUORUM,
                   end_wait_s: float = END_WAIT_S) -> IngestStats:
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
    ``peers``: the senders (``HOST`` or ``HOST:PORT``) whose datagrams are read; without,
    the run locks onto the sender of its reference (:mod:`.senders`). ``break_quorum``:
    datagrams of the run's sender that agree with each other but not with the stream
    before they are taken as the FPGA's restarted stream (a new segment of the run).

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
    # each consumer's connection, watched from before it is made: the ingest stays
    # connected until each has hung up after the run's end (its acknowledgement), and one
    # that hung up has all it will ever take: nothing is lingered over for it (hangup.py)
    txs = [_socket(ctx, zmq.PUSH, 4) for _ in pushes]
    consumers = Consumers(txs)
    for tx, ep in zip(txs, pushes, strict=True):
        connect(tx, ep)
    if (split is not None and len(split) != len(txs)) or (split is None and len(txs) != 1):
        raise ValueError("one TDC range per endpoint")
    beat = Metrics(metrics, "source", ctx, token=token)
    date = date or dt.date.today().isoformat()
    stop = stop or threading.Event()
    senders = Senders(parse_peers(peers), quorum)
    stats = IngestStats(senders=senders)
    reasm = Reassembler(reorder_window, max_jump_cycles, max_jump_datagrams)
    resumed = resume_state(journal, run) if journal is not None else None
    ref = Reference(quorum, n_tdc, gate_ps)
    if resumed is not None:  # a restarted ingest: the journal is the truth
        reasm.resume(resumed)
        stats.late = resumed["late"]
        stats.ring_dropped, stats.conflicts = resumed["ring_dropped"], resumed["conflicts"]
        stats.resets = resumed["resets"]
        n_tdc, gate_ps = resumed["n_tdc"], resumed["gate_ps"]
        ref = Reference(quorum, n_tdc, gate_ps, anchor=resumed["device_anchor"])
        # (the sender is locked again by the quorum that agrees with the journal: an FPGA
        # may send from another port after a reset of its own)
        for name in resumed["second_senders"]:
            senders.others[name] = {"datagrams": 0, "consistent": True}
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
    last_rx = [time.monotonic()]  # when the run's sender(s) last sent: idle is since then

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
                    data, addr = sock.recvfrom(size)
                    if senders.admits(addr):
                        items.append((data, addr))
                    else:  # another sender: named and counted, never in the ring
                        senders.note(addr, data)
            except BlockingIOError:
                pass
            except OSError:
                closed = True  # the socket was closed under us: the run is over
            if items:
                last_rx[0] = time.monotonic()
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
                # (the words' frame without a copy, as the replay's source: a new
                # buffer nothing writes again)
                tx.send_multipart(frames, zmq.NOBLOCK, copy=False)

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
    breaks: Reference | None = None  # datagrams held as the start of a restarted stream
    events: list[dict] = []  # stream events for the next chunk's index line

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
                 "datagrams": len(seqs), "late": stats.late,
                 "ring_dropped": stats.ring_dropped, "conflicts": stats.conflicts}
        if senders.locked is not None:
            extra["sender"] = sender_name(senders.locked)
        if senders.second_stream():  # (a restarted ingest must not forget them)
            extra["second_senders"] = senders.second_stream()
        if reasm.seg != (0, 0):  # device -> run offsets of a restarted stream
            extra["seg"] = list(reasm.seg)
        if events:
            extra["events"] = events[:]
            events.clear()
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
        if reason == "conflict":  # the stream contradicts itself: the run is incomplete
            stats.conflicts += 1
        try:
            quar.put(reason, data, detail=detail)
        except OSError:
            quar.dropped += 1  # a full disk: counted, not kept
        stats.quarantine_dropped = quar.dropped

    def offer(d: datagram.Datagram, data: bytes, addr=None) -> None:
        # the run's axes; a datagram that could start another stream is held for a quorum
        nonlocal breaks
        t = reasm.translate(d)
        if not reasm.breaks(t):
            stream(t, data)
            return
        if breaks is None:
            breaks = Reference(break_quorum, n_tdc, gate_ps)
        group, strays = breaks.offer(d, data, addr)
        for sd, sdata, _ in strays:  # not a new stream: judged against the run's
            stream(reasm.translate(sd), sdata)
        if group is not None:
            breaks = None
            restart(group)

    def stream(d: datagram.Datagram, data: bytes) -> None:
        nonlocal last_end
        try:
            verdict, released = reasm.offer(d)
        except datagram.DatagramError as exc:
            reject(exc.reason, str(exc), data)
            return
        if verdict == "duplicate":
            stats.duplicates += 1
            return
        if verdict == "conflict":
            reject("conflict", f"sequence {d.seq} at cycle {d.first_cycle} again, with "
                               f"other bytes than the datagram taken", data)
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

    def restart(group: list) -> None:
        # ``break_quorum`` datagrams of one sender agree with each other, not with the
        # stream: the FPGA restarted it (its sequence numbers back, with or without its
        # cycle counter) or its sequence numbers jumped with the cycles going on. The old
        # stream is released, the event journaled, the new one put after it on the run's
        # axes: a new segment, measured on. Anything else is judged as the run's datagram.
        a = min(group, key=lambda c: c[0].seq)[0]
        at = reasm.translate(a)
        behind = reasm._unwrap(at.seq) < reasm.newest[0]
        goes_on = at.first_cycle >= reasm.next_cycle  # the cycle counter was not reset
        if not behind and not goes_on:
            for sd, sdata, _ in group:
                stream(reasm.translate(sd), sdata)
            return
        for r in reasm.drain():
            take(r)
        flush()
        base = first_seq or 0
        if not behind or a.seq - base > QUORUM_HOLD:
            base = a.seq  # (where it restarted from is unknown: nothing counted lost)
        end = reasm.next_cycle
        reasm.new_segment(reasm.seq_hi + 1 - base, reasm.seg[1] if goes_on else end)
        event = {"event": "fpga_restart" if behind else "sequence_jump",
                 "cycle_counter": "continued" if goes_on else "restarted",
                 "device_seq": a.seq, "device_cycle": a.first_cycle, "at_cycle": end,
                 "seq_offset": reasm.seg[0], "cycle_offset": reasm.seg[1],
                 "t": round(time.time(), 3)}
        stats.resets.append(event)
        events.append(event)
        print(f"ingest: the stream restarted ({event['event']}, cycle counter "
              f"{event['cycle_counter']}) at sequence {a.seq}, cycle {a.first_cycle}: a new "
              f"segment from the run's cycle {end}", flush=True)
        for sd, sdata, _ in group:
            stream(reasm.translate(sd), sdata)

    def stray(d: datagram.Datagram, data: bytes) -> None:
        reject("stray", f"sequence {d.seq}, first cycle {d.first_cycle}, {d.n_tdc} TDCs, "
                        f"gate {d.t_laser_win_ps} ps: not the run's stream", data)

    def fix(group: list) -> None:
        # the reference is fixed: the held datagrams that agree go in, in arrival order;
        # their sender is the run's (without peers, every other is kept out from now)
        nonlocal ref, n_tdc, gate_ps, last_end
        if not group:
            return
        n_tdc, gate_ps = group[0][0].n_tdc, group[0][0].t_laser_win_ps
        senders.lock(group[0][2])
        if resumed is not None:
            first = reasm.translate(min(group, key=lambda c: c[0].first_cycle)[0])
            reasm.rejoin(first.seq, first.first_cycle)
        ref = None
        if last_end == -1:
            last_end = None
        for gd, gdata, gaddr in group:
            offer(gd, gdata, gaddr)

    def intake(data: bytes, addr) -> None:
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
            group, strays = ref.offer(d, data, addr)
            for sd, sdata, _ in strays:
                stray(sd, sdata)
            if group is None:
                if d.last and ref.held:
                    last_end = -1  # settle after the linger (below)
                return
            fix(group)
            return
        senders.lock(addr)  # (a configured reference: its first datagram's sender)
        offer(d, data, addr)

    def complete() -> bool:  # the last datagram and everything before it are in
        return (last_end is not None and last_end >= 0 and reasm.next_cycle >= last_end
                and not reasm.held)

    gave_up = False  # on a stage downstream that took nothing for a minute (a journal)
    at_end = None  # the consumers' connections when the run's end was reached
    try:
        while not stop.is_set():
            stats.gap_cycles, stats.lost_datagrams = reasm.gap_cycles, reasm.lost()
            consumers.keep()
            beat.beat(state="running", **stats.fields())
            if last_end == -1 and idle >= linger_s and ref is not None:
                group, strays = ref.settle()  # a run of fewer datagrams than the quorum
                for sd, sdata, _ in strays:
                    stray(sd, sdata)
                last_end = None
                fix(group)
            if complete():
                break
            try:
                batch = ring.get(timeout=flush_s if pending else 0.2)
            except queue.Empty:
                flush()  # a partial batch waits no longer than flush_s
                # idle: since the run's sender last sent (the time this thread spent
                # waiting on its own journal, a full disk, is not idle: the ring held on)
                idle = time.monotonic() - last_rx[0] if not ring_fill[0] else 0.0
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
            for k, (data, addr) in enumerate(batch):
                if not senders.admits(addr):  # (the lock came after the receiver read it)
                    senders.note(addr, data)
                    continue
                stats.datagrams += 1
                if complete():  # the rest came after the run's end: counted, not taken
                    rest = sum(senders.admits(a) for _, a in batch[k + 1:])
                    stats.datagrams += rest
                    stats.rejected["after_end"] += 1 + rest
                    break
                intake(data, addr)
            if pending and time.monotonic() - pending_t0 >= flush_s:
                flush()
        if ref is not None:  # the run's end without a quorum: the largest group agreeing
            group, strays = ref.settle()
            for sd, sdata, _ in strays:
                stray(sd, sdata)
            fix(group)
        if breaks is not None:  # no new stream formed: each judged as the run's datagram
            for sd, sdata, _ in breaks.held:
                stream(reasm.translate(sd), sdata)
            breaks = None
        for r in reasm.drain():
            take(r)
        flush()
        stats.gap_cycles, stats.lost_datagrams = reasm.gap_cycles, reasm.lost()
        at_end = consumers.at_end()  # (before a consumer can end on the end)
        if writer is not None:  # the run's end is on disk before anyone hears of it
            writer.close(complete=not stop.is_set())  # (a signal: a stop, resumable)
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
            "gap_cycles": stats.gap_cycles, "rejected": dict(stats.rejected),
            "conflicts": stats.conflicts, "ring_dropped": stats.ring_dropped,
            "resets": len(stats.resets)}
        # a stage downstream that takes nothing for a minute is given up on: the daemon
        # ends it, and it fetches the words it lacks from the journal. Waiting on it, this
        # stage reports "blocked" every second: the heartbeat deadline is for the stage
        # that stopped answering, not for the ones waiting on it
        t_end = time.monotonic() + 60
        for item in ([wire.encode(stop_head, None, token) for _ in txs], None):
            while not gave_up:
                try:
                    sendq.put(item, timeout=1.0)
                    break
                except queue.Full:
                    gave_up = journal is not None and time.monotonic() >= t_end
                    consumers.keep()
                    beat.beat(state="blocked", **stats.fields())
        while not gave_up and tx_thread.is_alive() and time.monotonic() < t_end:
            tx_thread.join(timeout=1.0)
            consumers.keep()
            beat.beat(state="blocked", **stats.fields())
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
        sent_all = not tx_thread.is_alive() and not gave_up and at_end is not None
        gone = (consumers.wait(at_end, end_wait_s, beat, **stats.fields()) if sent_all
                else [False] * len(txs))
        consumers.close()
        for tx, left in zip(txs, gone, strict=True):
            tx.close(linger=60_000 if sent_all and not left else 0)
        beat.close()
        if own and not tx_thread.is_alive():  # (a sender still stuck keeps its sockets)
            end_context(ctx)
    return stats

