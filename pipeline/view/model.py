"""What every open page shows, kept once per server: the daemon's status, the runs, and per
run followed its measurements, accounting identity and LSB drift.

:meth:`ViewModel.refresh` runs about once a second on the server's event loop (the pages
are then only rendered from it): it costs one status message or one ``stat`` of
status.json, a probe of the next measurement's file names, and the new files once. The
online LSB estimate (~0.5 s of CPU per 128-TDC measurement) runs on a worker thread, and
only while it takes under ``DRIFT_CPU_SHARE`` of a core: on a long run it is sampled. With
no page open nothing but the status is read.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.view import datasets, sensor
from pipeline.view.status import RateHistory, StatusFeed, daemon_state, read_status

#: The online LSB estimate may use this share of one core, at most.
DRIFT_CPU_SHARE = 0.05
#: With no page open for this long, a refresh only takes the daemon's status.
IDLE_S = 10.0
#: A run no page has asked about for this long is no longer followed.
FORGET_S = 120.0
RUNS_EVERY_S = 5.0


@dataclass
class RunTrack:
    """One run followed: its measurements, identity and drift."""

    run: str
    index: datasets.RunIndex
    consts: sensor.RunConstants
    tally: datasets.Tally = field(default_factory=datasets.Tally)
    left: int = 0                    #: measurements not yet counted in the tally
    accounting: dict | None = None
    drift: dict = field(default_factory=dict)   #: measurement -> lsb_drift()
    asked: float = 0.0

    @property
    def identity(self) -> dict:
        return datasets.identity(self.tally, self.accounting, self.left)


class ViewModel:
    def __init__(self, state: str | Path, out: str | Path, calibration: str | Path | None,
                 run: str | None = None, layout: str | None = None, feed: bool = True):
        self.state, self.out = Path(state), Path(out)
        self.cal_path = Path(calibration) if calibration else None
        self.pinned_run, self.layout_text = run, layout
        self.geometry = None  #: a stages.geometry.Geometry: the maps laid out as its array
        self.feed = StatusFeed(self.state) if feed else None
        self.history = RateHistory()
        self.status: dict | None = None
        self.runs: list[dict] = []
        self.tracks: dict[str, RunTrack] = {}
        self._runs_at = 0.0
        self._cal = None
        self._cal_key = None
        self.cal_error = ""
        self._meas: OrderedDict = OrderedDict()
        self._drift_busy = threading.Event()
        self._drift_next = 0.0
        self.updated = 0.0
        self.asked = 0.0  #: when a page last asked for anything

    # ---------------------------------------------------------------- refresh
    def refresh(self, now: float | None = None) -> None:
        now = time.time() if now is None else now
        self.status = self.feed.poll() if self.feed else read_status(self.state)
        self.history.add(self.status)
        self.updated = now
        if now - self.asked > IDLE_S:
            return  # nobody is looking: nothing else is read (a page asks, then it is)
        if now - self._runs_at > RUNS_EVERY_S or not self.runs:
            self.runs = datasets.list_runs(self.out)
            self._runs_at = now
        live = self.live_run
        if live:
            self.track(live)
        for name, tr in list(self.tracks.items()):
            if name != live and now - tr.asked > FORGET_S:
                del self.tracks[name]
                continue
            self._refresh_track(tr, now)

    def _refresh_track(self, tr: RunTrack, now: float) -> None:
        tr.index.refresh(now)
        if tr.consts.t_laser_win_s is None:  # a page opened before the run's journal
            consts = sensor.run_constants(self.state / "journal", tr.run)
            if consts != tr.consts:
                tr.consts = consts
                if tr.index.n_tdc is None:  # (and the array's size with it)
                    from pipeline.stream.journal import run_meta

                    tr.index.n_tdc = run_meta(self.state / "journal", tr.run).get("n_tdc")
                for key in [key for key in self._meas if key[0] == tr.run]:
                    del self._meas[key]  # drawn without the gate: drawn again with it
        if tr.accounting is None:
            tr.accounting = datasets.read_accounting(self.out, tr.run)
            if tr.accounting is not None:
                tr.index.rescan()  # the run ended: reconciliation may have backfilled
            tr.left = tr.tally.add(tr.index, tr.index.have["histograms"])
            tr.tally.read_journal(self.state / "journal", tr.run)
        self._drift(tr, now)

    def _drift(self, tr: RunTrack, now: float) -> None:
        """Start the LSB estimate of the newest measurement not done (then the oldest
        backlog), when the worker is free and its CPU budget allows."""
        cal = self.calibration
        if cal is None or self._drift_busy.is_set() or now < self._drift_next:
            return
        have = tr.index.have["histograms"]
        todo = next((k for k in reversed(have) if k not in tr.drift), None)
        if todo is None:
            return
        meas = self.measurement(tr.run, todo)
        if meas is None:
            return
        self._drift_busy.set()

        def work():
            t0 = time.thread_time()  # the CPU it takes (on a busy machine, not the wait)
            try:
                tr.drift[todo] = sensor.lsb_drift(meas["meas"], cal, tr.consts.window_s)
            except Exception as exc:  # noqa: BLE001 - shown, never fatal to the page
                tr.drift[todo] = {"k": todo, "n": 0, "error": f"{type(exc).__name__}: {exc}"}
            spent = time.thread_time() - t0
            self._drift_next = time.time() + spent * (1 / DRIFT_CPU_SHARE - 1)
            self._drift_busy.clear()

        threading.Thread(target=work, name="lsb-drift", daemon=True).start()

    def warm(self) -> None:
        """What the first measurement would otherwise pay (~1.5 s of imports and the
        calibration), paid at the server's start instead of in the middle of a run."""
        import polars  # noqa: F401
        import pyarrow.parquet  # noqa: F401
        import scipy.constants  # noqa: F401

        import stages.calibration_set  # noqa: F401

        _ = self.calibration

    def wake(self) -> None:
        """A page opened: bring everything up to date now, not at the next tick."""
        if time.time() - self.asked > IDLE_S:
            self.asked = time.time()
            self.refresh()

    # ---------------------------------------------------------------- what pages ask
    @property
    def live_run(self) -> str | None:
        """The daemon's run (when a status says one), else the pinned one."""
        return (self.status or {}).get("run") or self.pinned_run

    def default_run(self) -> str | None:
        if self.pinned_run:
            return self.pinned_run
        live = self.live_run
        if live:
            return live
        return self.runs[0]["run"] if self.runs else None

    def daemon(self, now: float | None = None):
        return daemon_state(self.status, time.time() if now is None else now, self.state)

    def track(self, run: str) -> RunTrack:
        tr = self.tracks.get(run)
        if tr is None:
            consts = sensor.run_constants(self.state / "journal", run)
            from pipeline.stream.journal import run_meta

            n_tdc = run_meta(self.state / "journal", run).get("n_tdc")
            tr = RunTrack(run, datasets.RunIndex(self.out, run, n_tdc), consts)
            self.tracks[run] = tr
            self._refresh_track(tr, time.time())
        tr.asked = self.asked = time.time()
        return tr

    def run_known(self, run: str) -> bool:
        """A run id found under the datasets or the daemon's (a directory name, never a
        path: ID_PATTERN)."""
        from pipeline.stream.wire import ID_PATTERN

        return isinstance(run, str) and bool(ID_PATTERN.fullmatch(run)) and (
            any(r["run"] == run for r in self.runs) or run == (self.status or {}).get("run"))

    @property
    def calibration(self):
        """The calibration in use, reloaded when its meta.json changes (a new one
        published); None without one, with ``cal_error`` saying why."""
        if self.cal_path is None:
            self.cal_error = "no calibration given (--calibration)"
            return None
        try:
            key = (self.cal_path / "meta.json").stat().st_mtime
        except OSError:
            key = None
        if key != self._cal_key or (self._cal is None and not self.cal_error):
            from pipeline.io.caldir import load_calibration

            try:
                self._cal, self.cal_error = load_calibration(self.cal_path), ""
            except Exception as exc:  # noqa: BLE001 - the page says it
                self._cal, self.cal_error = None, f"{self.cal_path}: {exc}"
            self._cal_key = key
        return self._cal

    def measurement(self, run: str, k: int) -> dict | None:
        """Measurement ``k`` of ``run`` with everything the sensor panel draws (cached)."""
        key = (run, k)
        if key in self._meas:
            self._meas.move_to_end(key)
            return self._meas[key]
        tr = self.tracks.get(run) or self.track(run)
        meas = datasets.read_measurement(tr.index, k)
        if meas is None:
            return None
        ranges = datasets.read_ranges(tr.index, k)
        cal = self.calibration
        ret, note = sensor.return_codes(meas, ranges, cal, tr.consts)
        if cal is None and ranges is not None:
            note = f"return not marked: {self.cal_error}"
        dead, hot = sensor.pixel_flags(meas.classes["hit"], meas.cycles)
        got = {"meas": meas, "ranges": ranges, "return_code": ret, "note": note,
               "reset_code": sensor.reset_peak_codes(meas.counts), "dead": dead, "hot": hot,
               "light": sensor.light_of(meas)}
        if ranges is not None and tr.index.have["ranges"] and k in tr.index.have["ranges"] \
                or k != tr.index.latest:
            self._meas[key] = got  # (the newest without its ranges yet is read again)
            while len(self._meas) > 6:
                self._meas.popitem(last=False)
        return got

    def layout(self, n_tdc: int) -> tuple[int, int]:
        try:
            return sensor.parse_layout(self.layout_text, n_tdc)
        except ValueError:
            return sensor.default_layout(n_tdc)

    def drift_series(self, run: str) -> dict:
        tr = self.tracks.get(run)
        done = tuple(tr.drift.values()) if tr else ()  # (one C call: the worker may add)
        rows = sorted((d for d in done if d.get("n")), key=lambda d: d["k"])
        out = {k: np.array([d[k] for d in rows], np.float64)
               for k in ("k", "median_ps", "p10_ps", "p90_ps", "light")}
        flagged: dict[int, str] = {}  # TDC -> why, over every sampled measurement
        for d in sorted(done, key=lambda d: d["k"]):
            flagged.update(d.get("flagged") or {})
        out["flagged"] = flagged
        return out

    def close(self) -> None:
        if self.feed is not None:
            self.feed.close()
