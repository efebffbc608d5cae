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
