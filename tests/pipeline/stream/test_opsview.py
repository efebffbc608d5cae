"""The operator's view (issue 38.8): Prometheus metrics behind a token, systemd's
notifications, and run totals that survive a daemon restart, from real daemons."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from pipeline.stream.notify import Notifier


def scrape(url: str, token: str | None = None, query: bool = False) -> dict:
    """{family name: {tuple(sorted labels): value}} of one scrape."""
    if token and query:
        url += f"?token={token}"
    req = urllib.request.Request(url)
    if token and not query:
        req.add_header("Authorization", f"Bearer {token}")
    with urllib.request.urlopen(req, timeout=10) as resp:
        text = resp.read().decode()
    out = {}
    for fam in text_string_to_metric_families(text):
        for s in fam.samples:
            out.setdefault(s.name, {})[tuple(sorted(s.labels.items()))] = s.value
    return out


def with_metrics(topo_path, extra="[metrics]\nport = 0\n"):
    topo_path.write_text(topo_path.read_text() + extra)
    return topo_path


def test_metrics_of_a_finished_run_equal_its_accounting(tmp_path, daemon_helpers):
    """In-process supervisor, real stages: after the run the last scrape's words in equal
    the accounting's words_in, every stage has its families, and the page needs the token
    (401 without it, or with a wrong one; the bearer header and ?token= both work)."""
    topo = with_metrics(daemon_helpers.topology(tmp_path, cycles=40_000))
    result, sup = daemon_helpers.run_daemon(topo, "m")
    try:
        assert result["state"] == "finished"
        ex = sup.ops.exporter
        url = (tmp_path / "state" / "metrics.url").read_text().strip()
        assert url == ex.url and url.startswith("http://127.0.0.1:")
        token = (tmp_path / "state" / "metrics.token").read_text().strip()
        assert oct(os.stat(tmp_path / "state" / "metrics.token").st_mode & 0o777) == "0o600"
        for bad in (None, "x" * 64):
            with pytest.raises(urllib.error.HTTPError) as e:
                scrape(url, bad)
            assert e.value.code == 401
        m = scrape(url, token)
        assert m == scrape(url, token, query=True)
        # OpenMetrics when the scraper asks for it (the library's negotiation, behind ours)
        req = urllib.request.Request(url, headers={
            "Authorization": f"Bearer {token}", "Accept": "application/openmetrics-text"})
        with urllib.request.urlopen(req, timeout=10) as resp:
            assert resp.headers["Content-Type"].startswith("application/openmetrics-text")
            om = resp.read().decode()
        assert om.endswith("# EOF\n") and "tcspc_words_in_total " in om
        words = m["tcspc_words_in_total"][()]
        assert words == result["accounting"]["words_in"] == 40_000 * daemon_helpers.N
        names = {dict(k)["stage"] for k in m["tcspc_stage_restarts_total"]}
        assert names == {"source", "histogram-0", "histogram-1", "sink"}
        assert m["tcspc_run_state"][(("tcspc_run_state", "finished"),)] == 1
        assert m["tcspc_stage_health"][(("stage", "sink"),
                                        ("tcspc_stage_health", "finished"))] == 1
        assert m["tcspc_disk_free_bytes"][(("dir", "state"),)] > 0
        assert m["tcspc_disk_free_bytes"][(("dir", "out"),)] > 0
        assert m["tcspc_restart_budget_available"][(("stage", "source"),)] == 3.0
        assert m["tcspc_daemon_starts_total"][()] == 1
        assert "tcspc_source_words_total" in m and "tcspc_messages_received_total" in m
        # the words by class, live from the workers' heartbeats: at the end, the
        # accounting's classes (issue 38.8)
        by_class = {}
        for k, v in m["tcspc_stage_words_by_class_total"].items():
            cls = dict(k)["class"]
            by_class[cls] = by_class.get(cls, 0) + v
        assert by_class == {k: float(v) for k, v in result["accounting"]["classes"].items()}
    finally:
        sup.ops.exporter.close()


def test_a_taken_metrics_port_fails_the_start_in_one_line(tmp_path, daemon_helpers):
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        topo = with_metrics(daemon_helpers.topology(tmp_path), f"[metrics]\nport = {port}\n")
        p = subprocess.run([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                            str(topo), "--run", "x"], capture_output=True, text=True,
                           timeout=120)
    assert p.returncode == 2, p.stderr
    assert f"metrics: cannot listen on 127.0.0.1:{port} ([metrics] port)" in p.stderr
    assert "Traceback" not in p.stderr


def _notify_socket(tmp_path):
    path = tmp_path / "notify.sock"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(str(path))
    sock.settimeout(0.2)
    return sock, path


def _drain(sock) -> list[str]:
    got = []
    while True:
        try:
            got.extend(sock.recv(4096).decode().split("\n"))
        except TimeoutError:
            return got


def test_a_daemon_under_a_fake_systemd_notifies_and_serves_metrics(tmp_path, daemon_helpers):
    """`tcspc daemon` in a subprocess with $NOTIFY_SOCKET (a datagram socket of the test's)
    and a 1 s watchdog: READY=1 once the stages report, WATCHDOG=1 about twice a second
    while it supervises, STATUS= lines, STOPPING=1 at the end; meanwhile its metrics
    (scraped with the token) show words coming in, and the scrape without it gets 401."""
    sock, path = _notify_socket(tmp_path)
    topo = with_metrics(daemon_helpers.topology(tmp_path, cycles=400_000, rate=1e6))
    env = {**os.environ, "NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "1000000"}
    p = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                          str(topo), "--run", "n", "--log-json"], env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    msgs, words = [], []
    try:
        deadline = time.time() + 120
        url_file = tmp_path / "state" / "metrics.url"
        while time.time() < deadline and p.poll() is None:
            msgs += _drain(sock)
            if url_file.exists() and "READY=1" in msgs:
                url = url_file.read_text().strip()
                token = (tmp_path / "state" / "metrics.token").read_text().strip()
                with pytest.raises(urllib.error.HTTPError) as e:
                    scrape(url)
                assert e.value.code == 401
                m = scrape(url, token)
                words.append(m.get("tcspc_words_in_total", {}).get((), 0))
                if len({w for w in words if w > 0}) >= 2:
                    break
                time.sleep(0.3)
        flowing = [w for w in words if w > 0]  # (words journaled: growing while it runs)
        assert len(set(flowing)) >= 2 and flowing == sorted(flowing), (words, msgs)
        p.send_signal(signal.SIGTERM)
        out, err = p.communicate(timeout=60)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    msgs += _drain(sock)
    sock.close()
    assert p.returncode == 128 + signal.SIGTERM, err
    assert msgs.count("READY=1") == 1
    assert msgs.count("WATCHDOG=1") >= 2
    assert any(x.startswith("STATUS=running: ") and "words journaled" in x for x in msgs)
    assert "STOPPING=1" in msgs
    # --log-json: every line of the daemon's log is one JSON object
    lines = [json.loads(x) for x in err.splitlines() if x.strip()]
    assert lines and all(set(x) == {"ts", "level", "stage", "msg"} for x in lines)
    assert any(x["msg"].startswith("metrics on http://127.0.0.1:") for x in lines)
    assert any(x["level"] == "INFO" and x["stage"] == "daemon" for x in lines)


def test_the_notifier_speaks_sd_notify(tmp_path):
    """One datagram of KEY=VALUE lines; the watchdog every WATCHDOG_USEC / 2 on its clock;
    an abstract socket name (@...) too; nothing at all without $NOTIFY_SOCKET."""
    sock, path = _notify_socket(tmp_path)
    t = [0.0]
    n = Notifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "4000000"}, clock=lambda: t[0])
    assert n.every == 2.0
    n.ready("up")
    n.watchdog()
    t[0] = 1.9
    n.watchdog()  # not due
    t[0] = 2.0
    n.watchdog()
    n.status("a\nb")
    n.status("a b")  # unchanged: not sent again
    n.stopping()
    assert _drain(sock) == ["READY=1", "STATUS=up", "WATCHDOG=1", "WATCHDOG=1", "STATUS=a b",
                            "STOPPING=1"]
    sock.close()
    name = f"tcspc-test-{os.getpid()}"
    abstract = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    abstract.bind("\0" + name)
    abstract.settimeout(0.5)
    Notifier({"NOTIFY_SOCKET": "@" + name}).ready()
    assert abstract.recv(100) == b"READY=1"
    abstract.close()
    quiet = Notifier({})
    assert not quiet.active and not quiet.send("READY=1") and quiet.every is None
    # another process's watchdog (WATCHDOG_PID): not ours to pet
    assert Notifier({"NOTIFY_SOCKET": str(path), "WATCHDOG_USEC": "1000",
                     "WATCHDOG_PID": "1"}).every is None


def test_the_unit_is_shipped_printed_and_verified(tmp_path, daemon_helpers):
    """docs/systemd/tcspc-daemon.service is the unit the code makes; `tcspc daemon --unit`
    prints one for a topology (Type=notify, a watchdog, its state and output writable);
    `systemd-analyze verify` accepts it where systemd-analyze exists."""
    import shutil
    from pathlib import Path

    from pipeline.stream.systemd import daemon_unit, doc_unit

    shipped = Path(__file__).parents[3] / "docs" / "systemd" / "tcspc-daemon.service"
    assert shipped.read_text() == doc_unit()
    topo = daemon_helpers.topology(tmp_path)
    p = subprocess.run([sys.executable, "-m", "pipeline.cli", "daemon", "--config", str(topo),
                        "--run", "r1", "--unit"], capture_output=True, text=True, timeout=60)
    assert p.returncode == 0, p.stderr
    unit = p.stdout
    assert unit == daemon_unit(str(topo), "r1")
    for line in ("Type=notify", "NotifyAccess=main", "WatchdogSec=30", "KillMode=mixed",
                 f"ReadWritePaths={tmp_path.resolve() / 'out'} {tmp_path.resolve() / 'state'}"):
        assert line in unit.splitlines(), line
    assert f"daemon --config {topo.resolve()} --run r1" in unit
    if shutil.which("systemd-analyze") is None:
        pytest.skip("no systemd-analyze here")
    path = tmp_path / "tcspc-daemon.service"
    # (verify checks that ExecStart's program exists: the venv's tcspc, or this python)
    exe = Path(sys.executable).with_name("tcspc")
    path.write_text(daemon_unit(str(topo), "r1", exe=str(exe if exe.exists()
                                                           else sys.executable))
                    .replace("User=tcspc\nGroup=tcspc\n", ""))
    v = subprocess.run(["systemd-analyze", "verify", str(path)], capture_output=True,
                       text=True, timeout=60)
    problems = [x for x in (v.stdout + v.stderr).splitlines()
                if "tcspc-daemon.service" in x]
    assert v.returncode == 0 and not problems, v.stdout + v.stderr


def test_restarts_and_rejections_are_run_totals_across_a_daemon_restart(tmp_path,
                                                                        daemon_helpers):
    """Two forged messages rejected by a worker, then the worker SIGKILLed (its counts die
    with it) and restarted, then the daemon stopped (SIGTERM) and started again on the same
    run: the resumed run's result, accounting and metrics still hold the rejections and the
    restart (on main before issue 38 both were back at 0), and STATE/counters/RUN.json
    holds them in between."""
    import pyarrow as pa
    import zmq

    from pipeline.stream import wire
    from schemas import RAW_WORDS

    N = daemon_helpers.N

    def forge_kill_stop(sup):
        deadline = time.time() + 90

        def wait(cond):
            while not cond():
                assert time.time() < deadline
                time.sleep(0.05)

        wait(lambda: sup.metrics.get("source", {}).get("words", 0) > 3e5)
        ctx = zmq.Context()
        tx = ctx.socket(zmq.PUSH)
        tx.connect(sup.topo.endpoint(sup.topo.histogram, "histogram-0", 0))
        words = pa.record_batch([pa.array(np.full(N // 2 * 100, 0x202, np.uint32))],
                                schema=RAW_WORDS.schema)
        head = {"kind": "data", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
                "run": "t", "seq": 1, "step": "source", "first_word": 0, "n_tdc": N // 2,
                "t_laser_win_ns": 140.0}
        for _ in range(2):
            tx.send_multipart(wire.encode(head, words))  # no token: bad_token
        tx.close(linger=30_000)
        ctx.term()
        worker = sup.by_name["histogram-0"]
        wait(lambda: (sup.metrics.get("histogram-0", {}).get("rejected") or {}).get(
            "bad_token") == 2)
        old = worker.popen.pid
        os.kill(old, signal.SIGKILL)
        wait(lambda: worker.restarts == 1 and sup.metrics.get("histogram-0", {}).get(
            "pid") not in (None, old))
        sup.interrupt(signal.SIGTERM)

    topo = daemon_helpers.topology(tmp_path, cycles=1_000_000, rate=2e6)
    with_metrics(topo)
    first, sup1 = daemon_helpers.run_daemon(topo, "t", forge_kill_stop)
    sup1.ops.exporter.close()
    assert first["state"] == "interrupted", first
    want_rej = {"histogram-0": {"bad_token": 2}}
    assert first["totals"]["restarts"] == {"histogram-0": 1}
    assert first["totals"]["rejected"] == want_rej
    saved = json.loads((tmp_path / "state" / "counters" / "t.json").read_text())
    assert saved["restarts"] == {"histogram-0": 1} and saved["rejected"] == want_rej

    second, sup2 = daemon_helpers.run_daemon(topo, "t")
    try:
        assert second["state"] == "finished", second
        tot = second["totals"]
        assert tot["restarts"] == {"histogram-0": 1} and tot["rejected"] == want_rej
        assert tot["daemon_starts"] == 2
        assert second["accounting"]["rejected_messages"] == want_rej
        token = (tmp_path / "state" / "metrics.token").read_text().strip()
        m = scrape(sup2.ops.exporter.url, token)
        assert m["tcspc_stage_restarts_total"][(("stage", "histogram-0"),)] == 1
        assert m["tcspc_rejected_total"][(("reason", "bad_token"),
                                          ("stage", "histogram-0"))] == 2
        assert m["tcspc_daemon_starts_total"][()] == 2
        assert m["tcspc_words_in_total"][()] == second["accounting"]["words_in"]
        # `tcspc status` shows the run's restarts and rejections, not this daemon's (0)
        st = subprocess.run([sys.executable, "-m", "pipeline.cli", "status", "--state",
                             str(tmp_path / "state")], capture_output=True, text=True,
                            timeout=60)
        row = [x.split("│") for x in st.stdout.splitlines() if "histogram-0" in x][0]
        assert row[4].strip() == "1" and "'bad_token': 2" in row[10], st.stdout
    finally:
        sup2.ops.exporter.close()


def test_run_totals_fold_a_stage_restart_and_reload(tmp_path):
    """RunTotals alone: a new pid folds the old process's last counts in; the file is
    taken up by the next daemon of the run (a new run starts at 0)."""
    from types import SimpleNamespace

    from pipeline.stream.exporter import RunTotals

    t = RunTotals(tmp_path, "r")
    t.observe({"stage": "sink", "pid": 1, "rejected": {"bad_token": 1}})
    t.observe({"stage": "sink", "pid": 1, "rejected": {"bad_token": 3},
               "quarantine_dropped": 2})
    t.observe({"stage": "sink", "pid": 2, "rejected": {"bad_header": 1}})
    procs = [SimpleNamespace(name="sink", restarts=1, frozen=0)]
    assert t.totals(procs)["rejected"] == {"sink": {"bad_token": 3, "bad_header": 1}}
    t.save(procs)
    again = RunTotals(tmp_path, "r")
    tot = again.totals([SimpleNamespace(name="sink", restarts=2, frozen=1)])
    assert tot == {"daemon_starts": 2, "restarts": {"sink": 3}, "frozen": {"sink": 1},
                   "rejected": {"sink": {"bad_token": 3, "bad_header": 1}},
                   "quarantine_dropped": {"sink": 2}}
    assert RunTotals(tmp_path, "other").totals()["daemon_starts"] == 1


def test_a_udp_runs_datagrams_and_rejections_in_the_metrics_equal_its_accounting(tmp_path):
    """A UDP run with a datagram lost and 24 bad ones (bad magic, truncated, garbage): the
    metrics' words in, datagrams accepted and lost, and rejections by reason are the
    accounting's numbers."""
    from pipeline.stream import datagram
    from pipeline.stream.daemon import Supervisor
    from pipeline.stream.topology import load_topology
    from stages.testpattern import pattern_words

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (tmp_path / "udp.toml").write_text(f"""
[daemon]
state = "{tmp_path / 'state'}"
[source]
kind = "udp"
bind = "127.0.0.1:{port}"
n_tdc = 128
idle = 20
[histogram]
workers = 2
measurement_cycles = 256
artifacts = "count-as-hits"
[sink]
out = "{tmp_path / 'out'}"
[metrics]
port = 0
""")
    sup = Supervisor(load_topology(tmp_path / "udp.toml", "u"), log=lambda m: None)
    result = {}
    import threading

    t = threading.Thread(target=lambda: result.update(sup.run()))
    t.start()
    try:
        deadline = time.time() + 60
        while "source" not in sup.metrics and time.time() < deadline:
            time.sleep(0.1)  # the ingest is listening once it beats
        words, _ = pattern_words(40 * 32, 128, hit_prob=0.1, rng=2)
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        rng = np.random.default_rng(0)
        for i in range(40):
            chunk = words[i * 32 * 128:(i + 1) * 32 * 128]
            if i != 7:  # (7: lost on the way)
                out.sendto(datagram.encode(chunk, i, i * 32, 128, 140_000, last=(i == 39)),
                           ("127.0.0.1", port))
            if i % 5 == 0:
                junk = datagram.encode(chunk, 99, 0, 128, 140_000)
                for bad in (b"NOPE" + junk[4:], junk[:100], rng.bytes(64)):
                    out.sendto(bad, ("127.0.0.1", port))
            time.sleep(0.003)
        out.close()
        t.join(timeout=240)
        assert not t.is_alive()
        acc = result["accounting"]
        token = (tmp_path / "state" / "metrics.token").read_text().strip()
        m = scrape(sup.ops.exporter.url, token)
        assert m["tcspc_words_in_total"][()] == acc["words_in"] == 39 * 32 * 128
        assert m["tcspc_datagrams_lost_total"][()] == acc["lost_datagrams"] == 1
        assert m["tcspc_datagrams_accepted_total"][()] == 39
        rejected = {dict(k)["reason"]: v for k, v in m["tcspc_rejected_total"].items()
                    if dict(k)["stage"] == "source"}
        assert rejected == acc["rejected_messages"]["source"]
        assert sum(rejected.values()) == 8 * 3
    finally:
        t.join(timeout=240)
        sup.ops.exporter.close()


def test_a_failing_operators_view_is_logged_once_and_never_stops_the_run(tmp_path,
                                                                        daemon_helpers):
    from types import SimpleNamespace

    from pipeline.stream.opsview import OpsView
    from pipeline.stream.topology import load_topology

    topo = load_topology(daemon_helpers.topology(tmp_path), "f")
    lines = []
    ops = OpsView(topo, lines.append)

    def broken(procs=()):
        raise RuntimeError("boom")

    ops.totals.save = broken
    sup = SimpleNamespace(procs=[], metrics={})
    for _ in range(3):
        ops.update(sup, {"state": "running", "stages": {}})
    assert lines == ["metrics not updated: RuntimeError: boom"]
    ops.close()
