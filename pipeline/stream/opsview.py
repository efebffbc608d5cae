"""What the daemon shows a monitoring system and a service manager (issue 38.8), in one
object the supervisor calls at a few points: the run's totals (``exporter.RunTotals``),
the metrics server (``exporter.Exporter``, with ``[metrics]``) and systemd's notifications
(``notify.Notifier``, under ``Type=notify``)."""

from __future__ import annotations

from pipeline.stream.exporter import Exporter, RunTotals
from pipeline.stream.notify import Notifier


class OpsView:
    def __init__(self, topo, log):
        self.topo, self.log = topo, log
        self.totals = RunTotals(topo.state, topo.run)
        self.notifier = Notifier()
        self.exporter = None
        self.failing = False  #: the last update failed (said once in the log)
        cfg = topo.exporter
        if cfg is not None:
            host, port = cfg.get("host", "127.0.0.1"), int(cfg.get("port", 0))
            try:
                self.exporter = Exporter(topo, host, port)
            except OSError as exc:
                from pipeline.stream.state import StateError

                raise StateError(f"{topo.path}: the daemon cannot start; nothing was started:"
                                 f"\nmetrics: cannot listen on {host}:{port} ([metrics] "
                                 f"port): {exc.strerror or exc}") from None
            log(f"metrics on {self.exporter.url} (bearer token in "
                f"{topo.state / 'metrics.token'})")

    def tick(self, sup) -> None:
        """Each iteration of the supervision loop: the watchdog, and READY=1 once every
        stage has reported or finished."""
        self.notifier.watchdog()
        if not self.notifier.ready_sent and all(p.name in sup.metrics or p.finished
                                                for p in sup.procs):
            self.notifier.ready(f"run {self.topo.run}: {len(sup.procs)} stages up")

    def update(self, sup, status: dict) -> None:
        """Each status written (once a second, and at the end): totals saved, the metrics'
        snapshot, systemd's STATUS line. The operator's view never stops a run: a failure
        here is logged once and the run goes on."""
        try:
            self._update(sup, status)
            self.failing = False
        except Exception as exc:  # noqa: BLE001 - a monitoring aid must not end the run
            if not self.failing:
                self.log(f"metrics not updated: {type(exc).__name__}: {exc}")
            self.failing = True

    def _update(self, sup, status: dict) -> None:
        totals = self.totals.save(sup.procs)
        status["totals"] = totals
        if self.exporter is not None:
            budget = {p.name: (float(p.budget.available()) if p.budget is not None
                               else float(self.topo.restarts)) for p in sup.procs}
            self.exporter.update(status, totals, budget)
        src = status.get("stages", {}).get("source", {})
        words = self.exporter.snapshot["words_in"] if self.exporter is not None else None
        self.notifier.status(
            f"{status.get('state')}: " + (f"{words:,} words journaled; " if words is not None
                                         else f"source {src.get('words', 0):,} words; ")
            + f"restarts {sum(totals['restarts'].values())}"
            + (f"; paused {', '.join(status['paused'])}" if status.get("paused") else ""))

    def stopping(self) -> None:
        self.notifier.ready()  # (a run that ended before every stage reported)
        self.notifier.stopping("the graph has ended: reconciling")

    def close(self) -> None:
        """The metrics server and the notify socket (the CLI's exit does the same)."""
        if self.exporter is not None:
            self.exporter.close()
        self.notifier.close()
