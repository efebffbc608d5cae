"""The daemon's health as the page shows it: status.json and the daemon's status PUB in,
plain rows and a state sentence out.

The daemon writes ``STATE/status.json`` once a second and publishes the same record on
``ipc://STATE/sock/status`` (``pipeline.stream.sidecar.status_endpoint``). The view
subscribes (pushed, no file polling while the daemon runs) and falls back to the file when
nothing is published: a finished run, a daemon that has died, or one from before the PUB.
"""

from __future__ import annotations

import json
import os
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from pipeline.io.limits import read_bounded

#: A running daemon's status older than this means the daemon stopped writing it.
STALE_S = 5.0
#: Heartbeats (one a second) this close are one heartbeat seen in two status records.
SAME_BEAT_S = 0.3
#: Without a published status for this long, the view reads status.json instead.
PUB_FRESH_S = 2.5


def read_status(state: str | Path) -> dict | None:
    """``STATE/status.json``, or None when there is none (or it cannot be read)."""
    try:
        return json.loads(read_bounded(Path(state) / "status.json"))
    except (OSError, ValueError):
        return None


def pid_alive(pid) -> bool | None:
    """True / False for a process id on this host, None when there is no pid to check."""
    if not isinstance(pid, int) or pid <= 0:
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


class StatusFeed:
    """The latest status of the daemon on ``state``: from its PUB when it publishes, from
    status.json otherwise. ``poll()`` never blocks."""

    def __init__(self, state: str | Path, endpoint: str | None = None, context=None):
        import zmq

        from pipeline.stream.sidecar import status_endpoint

        self.state = Path(state)
        self.endpoint = endpoint or status_endpoint(self.state)
        self.sock = (context or zmq.Context.instance()).socket(zmq.SUB)
        self.sock.setsockopt(zmq.SUBSCRIBE, b"")
        self.sock.setsockopt(zmq.LINGER, 0)
        self.sock.setsockopt(zmq.RCVHWM, 4)
        self.sock.connect(self.endpoint)  # ZeroMQ reconnects when a daemon binds it again
        self.status: dict | None = None
        self.source = "none"  #: "pub", "file" or "none"
        self.last_pub = 0.0
        self._mtime: float | None = None

    def poll(self) -> dict | None:
        import zmq

        got = None
        while True:
            try:
                got = self.sock.recv(zmq.NOBLOCK)
            except zmq.Again:
                break
        if got is not None:
            try:
                self.status, self.source = json.loads(got), "pub"
                self.last_pub = time.time()
                return self.status
            except ValueError:
                pass  # not a status: keep the last one
        if time.time() - self.last_pub > PUB_FRESH_S:
            path = self.state / "status.json"
            try:
                mtime = path.stat().st_mtime
            except OSError:
                self.status, self.source, self._mtime = None, "none", None
                return None
            if mtime != self._mtime:
                st = read_status(self.state)
                if st is not None:
                    self.status, self.source, self._mtime = st, "file", mtime
        return self.status

    def close(self) -> None:
        self.sock.close()


@dataclass(frozen=True)
class DaemonState:
    kind: str   #: "absent", "running", "lost", "finished", "failed", "interrupted",
    #: "incomplete"
    text: str   #: one plain sentence for the banner


def daemon_state(status: dict | None, now: float, state_dir: str | Path = "") -> DaemonState:
    """What the banner says about the daemon."""
    if status is None:
        return DaemonState("absent", f"No daemon status in {state_dir or 'the state directory'}"
                           " (no daemon has run there yet, or it is elsewhere): showing the "
                           "datasets only. This page picks the daemon up when it starts.")
    run, state = status.get("run", "?"), status.get("state")
    age = now - float(status.get("updated", 0))
    if state == "running" and age > STALE_S:
        alive = pid_alive(status.get("pid"))
        why = {False: f"its process {status.get('pid')} is gone",
               True: f"its process {status.get('pid')} still exists but is not answering",
               None: "it may have died"}[alive]
        return DaemonState("lost", f"The daemon of run {run} has not reported for "
                           f"{_span(age)}: {why}. Start it again with the same --run and "
                           "this page picks it up by itself.")
    if state == "running":
        return DaemonState("running", f"Run {run} running for "
                           f"{_span(now - float(status.get('started', now)))}.")
    if state == "failed":
        why = (status.get("result") or {}).get("failed") or "see the daemon's log"
        return DaemonState("failed", f"Run {run} failed: {why}")
    if state == "interrupted":  # (the daemon's own words: pipeline.stream.daemon.run_state)
        sig = (status.get("result") or {}).get("interrupted") or "a signal"
        return DaemonState("interrupted", f"Run {run} interrupted ({sig}) {_span(age)} ago: "
                           "start the daemon again with the same --run to resume it.")
    if state == "incomplete":
        return DaemonState("incomplete", f"Run {run} ended incomplete {_span(age)} ago: "
                           + "; ".join(status.get("problems") or ["see the daemon's log"]))
    return DaemonState("finished", f"Run {run} finished "
                       f"{_span(age)} ago.")


def _span(s: float) -> str:
    s = max(0.0, s)
    if s < 120:
        return f"{s:.0f} s"
    if s < 7200:
        return f"{s / 60:.0f} min"
    if s < 172800:
        return f"{s / 3600:.1f} h"
    return f"{s / 86400:.1f} days"


class RateHistory:
    """Words/s and messages/s per stage over the last ``keep`` heartbeats (the sparklines)."""

    def __init__(self, keep: int = 120):
        self.keep = keep
        self.series: dict[str, deque] = {}
        self._last: dict[str, tuple] = {}

    def add(self, status: dict | None) -> None:
        for name, s in ((status or {}).get("stages") or {}).items():
            age = s.get("heartbeat_age_s")
            if age is None or "updated" not in status:
                continue
            t = float(status["updated"]) - float(age)  # the heartbeat's time, to 10 ms
            msgs = s.get("received") if name != "source" else s.get("sent")
            words = s.get("words_total", s.get("words"))
            prev = self._last.get(name)
            if prev is not None and abs(prev[0] - t) < SAME_BEAT_S:
                continue  # the same heartbeat in another status record
            self._last[name] = (t, s.get("pid"), msgs, words)
            if prev is None or prev[1] != s.get("pid") or t <= prev[0]:
                continue  # a first look, or a restarted stage: no rate across it
            dt_s = t - prev[0]
            w_rate = s.get("rate_words_s")
            if w_rate is None and words is not None and prev[3] is not None:
                w_rate = (words - prev[3]) / dt_s
            m_rate = (msgs - prev[2]) / dt_s if msgs is not None and prev[2] is not None \
                else None
            self.series.setdefault(name, deque(maxlen=self.keep)).append(
                (t, w_rate, m_rate))

    def words_s(self, stage: str) -> list[float]:
        return [w for _, w, _ in self.series.get(stage, ()) if w is not None]

    def msgs_s(self, stage: str) -> list[float]:
        return [m for _, _, m in self.series.get(stage, ()) if m is not None]


def health_rows(status: dict | None, history: RateHistory | None = None,
                stale: bool = False) -> list[dict]:
    """One row per stage, in the daemon's order (sink first, source last: the page shows them
    source first, as the data flows). ``stale``: the daemon stopped reporting, so nothing
    is known of its stages now (they die with it): their health reads "unknown"."""
    if not status:
        return []
    depth = status.get("queue_depth") or {}
    rows = []
    for name, s in (status.get("stages") or {}).items():
        words = history.words_s(name) if history else []
        msgs = history.msgs_s(name) if history else []
        rows.append({
            "stage": name, "health": "unknown" if stale and s.get("health") != "finished"
            else s.get("health", "?"), "pid": s.get("pid"),
            "restarts": int(s.get("restarts", 0)),
            "words_s": s.get("rate_words_s"), "msgs_s": msgs[-1] if msgs else None,
            "words_series": words, "msgs_series": msgs,
            "received": s.get("received"), "sent": s.get("sent"),
            "queue": depth.get(name), "blocked_s": s.get("blocked_s"),
            "rejected": dict(s.get("rejected") or {}),
            "quarantine_dropped": int(s.get("quarantine_dropped", 0)),
            "heartbeat_age_s": s.get("heartbeat_age_s"), "reason": s.get("reason")})
    return rows[::-1]


def datagram_counts(status: dict | None) -> dict:
    """The UDP ingest's lost, duplicated and late datagrams (zeros for other sources)."""
    src = ((status or {}).get("stages") or {}).get("source") or {}
    return {k: int(src.get(k, 0)) for k in ("datagrams", "lost_datagrams", "duplicates",
                                             "late")}
