"""A resume that does not fit the run, a finished run started again (issue 38.5, 38.6)."""

import subprocess
import sys

from tests.pipeline.stream.test_daemon import run_daemon, topology


def _daemon(topo_path, run):
    return subprocess.run([sys.executable, "-m", "pipeline.cli.app", "daemon", "--config",
                           str(topo_path), "--run", run], capture_output=True, text=True,
                          timeout=300)


def test_a_resume_that_changes_a_measurement_is_refused_and_a_finished_run_stands(tmp_path):
    topo = topology(tmp_path, cycles=20_000)
    result, _ = run_daemon(topo, "r1")
    assert result["state"] == "finished"
    # started again: recognised as finished, exit 0, the accounting not rewritten
    again = _daemon(topo, "r1")
    assert again.returncode == 0, again.stderr
    assert "already finished" in again.stderr
    # the same run with another measurement_cycles: refused in one line, exit 2
    topo.write_text(topo.read_text().replace("measurement_cycles = 10000",
                                             "measurement_cycles = 20000"))
    bad = _daemon(topo, "r1")
    assert bad.returncode == 2, bad.stderr
    assert "histogram.measurement_cycles changed 10000 -> 20000" in bad.stderr
    assert "Traceback" not in bad.stderr


def test_a_resume_on_another_date_keeps_the_run_partition(tmp_path):
    from pipeline.stream.runrecord import take
    from pipeline.stream.topology import load_topology

    topo = load_topology(topology(tmp_path), "r2")
    take(topo)
    later = load_topology(topology(tmp_path), "r2")
    later.date = "2099-01-01"  # the next local date
    take(later)
    assert later.date == topo.date


def test_unbalanced_says_why():
    from pipeline.stream.daemon import problems

    rec = {"checked": True}
    extra = problems({"reconciled": rec, "accounting": {
        "balanced": False, "words_in": 100, "classified": 132, "withheld": 0}})
    assert "difference -32: the parts hold more words than the journal" in extra[0]
    missing = problems({"reconciled": rec, "accounting": {
        "balanced": False, "words_in": 100, "classified": 36, "withheld": 0}})
    assert "difference +64: journaled words in no part" in missing[0]


def test_a_failed_run_writes_its_accounting(tmp_path):
    import json

    from tests.pipeline.stream.test_daemon import _kill_when_running

    topo = topology(tmp_path, cycles=400_000, rate=2_000_000)
    topo.write_text(topo.read_text().replace("restarts = 3", "restarts = 0"))
    result, _ = run_daemon(topo, "f1", during=lambda s: _kill_when_running(
        s, "histogram-1", 20_000 * 64))
    assert result["failed"] and result["state"] == "failed"
    acc = json.loads((tmp_path / "out" / "accounting" / "run=f1.json").read_text())
    assert acc["words_in"] > 0 and acc["classified"] <= acc["words_in"]


def _reconcile(topo_path, run):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", "reconcile", "--config",
                           str(topo_path), "--run", run], capture_output=True, text=True,
                          timeout=300)


def test_reconcile_finishes_a_run_offline_and_again_changes_nothing(tmp_path):
    """Issue 38.7: `tcspc reconcile RUN` with no daemon running: a measurement missing from
    the datasets (a daemon killed while reconciling, a part deleted) is rebuilt from the
    journal, the run balanced and its accounting written (exit 0); run again, nothing is
    rebuilt and the accounting is the same; a daemon holding the state, or a run with no
    journal, is refused in one line (exit 2)."""
    import json

    from pipeline.stream.state import open_state

    topo = topology(tmp_path, cycles=30_000)
    result, _ = run_daemon(topo, "r1")
    assert result["state"] == "finished"
    want = result["accounting"]
    parts = sorted((tmp_path / "out" / "histograms").rglob("*.parquet"))
    parts[1].unlink()  # one worker's part of a measurement, gone
    first = _reconcile(topo, "r1")
    assert first.returncode == 0, first.stderr
    assert "recomputed from the journal: measurement 0" in first.stderr, first.stderr
    assert "r1 finished" in first.stderr
    got = json.loads(first.stdout)["accounting"]
    assert got["balanced"] and got["words_in"] == want["words_in"]
    assert got["classes"] == want["classes"] and parts[1].exists()
    again = _reconcile(topo, "r1")
    assert again.returncode == 0 and "from the journal" not in again.stderr, again.stderr
    assert json.loads(again.stdout)["accounting"]["classes"] == want["classes"]
    record = json.loads((tmp_path / "state" / "runs" / "r1.json").read_text())
    assert record["state"] == "finished" and record["result"]["reconciled_offline"]
    lock = open_state(tmp_path / "state")  # a daemon running on this state
    try:
        busy = _reconcile(topo, "r1")
    finally:
        lock.release()
    assert busy.returncode == 2 and "in use by daemon" in busy.stderr, busy.stderr
    none = _reconcile(topo, "nope")
    assert none.returncode == 2 and "no journal" in none.stderr, none.stderr
    assert "Traceback" not in busy.stderr + none.stderr
    # a journal without its end (a daemon killed mid-run): incomplete, exit 3, said why
    with open(tmp_path / "state" / "journal" / "r1.index.jsonl", "a") as index:
        index.write('{"reopen": true}\n')
    cut = _reconcile(topo, "r1")
    assert cut.returncode == 3 and "r1 incomplete" in cut.stderr, cut.stderr
    assert "reconciliation skipped" in cut.stderr


def test_a_udp_daemon_killed_after_its_streams_end_finishes_when_started_again(tmp_path):
    """Issue 38.6: the whole daemon SIGKILLed once its UDP stream's end is journaled (during
    the stages' drain or its reconciliation): started again on the run, it does not wait for
    datagrams that will never come (before: for ever, without ``idle``); the journal's end
    says the stream ended, the stages finish from the journal, and the run ends finished,
    balanced, every datagram's words in once."""
    import json
    import os
    import signal
    import socket
    import time

    from pipeline.stream import datagram
    from pipeline.stream.journal import stream_ended
    from stages.testpattern import pattern_words

    n_tdc, n, cyc = 16, 300, 64
    words, _ = pattern_words(n * cyc, n_tdc, hit_prob=0.2, rng=4)
    dgs = [datagram.encode(words[i * cyc * n_tdc:(i + 1) * cyc * n_tdc], i, i * cyc, n_tdc,
                           140_000, last=(i == n - 1)) for i in range(n)]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    topo = tmp_path / "udp.toml"
    topo.write_text(f"""
[daemon]
state = "{tmp_path / 'state'}"
[source]
kind = "udp"
bind = "127.0.0.1:{port}"
n_tdc = {n_tdc}
[histogram]
workers = 2
measurement_cycles = 6400
artifacts = "count-as-hits"
[sink]
out = "{tmp_path / 'out'}"
""")
    cmd = [sys.executable, "-m", "pipeline.cli", "daemon", "--config", str(topo), "--run", "u"]
    d = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    status, journal = tmp_path / "state" / "status.json", tmp_path / "state" / "journal"
    deadline = time.time() + 60
    while time.time() < deadline and not status.exists():
        time.sleep(0.05)
    time.sleep(1.0)  # (the ingest bound)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as out:
        for data in dgs:
            out.sendto(data, ("127.0.0.1", port))
            time.sleep(0.002)
    deadline = time.time() + 60
    while time.time() < deadline and not stream_ended(journal, "u"):
        time.sleep(0.01)
    assert stream_ended(journal, "u")  # the ingest journaled the stream's end
    os.kill(d.pid, signal.SIGKILL)  # the daemon, before it is done with the run
    d.communicate(timeout=30)
    t0 = time.time()
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert again.returncode == 0, again.stderr[-3000:]
    assert time.time() - t0 < 60
    assert "its source's stream had ended" in again.stderr
    res = json.loads(again.stdout)
    acc = res["accounting"]
    assert res["state"] == "finished" and acc["balanced"], res["problems"]
    assert acc["words_in"] == acc["classified"] == words.size
    assert acc["lost_datagrams"] == 0
