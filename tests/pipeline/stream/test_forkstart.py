"""Issue 38.9: the stages start as forks of a server that imported their modules once
(pipeline.stream.forkstart), with what an exec'd stage had: its log, its own process
group, the daemon's environment, its exit code; ``fork_server = false`` exec's them."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipeline.stream.forkstart import StageProcess, warm_for
from tests.pipeline.stream.test_startup import write_topology


def _cmd(*args):
    return [sys.executable, "-m", "pipeline.cli", *args]


def test_a_forked_command_has_its_log_and_exit_code(tmp_path):
    log = tmp_path / "x.log"
    p = StageProcess(_cmd("stage", "--help"), dict(os.environ), str(log), "probe")
    assert p.wait(60) == 0 and p.poll() == 0
    assert "Usage: tcspc stage" in log.read_text()  # its output in its log, not ours
    bad = StageProcess(_cmd("stage", "histogram", "--n-tdc", "nope"), dict(os.environ),
                       str(log), "bad")
    assert bad.wait(60) == 2  # click's usage error: the exit code stands
    assert "Invalid value" in log.read_text()
    with pytest.raises(ValueError, match="python -m MODULE"):
        StageProcess(["/bin/true"], dict(os.environ), str(log), "x")


def test_a_forked_stage_is_signalled_and_named_like_an_execd_one(tmp_path):
    """Its own process group (a Ctrl-C at the terminal reaches the daemon only), its
    name in ``ps -o comm``, and -SIGNAL when killed (the environment it is given: the
    daemon's test below, whose stages' heartbeats carry the run's token from it)."""
    log = tmp_path / "p.log"
    env = dict(os.environ)
    q = StageProcess([sys.executable, "-m", "pipeline.cli", "stage", "sink", "--pull",
                      f"ipc://{tmp_path}/in", "--out", str(tmp_path / "out"), "--workers",
                      "1"], env, str(log), "sink")
    deadline = time.time() + 30
    while time.time() < deadline and "sink" not in Path(f"/proc/{q.pid}/comm").read_text():
        time.sleep(0.05)
    assert Path(f"/proc/{q.pid}/comm").read_text().strip() == "sink"
    assert os.getpgid(q.pid) == q.pid != os.getpgid(0)
    q.send_signal(signal.SIGKILL)
    assert q.wait(30) == -signal.SIGKILL
    q.send_signal(signal.SIGTERM)  # (an ended stage: nothing to signal, no error)


@pytest.mark.parametrize("fork", [True, False])
def test_the_daemon_forks_its_stages_or_execs_them(tmp_path, fork):
    """The same run either way; forked stages are named by their stage and are not the
    daemon's children (the server's), exec'd ones run their own interpreter."""
    scene = tmp_path / "small.toml"
    path = write_topology(tmp_path, source=f'kind = "sim"\nscene = "{scene}"\n'
                          'cycles = 200000\nrate = 2e6')
    text = path.read_text().replace("[daemon]\n",
                                    f"[daemon]\nfork_server = {str(fork).lower()}\n")
    path.write_text(text)
    d = subprocess.Popen(_cmd("daemon", "--config", str(path), "--run", "f"),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    status, seen = tmp_path / "state" / "status.json", {}
    deadline = time.time() + 90
    # (read again while the stage lives: status.json has its pid from the fork, before
    # the stage has named itself)
    while time.time() < deadline and d.poll() is None and not (
            len(seen) == 3 and all(c != "python" for c, _ in seen.values())):
        try:
            for name, s in json.loads(status.read_text())["stages"].items():
                pid = s.get("pid")
                if s.get("alive") and pid:
                    stat = Path(f"/proc/{pid}/stat").read_text()
                    seen[name] = (Path(f"/proc/{pid}/comm").read_text().strip(),
                                  int(stat.rsplit(")", 1)[1].split()[1]))
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.05)
    out, err = d.communicate(timeout=120)
    assert d.returncode == 0, err[-2000:]
    res = json.loads(out)
    assert res["accounting"]["balanced"] and res["accounting"]["words_in"] == 200_000 * 16
    assert len(seen) == 3, seen  # source, a worker, the sink
    for name, (comm, ppid) in seen.items():
        if fork:
            assert comm == name[:15] and ppid != d.pid, (name, comm, ppid)
        else:
            assert comm.startswith("python") and ppid == d.pid, (name, comm, ppid)


def test_warm_for_reads_only_what_it_needs_and_never_fails(tmp_path, monkeypatch):
    """The daemon's first step looks at the topology before it is checked: a missing,
    unreadable or invalid file starts nothing and raises nothing (load_topology reports
    it); ``fork_server = false`` starts no server; a [range] with a calibration asks the
    server to warm the range stage's kernels."""
    import pipeline.stream.forkstart as fs

    started = []
    monkeypatch.setattr(fs, "warm", lambda ranging=False: started.append(ranging))
    monkeypatch.delenv(fs.WARM_ENV, raising=False)
    warm_for(str(tmp_path / "missing.toml"))
    (tmp_path / "bad.toml").write_text("[daemon\n")
    warm_for(str(tmp_path / "bad.toml"))
    (tmp_path / "off.toml").write_text("[daemon]\nfork_server = false\n[range]\n")
    warm_for(str(tmp_path / "off.toml"))
    assert started == []
    (tmp_path / "on.toml").write_text('[source]\nkind = "sim"\n[range]\n'
                                      'calibration = "cal"\nestimator = "fast"\n')
    warm_for(str(tmp_path / "on.toml"))
    assert started == [True]
    assert json.loads(os.environ[fs.WARM_ENV]) == {"calibration": "cal", "estimator": "fast"}


def test_a_killed_fork_server_takes_its_stages_and_the_run_still_ends_exact(tmp_path):
    """SIGKILL the server the stages were forked from: they die with it (their parent-death
    signal), the supervisor restarts them from a new server, and the run ends finished,
    every word once (the source resumes after its journal, the worker from its checkpoint
    and the journal)."""
    scene = tmp_path / "small.toml"
    path = write_topology(tmp_path, source=f'kind = "sim"\nscene = "{scene}"\n'
                          'cycles = 300000\nrate = 1.5e6')
    d = subprocess.Popen(_cmd("daemon", "--config", str(path), "--run", "k"),
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    status, server = tmp_path / "state" / "status.json", None
    deadline = time.time() + 60
    while time.time() < deadline and server is None:
        try:
            st = json.loads(status.read_text())["stages"]
            if st["source"].get("words", 0) > 5e5:
                stat = Path(f"/proc/{st['source']['pid']}/stat").read_text()
                server = int(stat.rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.05)
    assert server is not None and server != d.pid
    os.kill(server, signal.SIGKILL)
    out, err = d.communicate(timeout=180)
    assert d.returncode == 0, err[-3000:]
    res = json.loads(out)
    assert res["restarts"].get("source", 0) >= 1
    acc = res["accounting"]
    assert acc["balanced"] and acc["words_in"] == 300_000 * 16 == acc["classified"]


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_a_sigkilled_daemon_takes_its_fork_server_and_stages_with_it(tmp_path):
    """The daemon SIGKILLed with a UDP source waiting (a source that never ends on its
    own): the server sees the daemon's end of its pipe close and ends, and every stage
    with it (their parent-death signal). Before, each forked stage held a copy of that pipe
    (multiprocessing gives it one), so the server and its stages outlived the daemon."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    path = write_topology(tmp_path, source=f'kind = "udp"\nbind = "127.0.0.1:{port}"\n'
                          'n_tdc = 16')
    d = subprocess.Popen(_cmd("daemon", "--config", str(path), "--run", "o"),
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    status, pids = tmp_path / "state" / "status.json", []
    deadline = time.time() + 60
    while time.time() < deadline and len(pids) < 3:
        try:
            pids = [s["pid"] for s in json.loads(status.read_text())["stages"].values()
                    if s.get("alive") and s.get("pid")]
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.05)
    assert len(pids) == 3, pids
    server = int(Path(f"/proc/{pids[0]}/stat").read_text().rsplit(")", 1)[1].split()[1])
    assert server != d.pid
    d.kill()
    d.wait(30)
    deadline = time.time() + 5
    while time.time() < deadline and any(_alive(p) for p in [server, *pids]):
        time.sleep(0.05)
    left = [p for p in [server, *pids] if _alive(p)]
    for p in left:  # (no orphan outlives the test either)
        os.kill(p, signal.SIGKILL)
    assert not left, "the fork server or its stages outlived the daemon"


def test_the_topologys_estimators_are_the_rangings():
    """The topology names the estimators itself (checking a topology must not import the
    ranging's numba kernels): the same list as the ranging's registry."""
    from pipeline.stream.topology import ESTIMATORS as named
    from stages.ranging import ESTIMATORS

    assert tuple(named) == tuple(ESTIMATORS)


def test_no_other_account_reaches_the_fork_server():
    """The server's socket (it forks whatever its client sends: a process as this
    account) lies in a directory only this account may enter (mode 0700), as the stages'
    ipc:// sockets and the state do."""
    from multiprocessing import forkserver

    from pipeline.stream.forkstart import warm

    warm()
    address = Path(forkserver._forkserver._forkserver_address)
    assert address.exists()
    st = address.parent.stat()
    assert st.st_uid == os.getuid() and st.st_mode & 0o077 == 0, oct(st.st_mode)


def test_the_servers_imports_are_the_stages_not_the_daemons():
    """The server imports what the stages use, before it forks the first: not the
    daemon's supervisor or the topology's pydantic models (0.1 CPU-s on the way to the
    first measurement, docs/performance.md), and not the ranging (numba, scipy: the range
    stage's, ``PRELOAD_RANGE``, only for a graph with one)."""
    from pipeline.stream.forkstart import PRELOAD

    code = ("import importlib, sys\n"
            f"for m in {PRELOAD!r}: importlib.import_module(m)\n"
            "print(' '.join(m for m in ('pipeline.stream.daemon', 'pipeline.stream.topology',"
            " 'pydantic', 'numba', 'scipy') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True).stdout.split()
    assert out == [], out


def _late_imports(tmp_path, topo: Path) -> dict[str, str]:
    """Each forked stage's imports after its fork, from its log (TCSPC_FORK_LATE_IMPORTS)."""
    from pipeline.stream.forkstart import LATE_IMPORTS_ENV

    p = subprocess.run(_cmd("daemon", "--config", str(topo), "--run", "late"),
                       capture_output=True, text=True, timeout=300,
                       env={**os.environ, LATE_IMPORTS_ENV: "1"})
    assert p.returncode == 0, p.stderr[-3000:]
    late = {}
    for f in sorted((tmp_path / "state" / "logs").glob("*.log")):
        lines = [ln for ln in f.read_text().splitlines()
                 if ln.startswith("forkstart: imported after the fork:")]
        assert lines, f.name
        late[f.stem] = lines[-1].rsplit(": ", 1)[1]
    return late


def test_a_forked_stage_imports_nothing_after_its_fork(tmp_path):
    """Every module the stages import is the server's (``PRELOAD``): one a stage imports
    after its fork is imported by each stage, on two cores, on the way to the first
    measurement. (Before: CURVE's zmq.auth.thread and zmq.asyncio with asyncio, numpy.ma,
    rich's emoji table, in every stage.) A capture replayed through 2 workers and the
    sink, with ``TCSPC_FORK_LATE_IMPORTS=1``: each stage's log says what it imported."""
    from pipeline.io.capture import CaptureWriter
    from stages.testpattern import pattern_words

    words, _ = pattern_words(20_000, 16, hit_prob=0.2, rng=5)
    with CaptureWriter(tmp_path / "cap", 16, kind="pattern") as w:
        w.write(words)
    topo = tmp_path / "topo.toml"
    topo.write_text(f'[daemon]\nstate = "{tmp_path / "state"}"\n[source]\nkind = "capture"\n'
                    f'capture = "{tmp_path / "cap"}"\n[histogram]\nworkers = 2\n'
                    f'measurement_cycles = 10000\nartifacts = "count-as-hits"\n'
                    f'[sink]\nout = "{tmp_path / "out"}"\n')
    late = _late_imports(tmp_path, topo)
    assert set(late) == {"source", "histogram-0", "histogram-1", "sink"}
    assert set(late.values()) == {"nothing"}, late


def test_a_forked_range_stage_imports_nothing_after_its_fork(tmp_path, caldir):
    """With a range stage the server imports the ranging too (``PRELOAD_RANGE``): the
    range stage imports nothing after its fork either (before: the chip check, at its
    first measurement). (The simulator's source imports the simulator, which a capture's
    or a chip's source does not need.)"""
    scene = tmp_path / "small.toml"
    path = write_topology(tmp_path, source=f'kind = "sim"\nscene = "{scene}"\n'
                          'cycles = 20000', extra=f'[range]\ncalibration = "{caldir}"\n')
    late = _late_imports(tmp_path, path)
    assert set(late) == {"source", "histogram-0", "range", "sink"}
    assert {k: v for k, v in late.items() if k != "source"} == dict.fromkeys(
        ["histogram-0", "range", "sink"], "nothing"), late
