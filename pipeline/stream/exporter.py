"""The operator's view for a monitoring system (issue 38.8): Prometheus / OpenMetrics metrics
served by the daemon, and the run's counters that survive a daemon restart.

``[metrics] port = N`` (off without the section) serves ``/metrics`` from a thread of the
daemon on ``host`` (127.0.0.1 unless configured), with prometheus_client's WSGI app
(``make_wsgi_app``: the text format, or OpenMetrics when the scraper asks for it) behind
a token: ``Authorization: Bearer TOKEN`` or ``?token=TOKEN``, the token in
``STATE/metrics.token`` (0600, made once and kept, so a Prometheus ``credentials_file``
stays valid across restarts). Without it: 401. The same rule as the live page's, whose
token is in ``STATE/view.url``: any local account reaches a loopback port.

The values are the daemon's own (``status.json``'s source), taken once a second by the
supervision loop (:meth:`Exporter.update`); a scrape reads that snapshot, never the stages.

:class:`RunTotals`: restarts, frozen stages and rejections by reason are run totals, kept in
``STATE/counters/RUN.json`` (written atomically every second and at the end) and taken up
by a resumed run: a stage's counters restart at 0 with each process, the totals do not.
"""

from __future__ import annotations

import hmac
import json
import os
import threading
import time
from collections import Counter
from pathlib import Path

from pipeline.io.atomic import atomic_path

#: the families' prefix
NS = "tcspc"


# --------------------------------------------------------------------------- run totals
class RunTotals:
    """Restarts, frozen and rejections (by stage and reason) of the whole run, across the
    stages' restarts (a new pid: the old one's last counts are folded in) and the daemon's
    (the file, reloaded on resume)."""

    KEYS = ("restarts", "frozen", "quarantine_dropped")

    def __init__(self, state: Path, run: str):
        self.path = Path(state) / "counters" / f"{run}.json"
        self.lock = threading.Lock()
        base = {}
        try:
            base = json.loads(self.path.read_text())
        except (OSError, ValueError):
            pass  # a new run (or an unreadable file: the totals start again, said in docs)
        self.daemon_starts = int(base.get("daemon_starts", 0)) + 1
        self.base = {k: Counter({s: int(v) for s, v in (base.get(k) or {}).items()})
                     for k in self.KEYS}
        self.rejected = {s: Counter({r: int(n) for r, n in d.items()})
                         for s, d in (base.get("rejected") or {}).items()}
        self.live: dict[str, tuple] = {}  #: stage -> (pid, rejected, quarantine_dropped)

    def observe(self, rec: dict) -> None:
        """A heartbeat record (the collector's thread): a new pid folds the old one in."""
        name = rec.get("stage")
        if not isinstance(name, str):
            return
        rej = rec.get("rejected") if isinstance(rec.get("rejected"), dict) else {}
        with self.lock:
            old = self.live.get(name)
            if old is not None and old[0] != rec.get("pid"):
                self._fold(name, old)
            self.live[name] = (rec.get("pid"), dict(rej), int(rec.get("quarantine_dropped")
                                                               or 0))

    def _fold(self, name: str, live: tuple) -> None:
        self.rejected.setdefault(name, Counter()).update(live[1])
        self.base["quarantine_dropped"][name] += live[2]

    def totals(self, procs=()) -> dict:
        """The run's totals now: ``{"restarts": {stage: n}, "frozen": ..., "rejected":
        {stage: {reason: n}}, "quarantine_dropped": ..., "daemon_starts": n}``."""
        with self.lock:
            rejected = {s: Counter(c) for s, c in self.rejected.items()}
            dropped = Counter(self.base["quarantine_dropped"])
            for name, live in self.live.items():
                rejected.setdefault(name, Counter()).update(live[1])
                dropped[name] += live[2]
        restarts, frozen = Counter(self.base["restarts"]), Counter(self.base["frozen"])
        for p in procs:
            restarts[p.name] += p.restarts
            frozen[p.name] += p.frozen
        return {"daemon_starts": self.daemon_starts,
                "restarts": {k: v for k, v in restarts.items() if v},
                "frozen": {k: v for k, v in frozen.items() if v},
                "rejected": {s: {r: n for r, n in c.items() if n}
                             for s, c in rejected.items() if any(c.values())},
                "quarantine_dropped": {k: v for k, v in dropped.items() if v}}

    def save(self, procs=()) -> dict:
        """Write the totals (atomically; a full state disk keeps the last file)."""
        tot = self.totals(procs)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_path(self.path) as tmp:
                tmp.write_text(json.dumps(tot, indent=1) + "\n")
        except OSError:
            pass  # (said by status.json's own failure; the next second tries again)
        return tot

    def merged(self, metrics: dict[str, dict]) -> dict[str, dict]:
        """The stages' last records with their run-total rejections (for the accounting)."""
        tot = self.totals()
        out = {name: dict(m) for name, m in metrics.items()}
        for name, rej in tot["rejected"].items():
            out.setdefault(name, {})["rejected"] = rej
        for name, n in tot["quarantine_dropped"].items():
            out.setdefault(name, {})["quarantine_dropped"] = n
        return out


# ------------------------------------------------------------------------------- token
def secret_token(path: Path) -> str:
    """A random token kept in ``path`` (0600, its folder 0700): made once, then read (one
    empty or cut short is made anew). Never followed through a link."""
    import secrets

    from pipeline.stream.state import open_nofollow

    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW, 0o600)
    except FileExistsError:
        with os.fdopen(open_nofollow(path, os.O_RDONLY), "r") as fh:
            os.fchmod(fh.fileno(), 0o600)
            token = fh.read().strip()
        if len(token) >= 32:
            return token
        fd = open_nofollow(path, os.O_WRONLY | os.O_TRUNC)
    token = secrets.token_hex(32)
    with os.fdopen(fd, "w") as fh:
        fh.write(token + "\n")
    return token


def authorized(environ: dict, token: str) -> bool:
    """A request with the token: ``Authorization: Bearer TOKEN`` or ``?token=TOKEN``."""
    from urllib.parse import parse_qs

    got = []
    auth = environ.get("HTTP_AUTHORIZATION", "")
    if auth[:7].lower() == "bearer ":
        got.append(auth[7:].strip())
    got += parse_qs(environ.get("QUERY_STRING", "")).get("token", [])
    return any(hmac.compare_digest(g.encode(), token.encode()) for g in got)


# ---------------------------------------------------------------------------- metrics
def _families(snap: dict) -> list:
    """The metric families of one snapshot (:meth:`Exporter.update`)."""
    from prometheus_client.core import (
        CounterMetricFamily,
        GaugeMetricFamily,
        InfoMetricFamily,
        StateSetMetricFamily,
    )

    st, tot = snap["status"], snap["totals"]
    stages = st.get("stages", {})
    out = []
    info = InfoMetricFamily(f"{NS}_run", "the daemon's run", labels=[])
    info.add_metric([], {"run": str(st.get("run")), "topology": str(st.get("topology"))})
    out.append(info)
    state = StateSetMetricFamily(f"{NS}_run_state", "the run's state", labels=[])
    now = st.get("state", "running")
    state.add_metric([], {s: s == now for s in ("running", "finished", "incomplete",
                                                 "interrupted", "failed")})
    out.append(state)
    g = GaugeMetricFamily(f"{NS}_run_started_seconds", "when the daemon started (Unix time)")
    g.add_metric([], float(st.get("started", 0)))
    out.append(g)
    c = CounterMetricFamily(f"{NS}_daemon_starts", "daemons that ran this run (1 + resumes)")
    c.add_metric([], tot["daemon_starts"])
    out.append(c)
    c = CounterMetricFamily(f"{NS}_words_in", "words journaled by the run (the accounting's "
                            "words_in)")
    c.add_metric([], snap["words_in"])
    out.append(c)
    src = stages.get("source", {})
    for key, name, what in (
            ("received", "datagrams_received", "UDP datagrams read (this ingest process)"),
            ("accepted", "datagrams_accepted", "UDP datagrams taken into the run"),
            ("lost_datagrams", "datagrams_lost", "UDP datagrams lost (sequence gaps)"),
            ("duplicates", "datagrams_duplicate", "UDP datagrams received twice"),
            ("late", "datagrams_late", "UDP datagrams too late for the reorder window"),
            ("ring_dropped", "datagrams_ring_dropped", "UDP datagrams dropped by a full "
             "ingest ring")):
        if key in src and "accepted" in src:  # (a UDP run's ingest)
            c = CounterMetricFamily(f"{NS}_{name}", what)
            c.add_metric([], float(src.get(key) or 0))
            out.append(c)
    per_stage = {
        "messages_received": ("received", CounterMetricFamily, "messages taken (this "
                              "process of the stage)"),
        "messages_sent": ("sent", CounterMetricFamily, "messages sent (this process)"),
        "stage_words": ("words_total", CounterMetricFamily, "words folded in (a histogram "
                        "worker, from its checkpoint on)"),
        "stage_words_per_second": ("rate_words_s", GaugeMetricFamily, "words per second "
                                   "over the last heartbeat"),
        "stage_blocked_seconds": ("blocked_s", CounterMetricFamily, "time spent waiting "
                                  "on a slow consumer (this process)"),
        "stage_paused_seconds": ("paused_s", CounterMetricFamily, "time paused on a full "
                                 "disk (this process)"),
        "stage_heartbeat_age_seconds": ("heartbeat_age_s", GaugeMetricFamily, "since the "
                                        "stage's last heartbeat"),
    }
    for name, (key, kind, what) in per_stage.items():
        fam = kind(f"{NS}_{name}", what, labels=["stage"])
        for s, m in stages.items():
            if isinstance(m.get(key), (int, float)):
                fam.add_metric([s], float(m[key]))
        out.append(fam)
    c = CounterMetricFamily(f"{NS}_stage_words_by_class", "words folded in by class (a "
                            "histogram worker, this process from its checkpoint on; the "
                            "run's truth is the accounting's)", labels=["stage", "class"])
    for s, m in sorted(stages.items()):
        if isinstance(m.get("classes"), dict):
            for cls, n in sorted(m["classes"].items()):
                if isinstance(n, (int, float)):
                    c.add_metric([s, str(cls)], float(n))
    out.append(c)
    if "source" in stages and isinstance(src.get("words"), (int, float)):
        c = CounterMetricFamily(f"{NS}_source_words", "words the source sent (this "
                                "process)")
        c.add_metric([], float(src["words"]))
        out.append(c)
    health = StateSetMetricFamily(f"{NS}_stage_health", "each stage's health (tcspc status)",
                                  labels=["stage"])
    for s, m in stages.items():
        h = m.get("health")
        health.add_metric([s], {x: x == h for x in (
            "ok", "waiting", "silent", "frozen", "paused", "restarting", "down", "finished")})
    out.append(health)
    for key, name, what in (("restarts", "stage_restarts", "restarts of the stage in the "
                             "run (across daemon restarts)"),
                            ("frozen", "stage_frozen", "times the stage missed its heartbeat "
                             "deadline and was killed"),
                            ("quarantine_dropped", "quarantine_dropped", "rejected inputs "
                             "counted but not kept (quarantine full)")):
        c = CounterMetricFamily(f"{NS}_{name}", what, labels=["stage"])
        for s in stages:
            c.add_metric([s], float(tot[key].get(s, 0)))
        out.append(c)
    c = CounterMetricFamily(f"{NS}_rejected", "inputs rejected (and quarantined) by reason, "
                            "run totals", labels=["stage", "reason"])
    for s, by in sorted(tot["rejected"].items()):
        for reason, n in sorted(by.items()):
            c.add_metric([s, reason], float(n))
    out.append(c)
    g = GaugeMetricFamily(f"{NS}_restart_budget_available", "restarts the stage may still "
                          "take now (the budget refills at its rate)", labels=["stage"])
    for s, v in snap["budget"].items():
        g.add_metric([s], v)
    out.append(g)
    g = GaugeMetricFamily(f"{NS}_queue_depth_messages", "messages sent upstream and not yet "
                          "taken (approximate)", labels=["stage"])
    for s, v in (st.get("queue_depth") or {}).items():
        g.add_metric([s], float(v))
    out.append(g)
    g = GaugeMetricFamily(f"{NS}_lag_words", "words journaled and not yet folded in by the "
                          "histogram worker (its TDC range's share)", labels=["stage"])
    for s, v in snap["lag"].items():
        g.add_metric([s], float(v))
    out.append(g)
    c = CounterMetricFamily(f"{NS}_forged_heartbeats", "heartbeats without the run's token")
    c.add_metric([], float(st.get("forged_heartbeats", 0)))
    out.append(c)
    for key, name, what in (("free", "disk_free_bytes", "bytes free to this user"),
                            ("size", "disk_size_bytes", "size of the file system")):
        g = GaugeMetricFamily(f"{NS}_{name}", what + " (state: the journal's; out: the "
                              "datasets')", labels=["dir"])
        for d, v in snap["disk"].items():
            g.add_metric([d], float(v[key]))
        out.append(g)
    g = GaugeMetricFamily(f"{NS}_status_updated_seconds", "when these values were taken")
    g.add_metric([], float(st.get("updated", 0)))
    out.append(g)
    return out


def _disk(path: Path) -> dict:
    try:
        v = os.statvfs(path)
    except OSError:
        return {"free": -1, "size": -1}
    return {"free": v.f_bavail * v.f_frsize, "size": v.f_blocks * v.f_frsize}


class Exporter:
    """The metrics server of one daemon (``[metrics]``): bound at start, served by a
    thread until the daemon exits (its final values included)."""

    def __init__(self, topo, host: str = "127.0.0.1", port: int = 0):
        from prometheus_client import make_wsgi_app
        from prometheus_client.registry import CollectorRegistry

        from pipeline.stream.journal import IndexSpans

        self.topo = topo
        self.token = secret_token(Path(topo.state) / "metrics.token")
        self.snapshot: dict | None = None
        self.index = IndexSpans(Path(topo.state) / "journal", topo.run)
        registry = CollectorRegistry(auto_describe=False)
        registry.register(self)
        self.server = _serve(_guard(make_wsgi_app(registry), self.token), host, port)
        self.port = self.server.server_port
        shown = f"[{host}]" if ":" in host else host
        self.url = f"http://{shown}:{self.port}/metrics"
        # (the URL only: the token is in metrics.token, which Prometheus reads as a file)
        self.url_file = _write_metrics_url(Path(topo.state), self.url)
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True,
                                       name="metrics")
        self.thread.start()

    def collect(self):
        snap = self.snapshot
        return [] if snap is None else _families(snap)

    def update(self, status: dict, totals: dict, budget: dict[str, float]) -> None:
        """A new snapshot (the supervision loop, once a second)."""
        from pipeline.stream.topology import tdc_ranges

        self.index.update()
        words = int(self.index.words)
        lag = {}
        cycles = words // max(int(self.topo.n_tdc or 1), 1)
        for i, (a, b) in enumerate(tdc_ranges(self.topo)):
            m = status.get("stages", {}).get(f"histogram-{i}", {})
            if isinstance(m.get("words_total"), (int, float)):
                lag[f"histogram-{i}"] = max(0, cycles * (b - a) - int(m["words_total"]))
        self.snapshot = {"status": status, "totals": totals, "budget": budget,
                         "words_in": words, "lag": lag, "taken": time.time(),
                         "disk": {"state": _disk(Path(self.topo.state)),
                                  "out": _disk(Path(self.topo.sink["out"]))}}

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def _write_metrics_url(state: Path, url: str) -> Path | None:
    from pipeline.stream.state import open_nofollow

    path = state / "metrics.url"
    try:
        fd = open_nofollow(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "w") as fh:
            fh.write(url + "\n")
        return path
    except OSError:
        return None


def _guard(app, token: str):
    """``app`` behind the token (401 without it)."""

    def guarded(environ, start_response):
        if not authorized(environ, token):
            start_response("401 Unauthorized", [
                ("Content-Type", "text/plain; charset=utf-8"),
                ("WWW-Authenticate", 'Bearer realm="tcspc metrics"'),
                ("Cache-Control", "no-store")])
            return [b"401: this needs the token of STATE/metrics.token (Authorization: "
                    b"Bearer TOKEN, or ?token=TOKEN)\n"]
        return app(environ, start_response)

    return guarded


def _serve(app, host: str, port: int):
    """A bound (not yet serving) threading WSGI server; OSError when it cannot bind."""
    import socket
    from wsgiref.simple_server import WSGIRequestHandler, make_server

    from prometheus_client.exposition import ThreadingWSGIServer

    class Quiet(WSGIRequestHandler):
        def log_message(self, *args):  # (a scrape a second is not worth a log line)
            pass

    class Server(ThreadingWSGIServer):
        daemon_threads = True

    if ":" in host:
        Server.address_family = socket.AF_INET6
    return make_server(host, port, app, server_class=Server, handler_class=Quiet)
