"""The ingest: the FPGA's UDP datagrams in, journaled raw-word batches out.

Binds 127.0.0.1 unless told otherwise. Every datagram is accounted for: taken (its words
journaled to capture segments before they are passed on), or rejected by reason and
quarantined; gaps in the sequence numbers are counted as lost datagrams.
"""

from __future__ import annotations

import json
import socket
import threading
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zmq

from pipeline import datagram, wire
from pipeline.journal import JournalWriter
from pipeline.stage import _socket
from schemas.words import RAW_WORDS

BATCH_WORDS = 1 << 18  # 1 MiB messages


@dataclass
class IngestStats:
    datagrams: int = 0
    words: int = 0
    lost_datagrams: int = 0
    rejected: Counter = field(default_factory=Counter)
    messages: int = 0
    journal: list[str] = field(default_factory=list)  #: segment files written


def udp_socket(address: str = "127.0.0.1:0") -> socket.socket:
    """A bound UDP socket; ``host:port`` (port 0 picks a free one)."""
    host, port = address.rsplit(":", 1)
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    s.bind((host, int(port)))
    return s


def run_udp_ingest(sock: socket.socket, push: str | list[str], *, run: str = "udp",
                   journal: str | Path | None = None, segment_words: int = 1 << 24,
                   quarantine: str | Path | None = None, stop: threading.Event | None = None,
                   idle_s: float | None = None, context: zmq.Context | None = None,
                   split: list[tuple[int, int]] | None = None, metrics: str | None = None,
                   date: str | None = None, compression: str | None = "zstd") -> IngestStats:
    """Receive until a datagram flagged last, ``stop``, or ``idle_s`` without data.

    ``split``: TDC ranges, one per endpoint of ``push`` (a fan-out by TDC range; datagrams
    hold whole cycles, so every batch splits cleanly)."""
    import datetime as dt

    from pipeline.fanout import TdcSplitter
    from pipeline.metrics import Metrics

    ctx = context or zmq.Context.instance()
    pushes = [push] if isinstance(push, str) else list(push)
    txs = []
    for ep in pushes:
        tx = _socket(ctx, zmq.PUSH, 4)
        tx.connect(ep)
        txs.append(tx)
    if (split is not None and len(split) != len(txs)) or (split is None and len(txs) != 1):
        raise ValueError("one TDC range per endpoint")
    beat = Metrics(metrics, "source", ctx)
    date = date or dt.date.today().isoformat()
    stop = stop or threading.Event()
    stats = IngestStats()
    seqs = datagram.SequenceTracker()
    qdir = Path(quarantine) if quarantine else None
    sock.settimeout(0.2)
    pending: list[np.ndarray] = []
    pending_first = None
    next_word = None
    n_tdc = gate_ns = None
    writer: JournalWriter | None = None
    idle = 0.0

    def flush():
        nonlocal pending, pending_first
        if not pending:
            return
        import pyarrow as pa

        words = np.concatenate(pending)
        ranges = split or [(0, n_tdc)]
        parts = (TdcSplitter(n_tdc, split).split(pending_first, words) if split
                 else [(pending_first, words)])
        for tx, (f, w), rng in zip(txs, parts, ranges, strict=True):
            batch = pa.record_batch([pa.array(w)], schema=RAW_WORDS.schema)
            head = {"kind": "data", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
                    "run": run, "seq": stats.messages, "step": "ingest",
                    "first_word": int(f), "n_tdc": rng[1] - rng[0], "n_tdc_total": n_tdc,
                    "tdc_range": list(rng), "t_laser_win_ns": gate_ns, "date": date}
            tx.send_multipart(wire.encode(head, batch))
        stats.messages += 1
        pending, pending_first = [], None

    def journal_words(first, words):
        # the same journal the sources write: readable while written, closed with the
        # run's end, so a restarted stage downstream can fill its gaps from it
        nonlocal writer
        if journal is None:
            return
        if writer is None:
            writer = JournalWriter(journal, run, n_tdc, gate_ns, segment_words=segment_words,
                                   compression=compression)
        writer.append(first, words)

    try:
        while not stop.is_set():
            beat.beat(state="running", received=stats.datagrams, sent=stats.messages,
                      words=stats.words, rejected=dict(stats.rejected),
                      lost_datagrams=stats.lost_datagrams)
            try:
                data = sock.recv(datagram.MAX_PAYLOAD + 1)
            except TimeoutError:
                idle += 0.2
                if idle_s is not None and idle >= idle_s:
                    break
                continue
            idle = 0.0
            stats.datagrams += 1
            try:
                d = datagram.decode(data)
                if n_tdc is not None and d.n_tdc != n_tdc:
                    raise datagram.DatagramError("n_tdc_mismatch",
                                                 f"{d.n_tdc} TDCs after {n_tdc}")
            except datagram.DatagramError as exc:
                stats.rejected[exc.reason] += 1
                if qdir is not None:
                    qdir.mkdir(parents=True, exist_ok=True)
                    k = sum(stats.rejected.values())
                    (qdir / f"{k:06d}.bin").write_bytes(data)
                    (qdir / f"{k:06d}.json").write_text(json.dumps({"reason": str(exc)}))
                continue
            stats.lost_datagrams += seqs.see(d.seq)
            n_tdc = d.n_tdc
            gate_ns = d.t_laser_win_ps / 1000
            first = d.first_cycle * n_tdc
            if next_word is not None and first != next_word:
                flush()  # a gap: the next batch starts where the words do
            if pending_first is None:
                pending_first = first
            pending.append(d.words)
            next_word = first + d.words.size
            journal_words(first, d.words)
            stats.words += d.words.size
            if sum(p.size for p in pending) >= BATCH_WORDS:
                flush()
            if d.last:
                break
        flush()
        if writer is not None:  # the run's end is on disk before anyone hears of it
            writer.close()
            stats.journal = [str(p) for p in writer.segments]
            writer = None
        for tx in txs:
            tx.send_multipart(wire.encode({
                "kind": "stop", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
                "run": run, "seq": stats.messages, "step": "ingest", "words": stats.words,
                "datagrams": stats.datagrams, "lost_datagrams": stats.lost_datagrams,
                "rejected": dict(stats.rejected)}, None))
        beat.beat(force=True, state="finished", received=stats.datagrams,
                  sent=stats.messages, words=stats.words, rejected=dict(stats.rejected),
                  lost_datagrams=stats.lost_datagrams)
    finally:
        if writer is not None:
            writer.close()
            stats.journal = [str(p) for p in writer.segments]
        beat.close()
        for tx in txs:
            tx.close()
    return stats
