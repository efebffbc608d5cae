"""The FPGA's UDP datagram (docs/streaming.md): encode, and decode with clear rejections."""

from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from schemas.errors import Rejected

MAGIC = b"TCSP"
VERSION = 1
HEADER = struct.Struct(">4sBBHIQHHII")
FLAG_LAST = 1
MAX_PAYLOAD = 65_507


class DatagramError(Rejected):
    """A datagram that cannot be taken."""


@dataclass(frozen=True)
class Datagram:
    seq: int
    first_cycle: int
    n_cycles: int
    n_tdc: int
    t_laser_win_ps: int
    last: bool
    #: n_cycles * n_tdc uint32, a big-endian view of the datagram's bytes (not copied: the
    #: journal writes them as they are, the message swaps them in its one copy)
    words: np.ndarray


def encode(words: np.ndarray, seq: int, first_cycle: int, n_tdc: int, t_laser_win_ps: int,
           last: bool = False) -> bytes:
    """One datagram of whole cycles.

    >>> from stages.codec import encode_words
    >>> d = decode(encode(encode_words(0, 0, 0, 0, [0, 1]), 7, 100, 2, 140_000))
    >>> d.seq, d.first_cycle, d.n_cycles, d.words.size
    (7, 100, 1, 2)
    """
    words = np.asarray(words, np.uint32)
    if words.size % n_tdc:
        raise ValueError(f"datagram: {words.size} words are not whole cycles of {n_tdc}")
    n_cycles = words.size // n_tdc
    head = HEADER.pack(MAGIC, VERSION, FLAG_LAST if last else 0, HEADER.size,
                       seq & 0xFFFFFFFF, first_cycle, n_cycles, n_tdc, t_laser_win_ps, 0)
    out = head + words.astype(">u4").tobytes()
    if len(out) > MAX_PAYLOAD:
        raise ValueError(f"datagram: {len(out)} bytes exceed a UDP payload ({MAX_PAYLOAD})")
    return out


def decode(data: bytes) -> Datagram:
    """Parse a datagram; a bad one raises DatagramError with its reason class."""
    if len(data) < HEADER.size:
        raise DatagramError("truncated", f"{len(data)} bytes, the header alone is "
                            f"{HEADER.size}")
    magic, version, flags, hlen, seq, first, n_cyc, n_tdc, gate, _ = HEADER.unpack_from(data)
    if magic != MAGIC:
        raise DatagramError("bad_magic", f"magic {magic!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise DatagramError("bad_version", f"version {version}, this software reads "
                            f"{VERSION}")
    if hlen != HEADER.size or n_tdc == 0:
        raise DatagramError("bad_header", f"header length {hlen}, n_tdc {n_tdc}")
    expected = hlen + 4 * n_cyc * n_tdc
    if len(data) != expected:
        raise DatagramError("bad_length", f"{len(data)} bytes, header says {expected}")
    words = np.frombuffer(data, ">u4", offset=hlen)
    return Datagram(seq, first, n_cyc, n_tdc, gate, bool(flags & FLAG_LAST), words)


class SequenceTracker:
    """Counts datagrams lost between sequence numbers (with 32-bit wrap)."""

    def __init__(self):
        self.expected: int | None = None
        self.lost = 0
        self.received = 0

    def see(self, seq: int) -> int:
        """Record ``seq``; returns how many datagrams went missing before it."""
        gap = 0 if self.expected is None else (seq - self.expected) & 0xFFFFFFFF
        if gap > 0x7FFFFFFF:  # an old or duplicated datagram, not a forward gap
            gap = 0
        self.lost += gap
        self.received += 1
        self.expected = (seq + 1) & 0xFFFFFFFF
        return gap
