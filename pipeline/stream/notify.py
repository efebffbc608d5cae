"""The daemon under systemd (``Type=notify``, issue 38.8): the sd_notify protocol, by hand.

The protocol is one datagram of ``KEY=VALUE`` lines to the AF_UNIX socket named by
``$NOTIFY_SOCKET`` (a path, or ``@name`` for the abstract namespace). The daemon sends

- ``READY=1`` once every stage has reported (its first heartbeat) or finished;
- ``WATCHDOG=1`` every ``$WATCHDOG_USEC / 2`` from its supervision loop, so only while that
  loop runs: a wedged supervisor stops petting, and systemd kills and restarts it
  (``WatchdogSec=`` in the unit, ``docs/systemd/tcspc-daemon.service``);
- ``STATUS=...``: one line of the run's state (``systemctl status`` shows it);
- ``STOPPING=1`` when the graph has ended and the reconciliation begins.

Without ``$NOTIFY_SOCKET`` (not under systemd) every call does nothing. A send that fails
is ignored: the service manager's absence must never stop a run. (Why not a package:
docs/decisions.md.)
"""

from __future__ import annotations

import os
import socket
import time


class Notifier:
    def __init__(self, environ=None, clock=time.monotonic):
        env = os.environ if environ is None else environ
        addr = env.get("NOTIFY_SOCKET") or ""
        self.addr = ("\0" + addr[1:]) if addr.startswith("@") else addr
        self.sock = None
        if self.addr:
            try:
                self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            except OSError:
                self.sock = None
        usec = env.get("WATCHDOG_USEC", "")
        pid = env.get("WATCHDOG_PID", "")
        mine = not pid or pid == str(os.getpid())
        #: seconds between WATCHDOG=1 (half the unit's WatchdogSec), None: no watchdog
        self.every = int(usec) / 2e6 if usec.isdigit() and int(usec) > 0 and mine else None
        self.clock = clock
        self.last = None
        self.status_text = None
        self.ready_sent = False

    @property
    def active(self) -> bool:
        return self.sock is not None

    def send(self, *lines: str) -> bool:
        if self.sock is None:
            return False
        try:
            self.sock.sendto("\n".join(lines).encode(), self.addr)
            return True
        except OSError:
            return False

    def ready(self, status: str | None = None) -> None:
        if not self.ready_sent:
            self.ready_sent = True
            self.send("READY=1", *((f"STATUS={status}",) if status else ()))

    def status(self, text: str) -> None:
        """``STATUS=`` when it changed."""
        text = " ".join(text.split())  # one line
        if text != self.status_text:
            self.status_text = text
            self.send(f"STATUS={text}")

    def watchdog(self) -> None:
        """``WATCHDOG=1`` when due (call it from the supervision loop, every iteration)."""
        if self.every is None:
            return
        now = self.clock()
        if self.last is None or now - self.last >= self.every:
            self.last = now
            self.send("WATCHDOG=1")

    def stopping(self, status: str | None = None) -> None:
        self.send("STOPPING=1", *((f"STATUS={status}",) if status else ()))

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None
