"""Who sends: the run takes one sender's stream, every other sender is named and kept out.

A sender is the address a datagram came from (``host:port``). With ``[source] peers``
configured, only datagrams from those hosts (``HOST``: any port; ``HOST:PORT``: that port)
are read at all: the receive thread drops the others before they reach the ring, so a
flood from elsewhere cannot crowd out the stream. Without peers, the run locks onto the
sender whose datagrams form its reference (:class:`~pipeline.stream.udp.reference.
Reference`, which groups datagrams by sender) and keeps every other sender out the same
way. Either way each other sender is counted by name (its datagrams, gate and TDC count,
and whether its datagrams form a consistent stream of their own: an old rig left on the
port, or a forger); without peers, a second consistent sender makes the run incomplete,
since nothing then says which of the two streams was the run's.
"""

from __future__ import annotations

import ipaddress
import socket
import sys
import threading

from pipeline.stream import datagram
from pipeline.stream.udp.order import _signed32, consistent

NAMED_SENDERS = 64  #: senders counted by name; the rest together as "others"


def sender_name(addr: tuple) -> str:
    return f"{addr[0]}:{addr[1]}"


def parse_peers(peers: list[str] | tuple[str, ...] | None) -> list[tuple[str, int | None]]:
    """``HOST`` or ``HOST:PORT`` (a host name is resolved once, here) -> (IPv4, port or
    None); ValueError naming the entry otherwise."""
    out = []
    for p in peers or ():
        host, _, port = str(p).rpartition(":") if ":" in str(p) else (str(p), "", "")
        try:
            port_n = int(port) if port else None
            if port_n is not None and not 1 <= port_n <= 65535:
                raise ValueError
            ip = str(ipaddress.IPv4Address(socket.gethostbyname(host)))
        except (ValueError, OSError):
            raise ValueError(f"peer {p!r}: not HOST or HOST:PORT (an IPv4 address or a "
                             f"name that resolves, port 1..65535)") from None
        out.append((ip, port_n))
    return out


class Senders:
    """Which senders are the run's (``peers``, or the one ``lock`` sets) and the book of the
    others. ``admits`` is called by the receive thread, ``lock`` by the main thread."""

    def __init__(self, peers: list[tuple[str, int | None]] | None = None, quorum: int = 3):
        self.peers = list(peers or [])
        self.locked: tuple | None = None   #: the run's sender without peers
        self.quorum = quorum
        self.others: dict[str, dict] = {}  #: name -> datagrams, gate, n_tdc, consistent
        self._last: dict[str, tuple] = {}  #: name -> (seq, first cycle, n_tdc, gate, streak)
        self.kept_out = 0
        self._lock = threading.Lock()

    def admits(self, addr: tuple) -> bool:
        if self.peers:
            return any(addr[0] == h and (p is None or addr[1] == p) for h, p in self.peers)
        return self.locked is None or addr == self.locked

    def lock(self, addr: tuple) -> None:
        if not self.peers and self.locked is None:
            self.locked = addr

    def note(self, addr: tuple, data: bytes) -> None:
        """A datagram kept out: counted under its sender's name, and its header (when it
        has one) checked against that sender's previous one."""
        name = sender_name(addr)
        with self._lock:
            self.kept_out += 1
            if name not in self.others and len(self.others) >= NAMED_SENDERS:
                name = "others"
            book = self.others.setdefault(name, {"datagrams": 0, "consistent": False})
            book["datagrams"] += 1
            if name == "others":
                return
            try:
                d = datagram.decode(data)
            except datagram.DatagramError:
                return
            book["gate_ps"], book["n_tdc"] = d.t_laser_win_ps, d.n_tdc
            last = self._last.get(name)
            streak = 1
            if last is not None and last[2:4] == (d.n_tdc, d.t_laser_win_ps) and consistent(
                    _signed32(d.seq - last[0]), d.first_cycle - last[1], d.n_tdc):
                streak = last[4] + 1
            self._last[name] = (d.seq, d.first_cycle, d.n_tdc, d.t_laser_win_ps, streak)
            if streak >= self.quorum and not book["consistent"]:
                book["consistent"] = True
                why = "" if self.peers else "; without [source] peers the run ends incomplete"
                print(f"ingest: another sender, {name}, sends a consistent stream (gate "
                      f"{d.t_laser_win_ps} ps, {d.n_tdc} TDCs): kept out{why}",
                      file=sys.stderr, flush=True)

    def second_stream(self) -> list[str]:
        """Other senders whose datagrams formed a consistent stream of their own."""
        with self._lock:
            return sorted(n for n, b in self.others.items() if b["consistent"])

    def fields(self) -> dict:
        with self._lock:
            return {"sender": (sender_name(self.locked) if self.locked else None),
                    "peers": [f"{h}:{p}" if p else h for h, p in self.peers],
                    "other_senders": {n: dict(b) for n, b in self.others.items()}}
