"""The daemon as a systemd service (issue 38.8): ``tcspc daemon --config T --unit`` prints a
unit for that topology; ``docs/systemd/tcspc-daemon.service`` is the same unit for
``/etc/tcspc/topology.toml`` (a test keeps the two equal)."""

from __future__ import annotations

import shlex
import sys
from pathlib import Path

#: the unit's watchdog: the supervision loop sends WATCHDOG=1 every half of it
WATCHDOG_SEC = 30
#: where the shipped unit expects the topology and the install
DOC_CONFIG = "/etc/tcspc/topology.toml"
DOC_EXE = "/opt/tcspc/.venv/bin/tcspc"

UNIT = """\
# The tcspc-lidar stream daemon (the whole graph under its supervisor) as a systemd service
# (docs/operations.md, "The daemon as a service"). Printed by
#   tcspc daemon --config {config} --unit
# Install: as /etc/systemd/system/tcspc-daemon.service, then
#   systemctl daemon-reload && systemctl enable --now tcspc-daemon
# Set [daemon] run in the topology (or --run here): a restart then resumes the same run.

[Unit]
Description=tcspc-lidar stream daemon ({config})
Documentation=file:///opt/tcspc/docs/operations.md
Wants=network-online.target
After=network-online.target
# systemd's own budget for restarting the daemon (the stages have theirs, in the topology)
StartLimitIntervalSec=3600
StartLimitBurst=5

[Service]
# READY=1 once every stage has reported; STATUS= the run's state; STOPPING=1 at the end
Type=notify
NotifyAccess=main
# WATCHDOG=1 comes from the supervision loop every {half} s: a daemon silent for {wd} s is
# killed and restarted (it resumes the run from its journal and checkpoints)
WatchdogSec={wd}
# its stages report within 60 s on a loaded machine (STARTUP_S), then READY=1
TimeoutStartSec=180
# a stop ends the graph in ~3 s; the reconciliation and the accounting follow
TimeoutStopSec=300
User=tcspc
Group=tcspc
Environment=PYTHONUNBUFFERED=1
ExecStart={exec}
# SIGTERM to the daemon only: it stops its stages in order (the source first)
KillMode=mixed
# exits: 0 finished, 3 incomplete, 143 stopped (resumable): an end, not a crash; 1 a
# stage out of its restart budget and 2 a bad topology are not retried by systemd; a
# crash or a watchdog kill is
SuccessExitStatus=3 143
RestartPreventExitStatus=1 2 3
Restart=on-failure
RestartSec=5
UMask=0077
NoNewPrivileges=yes
ProtectSystem=strict
ReadWritePaths={rw}
PrivateTmp=yes

[Install]
WantedBy=multi-user.target
"""


def daemon_unit(config: str | None, run: str | None = None, exe: str | None = None) -> str:
    """The unit for ``tcspc daemon --config config [--run run]``: its state and output
    directories writable (from the topology), everything else read-only."""
    from pipeline.stream.topology import load_topology

    if exe is None:
        exe = str(Path(sys.executable).with_name("tcspc"))
    cfg = str(Path(config).resolve()) if config else None
    rw = ["/var/lib/tcspc"]
    if cfg:
        topo = load_topology(cfg, run, writable=False)
        rw = sorted({str(Path(topo.state).resolve()), str(Path(topo.sink["out"]).resolve())})
    argv = [exe, "daemon", *(("--config", cfg) if cfg else ()), *(("--run", run) if run else ())]
    return UNIT.format(config=cfg or "the default topology", wd=WATCHDOG_SEC,
                       half=WATCHDOG_SEC // 2, exec=shlex.join(argv), rw=" ".join(rw))


def doc_unit() -> str:
    """docs/systemd/tcspc-daemon.service's text."""
    unit = UNIT.format(config=DOC_CONFIG, wd=WATCHDOG_SEC, half=WATCHDOG_SEC // 2,
                       exec=f"{DOC_EXE} daemon --config {DOC_CONFIG}",
                       rw="/var/lib/tcspc")
    return unit
