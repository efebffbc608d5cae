"""A sender's end: it stays connected until each consumer has hung up (docs/streaming.md
"The end of a run").

ZeroMQ's ``ipc://`` transport loses what a consumer has not read when its sender closes:
the consumer's ZeroMQ, held back by its high-water mark, has stopped reading the socket,
and at the sender's hang-up it drops the connection with the bytes the kernel still holds
for it. The sender's LINGER does not help: for its ZeroMQ a message written to the kernel
is delivered, so ``close``/``term`` return at once (libzmq issue 4660). A stage's last
measurements and its stop were lost that way whenever its consumer was slower than it
(three histogram workers ahead of the range stage: 54 of 63 messages received). A consumer
closes its input only once it has taken every stop it waits for (or has ended on the
journal's end), so its hang-up is the acknowledgement: the sender waits for it, bounded.
"""

from __future__ import annotations

import threading
import time

import zmq
from zmq.utils.monitor import recv_monitor_message

#: At a sender's end, how long it waits for its consumers to hang up: a consumer still
#: taking its queue (bounded by the high-water marks) ends well within it; a killed one has
#: hung up already; a frozen one is given up on here (counted ``unacknowledged``) before
#: the daemon's heartbeat deadline (60 s by default) kills it.
END_WAIT_S = 30.0
_EVENTS = zmq.EVENT_CONNECTED | zmq.EVENT_DISCONNECTED


class Consumers:
    """The connections of a sender's PUSH sockets, watched by ZeroMQ socket monitors
    (made before the sockets connect, so that no connection goes unseen)."""

    def __init__(self, socks: list[zmq.Socket]):
        self.socks = list(socks)
        self.monitors = [s.get_monitor_socket(_EVENTS) for s in self.socks]
        self.last: list[int | None] = [None] * len(self.socks)  #: each one's last event
        self.unacknowledged = 0  #: consumers :meth:`wait` waited for in vain
        self._next_read = 0.0

    def keep(self, every_s: float = 1.0) -> None:
        """Read the monitors, at most every ``every_s``: called from the sender's loop.
        A monitor left unread fills its queue (~1,000 events: ~500 reconnects of a
        consumer restarting) and then blocks ZeroMQ's I/O thread, every socket of the
        process with it; ``last`` keeps what :meth:`at_end` needs."""
        now = time.monotonic()
        if now >= self._next_read:
            self._next_read = now + every_s
            self.events()

    def events(self) -> list[list[int]]:
        """The events since the last call, in order, each consumer's; ``last`` follows."""
        out = []
        for i, mon in enumerate(self.monitors):
            evs = []
            while mon.poll(0):
                evs.append(recv_monitor_message(mon)["event"])
            if evs:
                self.last[i] = evs[-1]
            out.append(evs)
        return out

    def at_end(self) -> list[int | None]:
        """Each consumer's connection now (``zmq.EVENT_CONNECTED``, ``EVENT_DISCONNECTED``
        or None: never connected): taken at the stream's end, before any stop goes out."""
        self.events()
        return list(self.last)

    def wait(self, at_end: list[int | None], wait_s: float = END_WAIT_S, beat=None,
             halt: threading.Event | None = None, halt_wait_s: float = 1.0,
             **fields) -> list[bool]:
        """Which consumers hung up after the end (``at_end``: :meth:`at_end`). Waits up to
        ``wait_s`` for each one connected at the end, or not connected yet (a consumer
        slower to start than the run), to connect and hang up; one that had hung up before
        the end (a consumer that ended on the journal's end, or one restarting) is not
        waited for, and its stop stays queued for a restarted one. Reports ``finished``
        (with ``fields``) on ``beat`` while it waits; once ``halt`` is set (a signal) it
        waits at most ``halt_wait_s`` more."""
        watch = [ev != zmq.EVENT_DISCONNECTED for ev in at_end]
        seen = [ev == zmq.EVENT_CONNECTED for ev in at_end]  # connected since the end
        gone = [False] * len(at_end)
        t_end = time.monotonic() + wait_s
        halted = False
        while True:
            for i, evs in enumerate(self.events()):
                for ev in evs:
                    if ev == zmq.EVENT_CONNECTED:
                        seen[i] = True
                    elif seen[i] and watch[i]:
                        gone[i] = True
            now = time.monotonic()
            if halt is not None and halt.is_set() and not halted:
                halted, t_end = True, min(t_end, now + halt_wait_s)
            if all(g or not w for g, w in zip(gone, watch, strict=True)) or now >= t_end:
                self.unacknowledged = sum(w and not g for g, w in
                                          zip(gone, watch, strict=True))
                return gone
            if beat is not None:
                beat.beat(state="finished", **fields)
            time.sleep(0.02)

    def close(self) -> None:
        """Stop watching (before the sockets close: a context ends only with every socket
        closed, its monitors' too)."""
        for s, mon in zip(self.socks, self.monitors, strict=True):
            try:
                s.disable_monitor()
            except zmq.ZMQError:
                pass  # (its socket closed already)
            mon.close(linger=0)
