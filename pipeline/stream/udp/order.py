"""The stream's order: sequence numbers and cycles.

UDP reorders and duplicates, so datagrams are reassembled by first cycle in a bounded
reorder window and each cycle is released once, in order; cycles no datagram brought are a
gap (counted), and sequence numbers never seen are lost datagrams. A cycle or sequence
number beyond the window (``max_jump_cycles``, ``max_jump_datagrams``) is a rejected
datagram, never a gap to fill. :func:`consistent` says whether two datagrams can belong to
one stream.
"""

from __future__ import annotations

from collections import deque
from dataclasses import replace

import numpy as np

from pipeline.stream import datagram

REORDER_WINDOW = 64            #: datagrams held to put reordered ones back in place
MAX_JUMP_CYCLES = 1 << 20      #: a datagram this far past the run's newest cycle is refused
MAX_JUMP_DATAGRAMS = 1 << 16   #: ... and this far in sequence number


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
        # (seq, first cycle) released -> its words (a view of the datagram's bytes: a
        # duplicate is compared with them, a repeat with other bytes is a conflict)
        self.recent: deque = deque(maxlen=4 * window)
        self.recent_words: dict = {}
        self.gap_cycles = 0
        self.newest: tuple[int, int] | None = None  #: (seq, first cycle) of the newest taken
        #: device -> run: (sequence offset mod 2^32, cycle offset); (0, 0) until the FPGA
        #: restarts its stream (a new segment of the run, :meth:`new_segment`)
        self.seg = (0, 0)

    def resume(self, state: dict) -> None:
        """Take the run up where the journal has it (:func:`resume_state`)."""
        self.next_cycle = self.newest_cycle = state["next_cycle"]
        self.seq_lo, self.seq_hi = state["seq_lo"], state["seq_hi"]
        self.seqs_seen = state["taken"] + state["late"]
        self.gap_cycles = state["gap_cycles"]
        self.newest = state["anchor"]
        self.seg = tuple(state.get("seg", (0, 0)))

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

    def translate(self, d: datagram.Datagram) -> datagram.Datagram:
        """``d`` on the run's axes (its segment's sequence and cycle offsets)."""
        if self.seg == (0, 0):
            return d
        return replace(d, seq=(d.seq + self.seg[0]) & 0xFFFFFFFF,
                       first_cycle=d.first_cycle + self.seg[1])

    def refusal(self, d: datagram.Datagram) -> datagram.DatagramError | None:
        """Why ``d`` (on the run's axes) cannot be the stream's, or None."""
        seq = self._unwrap(d.seq)
        if self.seq_hi is not None and abs(seq - self.seq_hi) > self.max_jump_datagrams:
            return datagram.DatagramError("seq_out_of_window", f"sequence {d.seq} is "
                                          f"{seq - self.seq_hi:+d} from the newest")
        if d.first_cycle - max(self.newest_cycle, self.next_cycle) > self.max_jump_cycles:
            return datagram.DatagramError("cycle_out_of_window", f"first cycle "
                                          f"{d.first_cycle} is beyond the run's newest "
                                          f"{self.newest_cycle} + {self.max_jump_cycles}")
        if self.newest is not None and not consistent(seq - self.newest[0], d.first_cycle
                                                      - self.newest[1], d.n_tdc):
            return datagram.DatagramError("inconsistent", f"sequence {d.seq} at first cycle "
                                          f"{d.first_cycle} cannot follow the run's newest, "
                                          f"{self.newest[0]} at {self.newest[1]}")
        return None

    def conflicts(self, d: datagram.Datagram) -> bool:
        """``d`` repeats a sequence number and first cycle taken with other bytes."""
        key = (self._unwrap(d.seq), d.first_cycle)
        old = self.recent_words.get(key)
        if old is None and d.first_cycle in self.held and self.held[d.first_cycle][0] == key[0]:
            old = self.held[d.first_cycle][1].words
        return old is not None and not np.array_equal(old, d.words)

    def breaks(self, d: datagram.Datagram) -> bool:
        """Could ``d`` (on the run's axes) begin another stream (an FPGA reset)? A datagram
        the stream refuses, or far behind its newest (more than its duplicate horizon): held
        for a quorum of its own before it is judged. (A repeat with other bytes is not: it
        is a conflict, whoever sent it.)"""
        if self.newest is None or self.conflicts(d):
            return False
        return (self.refusal(d) is not None
                or self._unwrap(d.seq) - self.newest[0] < -self.recent.maxlen)

    def new_segment(self, seq_off: int, cycle_off: int) -> None:
        """The FPGA restarted its stream: from now on device datagrams are put on the run's
        axes by these offsets; the new stream is checked against itself, not the old one."""
        self.seg = (seq_off & 0xFFFFFFFF, cycle_off)
        self.newest = None

    def offer(self, d: datagram.Datagram) -> tuple[str, list]:
        """Take one checked datagram: ``("taken" | "duplicate" | "late" | "conflict",
        released)``, ``released`` the datagrams now in stream order. Out-of-window fields
        raise DatagramError."""
        refused = self.refusal(d)
        if refused is not None:
            raise refused
        seq = self._unwrap(d.seq)
        key = (seq, d.first_cycle)
        if key in self.recent_words or (d.first_cycle in self.held
                                        and self.held[d.first_cycle][0] == seq):
            return ("conflict" if self.conflicts(d) else "duplicate"), []
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
                self.recent_words.pop(self.recent[0], None)
            self.recent.append((seq, d.first_cycle))
            self.recent_words[(seq, d.first_cycle)] = d.words
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
