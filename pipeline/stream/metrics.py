"""Live metrics and heartbeats: every stage PUBlishes a small JSON record about once a
second on the metrics endpoint (the daemon SUBscribes and keeps ``status.json``).

Record: ``{"stage", "pid", "t", "state", "received", "sent", "words", "rejected",
"blocked_s", ...}``; ``blocked_s`` is the time spent waiting to send (a slow stage
downstream pushing back). Under the daemon a record carries the run's ``token``
(``$TCSPC_TOKEN_FILE``); the daemon drops, and counts, records without it. Sending never
blocks: with nobody listening, records are dropped.
"""

from __future__ import annotations

import json
import os
import time

import zmq

HEARTBEAT_S = 1.0


class Metrics:
    def __init__(self, endpoint: str | None, stage: str, context: zmq.Context | None = None,
                 interval_s: float = HEARTBEAT_S, token: str | None = None):
        self.stage, self.interval = stage, interval_s
        self.token = token  # the run's token: the daemon drops records without it
        self.sock = None
        self.last = 0.0
        if endpoint:
            self.sock = (context or zmq.Context.instance()).socket(zmq.PUB)
            self.sock.setsockopt(zmq.SNDHWM, 16)
            self.sock.setsockopt(zmq.LINGER, 500)
            from pipeline.stream import curve

            curve.client(self.sock)  # with $TCSPC_CURVE_DIR
            self.sock.connect(endpoint)

    def beat(self, force: bool = False, **fields) -> None:
        """Publish if a heartbeat is due (or ``force``)."""
        if self.sock is None:
            return
        now = time.time()
        if not force and now - self.last < self.interval:
            return
        self.last = now
        rec = {"stage": self.stage, "pid": os.getpid(), "t": now, **fields}
        if self.token is not None:
            rec["token"] = self.token
        try:
            self.sock.send(json.dumps(rec, default=int).encode(), zmq.NOBLOCK)
        except zmq.Again:
            pass

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
