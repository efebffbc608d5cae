"""What the daemon runs beside the graph, never in it: the status PUB the web page subscribes
to, and the web page's server itself (``tcspc view``, from the topology's ``[view]``).

Neither can fail or slow the run: the PUB never blocks (a record nobody takes is dropped),
and the page's server is restarted when it dies, ``VIEW_RESTART_S`` later, however often.
"""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import zmq

#: A dead web page server ([view]) is started again after this long.
VIEW_RESTART_S = 5.0


def status_endpoint(state: str | Path) -> str:
    """Where the daemon publishes each status it writes (the web page subscribes)."""
    return f"ipc://{Path(state).resolve()}/sock/status"


def status_pub(ctx: zmq.Context, state: Path, log):
    """The status PUB (None when it cannot be bound: the daemon runs all the same)."""
    from pipeline.stream.stage import bind

    pub = ctx.socket(zmq.PUB)
    pub.setsockopt(zmq.SNDHWM, 2)
    pub.setsockopt(zmq.LINGER, 0)
    try:
        bind(pub, status_endpoint(state))
    except (zmq.ZMQError, OSError) as exc:
        log(f"status PUB not bound ({exc}); the web page reads status.json instead")
        pub.close()
        return None
    return pub


def view_args(topo) -> list[str] | None:
    """``tcspc view``'s arguments for the run's state, datasets and calibration and the
    [view] keys (None without a [view] section)."""
    v = topo.view
    if v is None:
        return None
    cal = (topo.range or {}).get("calibration") or topo.histogram.get("calibration")
    return ["view", "--state", str(topo.state), "--out", str(topo.sink["out"]),
            "--run", topo.run, "--port", str(v.get("port", 5006)),
            "--bind", v.get("bind", "127.0.0.1"),
            *(("--calibration", str(cal)) if cal else ()),
            *(("--layout", v["layout"]) if v.get("layout") else ()),
            *(("--geometry", v["geometry"]) if v.get("geometry") else ())]


class Sidecar:
    """A process beside the graph (the daemon's ``Proc``, started by its ``start``): not
    part of the run, so never waited for, restarted when it dies, ended with the daemon."""

    def __init__(self, proc, start, log, log_path: Path):
        self.proc, self.start, self.log, self.log_path = proc, start, log, log_path

    def keep(self) -> None:
        p = self.proc
        if p.popen is None or p.popen.poll() is None:
            return
        now = time.time()
        if p.restart_at is None:
            p.exit_codes.append(p.popen.returncode)
            p.restart_at = now + VIEW_RESTART_S
            self.log(f"{p.name}: died (exit {p.popen.returncode}); restart in "
                     f"{VIEW_RESTART_S:.0f} s (see {self.log_path})")
        elif now >= p.restart_at:
            p.restart_at, p.restarts = None, p.restarts + 1
            self.start(p)

    def end(self) -> None:
        p = self.proc
        if p.popen is None or p.popen.poll() is not None:
            return
        p.popen.terminate()
        try:
            p.popen.wait(timeout=5)
        except subprocess.TimeoutExpired:
            p.popen.kill()
            p.popen.wait()
