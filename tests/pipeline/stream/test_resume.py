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
