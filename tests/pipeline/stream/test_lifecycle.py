"""A run's life cycle (issue 26 points 1-4 and 7, issue 27 point 5): the journal is the
truth for every stage that restarts, strays do not set the run's reference, a stop and a
restart give the uninterrupted run's datasets, a damaged part is rebuilt, and a run that
does not balance never ends as "finished". Each faulty run is compared with a clean run of
the same input (or with the journal, which the clean run's source writes identically)."""

import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import zmq

from pipeline.stream import datagram, wire
from pipeline.stream.journal import read_range, run_end
from pipeline.stream.udp import consistent, max_cycles
from schemas import RAW_SPARSE, RAW_WORDS
from stages.testpattern import pattern_words


def _load(name):
    # helpers of the sibling test modules, loaded by path (tests/ is not a package)
    import importlib.util

    spec = importlib.util.spec_from_file_location(f"_lc_{name}",
                                                  Path(__file__).with_name(f"{name}.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_d = _load("test_daemon")
_u = _load("test_untrusted")
N = _d.N
N_TDC, CYC, GATE = _u.N_TDC, _u.CYC, _u.GATE_PS


# ------------------------------------------------------------------ the run's reference

def test_consistency_is_the_payload_bound():
    """Two datagrams ds sequence numbers apart are between ds and ds * (payload) cycles
    apart, on the same side; nothing else belongs to one stream."""
    m = max_cycles(16)
    assert m == (65_507 - 32) // 64
    assert consistent(0, 0, 16) and not consistent(0, 4, 16)
    assert consistent(3, 3, 16) and consistent(3, 3 * m, 16) and not consistent(3, 3 * m + 1, 16)
    assert consistent(-2, -8, 16) and not consistent(-2, 8, 16) and not consistent(2, 1, 16)


@pytest.mark.parametrize("stray, reason", [
    (dict(seq=0, first=0, gate=GATE + 1000), "stray"),          # another gate, first
    (dict(seq=2**31, first=0, gate=GATE), "stray"),             # sequence 2^31, first
    (dict(seq=1, first=1_000_000, gate=GATE), "stray"),         # a cycle far ahead, first
])
def test_a_stray_datagram_before_the_stream_changes_nothing(tmp_path, stray, reason):
    """Issue 26.4: one stray datagram before the stream once set the run's reference (every
    real datagram then rejected, or a phantom measurement and lost_datagrams -1). Now a
    quorum of agreeing datagrams sets it: the stray is counted and quarantined, nothing
    else changes."""
    dgs = _u._datagrams(40)
    ref_stats, ref, ref_j = _u._ingest(tmp_path, "clean", dgs, reorder_window=8)
    w = np.zeros(CYC * N_TDC, np.uint32)
    bad = datagram.encode(w, stray["seq"], stray["first"], N_TDC, stray["gate"])
    s, got, journaled = _u._ingest(tmp_path, "stray", [bad, *dgs], reorder_window=8)
    assert dict(s.rejected) == {reason: 1}
    assert s.lost_datagrams == ref_stats.lost_datagrams == 0
    assert s.accepted == ref_stats.accepted == 40 and s.gap_cycles == 0
    assert sorted(got) == sorted(ref) and sorted(journaled) == sorted(ref_j)
    assert all(np.array_equal(got[c], ref[c]) for c in ref)
    assert run_end(tmp_path / "stray", "stray") == run_end(tmp_path / "clean", "clean")
    q = list((tmp_path / "q-stray").glob("*.json"))
    assert [json.loads(p.read_text())["reason"].split(":")[0] for p in q] != []


def test_a_stray_inside_the_stream_and_a_configured_reference(tmp_path):
    """After the reference is set, a datagram whose sequence number and cycle cannot follow
    the stream's (a cycle 1,000,000 ahead: within max_jump_cycles) is refused, not a
    phantom measurement; with the reference configured (gate, first sequence number) a
    stray before the stream is refused at once."""
    dgs = _u._datagrams(40)
    _, ref, _ = _u._ingest(tmp_path, "clean", dgs, reorder_window=8)
    w = np.zeros(CYC * N_TDC, np.uint32)
    ahead = datagram.encode(w, 21, 1_000_000, N_TDC, GATE)
    s, got, _ = _u._ingest(tmp_path, "ahead", [*dgs[:20], ahead, *dgs[20:]],
                           reorder_window=8)
    assert dict(s.rejected) == {"inconsistent": 1} and s.lost_datagrams == 0
    assert sorted(got) == sorted(ref)
    strays = [datagram.encode(w, 0, 0, N_TDC, GATE + 1000),
              datagram.encode(w, 2**31, 0, N_TDC, GATE)]
    s, got, _ = _u._ingest(tmp_path, "cfg", [*strays, *dgs], reorder_window=8,
                           n_tdc=N_TDC, gate_ps=GATE, first_seq=0)
    assert dict(s.rejected) == {"bad_gate": 1, "seq_out_of_window": 1}
    assert sorted(got) == sorted(ref) and s.lost_datagrams == 0


# ------------------------------------------------------------------ a restarted ingest

def _ingest_proc(tmp_path, port, ep, max_jump):
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).parents[3])}
    return subprocess.Popen(
        [sys.executable, "-m", "pipeline.cli", "stage", "ingest-udp", "--bind",
         f"127.0.0.1:{port}", "--push", ep, "--run", "r", "--journal", str(tmp_path / "j"),
         "--n-tdc", str(N_TDC), "--max-jump-cycles", str(max_jump), "--reorder-window", "8"],
        env=env, stderr=subprocess.PIPE, text=True)


def test_a_restarted_udp_ingest_takes_the_run_up_from_the_journal(tmp_path):
    """Issue 26.1: the UDP ingest SIGKILLed mid-run, the FPGA's stream going on while it is
    down (further than max_jump_cycles), then restarted: it resumes from the journal's
    sequence numbers, cycles and gate, counts the datagrams sent while it was down as lost
    (exactly), journals the rest and closes the run; the journal equals the stream but for
    the datagrams it missed."""
    n, down = 60, range(20, 30)
    words, _ = pattern_words(n * CYC, N_TDC, hit_prob=0.2, rng=8)
    dgs = [datagram.encode(words[i * CYC * N_TDC:(i + 1) * CYC * N_TDC], i, i * CYC, N_TDC,
                           GATE, last=(i == n - 1)) for i in range(n)]
    ctx = zmq.Context()
    ep = f"ipc://{tmp_path}/in.sock"
    rx = ctx.socket(zmq.PULL)
    rx.bind(ep)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send(items):
        for i in items:
            out.sendto(dgs[i], ("127.0.0.1", port))
            time.sleep(0.002)

    def until_journaled(k):  # the ingest has journaled k datagrams' words (in batches)
        deadline = time.time() + 60
        while sum(w.size for _, w in read_range(tmp_path / "j", "r", 0, 10**12)) \
                < k * CYC * N_TDC:
            assert time.time() < deadline, "the ingest journaled nothing"
            time.sleep(0.05)

    stops = []

    def drain():
        while rx.poll(30_000):
            head, _ = wire.decode(rx.recv_multipart(), {RAW_WORDS.name: RAW_WORDS,
                                                        RAW_SPARSE.name: RAW_SPARSE})
            if head["kind"] == "stop":
                stops.append(head)
                return

    def until_listening():  # the ingest holds the port
        deadline = time.time() + 60
        while True:
            with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
                try:
                    probe.bind(("127.0.0.1", port))
                except OSError:
                    return
            assert time.time() < deadline, "the ingest never listened"
            time.sleep(0.1)

    p = _ingest_proc(tmp_path, port, ep, max_jump=3 * CYC)
    try:
        until_listening()
        send(range(20))
        until_journaled(20)
        time.sleep(0.8)  # the reorder window's linger: nothing held back
        p.kill()
        p.wait()
        send(down)  # the stream goes on while the ingest is down
        p = _ingest_proc(tmp_path, port, ep, max_jump=3 * CYC)
        t = threading.Thread(target=drain)
        t.start()
        until_listening()
        send(range(30, n))
        t.join(timeout=60)
        rx.close(linger=0)  # a worker hangs up on its stop: the ingest then ends
        assert p.wait(timeout=60) == 0, p.stderr.read()
    finally:
        if p.poll() is None:
            p.kill()
        out.close()
        rx.close(linger=0)
        ctx.term()
    journaled = {}
    for first, w in read_range(tmp_path / "j", "r", 0, 10**12):
        for k in range(0, w.size, N_TDC):
            journaled[first // N_TDC + k // N_TDC] = w[k:k + N_TDC]
    # the datagrams sent before the restarted ingest listened are lost too: count them
    got = sorted({c // CYC for c in journaled})
    missed = sorted(set(range(n)) - set(got))
    assert set(down) <= set(missed) and got[-1] == n - 1 and len(got) >= 40
    for c, w in journaled.items():
        assert np.array_equal(w, words[c * N_TDC:(c + 1) * N_TDC])
    assert run_end(tmp_path / "j", "r") == n * CYC * N_TDC  # the run is closed
    stop = stops[-1]
    assert stop["lost_datagrams"] == len(missed)  # exactly the missed ones
    assert stop["gap_cycles"] == len(missed) * CYC
    assert stop["rejected"] == {}


def test_an_earlier_stops_end_line_is_not_the_runs_end(tmp_path):
    """Issue 26.2: after a graceful stop the index ends with `{end}`; a daemon resuming the
    run marks it reopened before any stage starts (and so does a writer), so a restarted
    worker sees no end until the resumed source closes the run again."""
    from pipeline.stream.journal import JournalWriter, journaled_total, reopen

    w = JournalWriter(tmp_path, "r", 4, 140.0)
    w.append(0, np.arange(400, dtype=np.uint32))
    w.close()
    assert run_end(tmp_path, "r") == 400
    assert reopen(tmp_path, "r") and run_end(tmp_path, "r") is None
    assert not reopen(tmp_path, "r")  # once
    w = JournalWriter(tmp_path, "r", 4, 140.0)  # the resumed source
    assert run_end(tmp_path, "r") is None
    w.append(400, np.arange(400, dtype=np.uint32))
    assert run_end(tmp_path, "r") is None  # an end line followed by chunks is not the end
    w.close()
    assert run_end(tmp_path, "r") == 800 and journaled_total(tmp_path, "r") == 800
    got = np.concatenate([x for _, x in read_range(tmp_path, "r", 0, 10**9)])
    assert np.array_equal(got, np.tile(np.arange(400, dtype=np.uint32), 2))


# ------------------------------------------------------------------ the daemon's verdict

def test_a_run_that_does_not_balance_is_never_finished():
    from pipeline.stream.daemon import exit_code, problems, run_state

    ok = {"reconciled": {"checked": True}, "accounting": {
        "balanced": True, "words_in": 10, "classified": 10, "withheld": 0}}
    assert problems(ok) == [] and run_state({**ok, "problems": []}) == "finished"
    short = {"reconciled": {"checked": True}, "accounting": {
        "balanced": False, "words_in": 4_800_000, "classified": 4_000_000, "withheld": 0,
        "words_in_gaps": 0}}
    p = problems(short)
    assert p == ["unbalanced: words journaled 4,800,000 != classified 4,000,000 + withheld 0 "
                 "(difference +800,000: journaled words in no part: a measurement missing)"]
    res = {**short, "problems": p}
    assert run_state(res) == "incomplete" and exit_code(res) == 3
    skipped = {"reconciled": {"checked": False, "why": "the journal has no end"}}
    assert problems(skipped) == ["reconciliation skipped: the journal has no end"]
    lost = {**ok, "accounting": {**ok["accounting"], "lost_datagrams": 149,
                                 "words_in_gaps": 9_536}}
    assert "149 datagrams" in problems(lost)[0]
    assert exit_code({"interrupted": "SIGINT", "problems": []}) == 130
    assert exit_code({"interrupted": "SIGTERM", "problems": []}) == 143
    assert exit_code({"failed": "x", "problems": []}) == 1

    from pipeline.view.status import daemon_state

    now = time.time()
    st = daemon_state({"run": "r", "state": "incomplete", "updated": now, "problems": p},
                      now)
    assert st.kind == "incomplete" and "4,800,000" in st.text
    st = daemon_state({"run": "r", "state": "interrupted", "updated": now,
                       "result": {"interrupted": "SIGINT"}}, now)
    assert st.kind == "interrupted" and "--run" in st.text


def test_a_damaged_or_short_part_is_rebuilt_from_the_journal(tmp_path):
    """Issue 26.7 and 26.2: reconciliation compares every part with the journal (cycles,
    words), not only missing ones: a part cut short on disk ("parquet: File out of
    specification") and one that holds a measurement's first 7,000 of 10,000 cycles are
    rebuilt and named; the good ones are left alone; the datasets then equal histograms
    computed straight from the journal."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from pipeline.stream.journal import JournalWriter
    from pipeline.stream.reconcile import reconcile
    from pipeline.stream.topology import load_topology

    cycles = 40_000
    topo = load_topology(_d.topology(tmp_path, cycles=cycles), "p")
    words, _ = pattern_words(cycles, N, hit_prob=0.2, rng=6)
    jw = JournalWriter(topo.state / "journal", "p", N, 140.0)
    for i in range(0, words.size, 1 << 16):  # as a source journals: chunk after chunk
        jw.append(i, words[i:i + (1 << 16)])
    jw.close()
    first = reconcile(topo)  # no dataset yet: every part is computed from the journal
    assert len(first["recomputed"]) == 8 and first["rebuilt"] == []
    parts = sorted((tmp_path / "out").glob("histograms/date=*/run=p/*.parquet"))
    damaged, short = parts[1], parts[4]  # (measurement 0, TDCs 8-15), (2, TDCs 0-7)
    damaged.write_bytes(damaged.read_bytes()[:200])
    t = pq.read_table(short)  # its first 7,000 cycles only: 3,000 no-hit words fewer
    t = t.set_column(t.schema.get_field_index("cycles"), "cycles",
                     pa.array(np.full(t.num_rows, 7_000, np.uint64)))
    t = t.set_column(t.schema.get_field_index("n_no_hit"), "n_no_hit", pa.array(
        t.column("n_no_hit").to_numpy() - np.uint64(3_000)))
    pq.write_table(t, short)
    rec = reconcile(topo)
    named = {r["file"]: r["why"] for r in rec["rebuilt"]}
    assert str(damaged) in named and "unreadable" in named[str(damaged)]
    assert str(short) in named and "7000..7000 cycles" in named[str(short)]
    assert "journal holds 10,000 cycles" in named[str(short)]
    assert len(rec["rebuilt"]) == 2 and len(rec["recomputed"]) == 2  # the rest left alone
    _d.check_histograms(tmp_path, "p", cycles)


# ------------------------------------------------------------------ stop, then resume

def _daemon_proc(topo, run):
    return subprocess.Popen([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                             str(topo), "--run", run], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)


def _wait_words(status: Path, words: float):
    deadline = time.time() + 120
    while time.time() < deadline:
        try:
            if json.loads(status.read_text())["stages"]["source"].get("words", 0) > words:
                return
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.1)
    raise AssertionError("words never flowed")


@pytest.mark.slow  # (two daemons, ~50 s on the shared 2-core machine)
def test_ctrl_c_then_a_restart_gives_the_uninterrupted_runs_datasets(tmp_path):
    """Issue 27.5 and 26.2: Ctrl-C (SIGINT) to `tcspc daemon` says "interrupted", exits 130
    and leaves the run resumable; started again on the same run it completes it, and every
    measurement, the one in progress at the stop included (written partial, then replaced),
    equals the uninterrupted run's. The restarted workers do not take the first stop's end
    line for the run's end."""
    cycles = 400_000
    topo = _d.topology(tmp_path, cycles=cycles, rate=1.5e6)
    p = _daemon_proc(topo, "c")
    _wait_words(tmp_path / "state" / "status.json", 0.7e6)
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 130, err
    assert "interrupted (SIGINT)" in err and "finished:" not in err
    first = json.loads(out)
    assert first["state"] == "interrupted" and first["accounting"]["balanced"]
    stopped_at = first["accounting"]["words_in"]
    assert 0.7e6 < stopped_at < cycles * N
    st = json.loads((tmp_path / "state" / "status.json").read_text())
    assert st["state"] == "interrupted"
    p = _daemon_proc(topo, "c")
    out, err = p.communicate(timeout=240)
    assert p.returncode == 0, err
    res = json.loads(out)
    assert res["state"] == "finished" and res["accounting"]["words_in"] == cycles * N
    assert res["reconciled"]["rebuilt"] == []  # the workers resumed the partial measurement
    _d.check_histograms(tmp_path, "c", cycles)
    import pyarrow.parquet as pq

    for part in (tmp_path / "out").glob("histograms/date=*/run=c/*.parquet"):
        meta = json.loads(pq.read_schema(part).metadata[b"tcspc.measurement"])
        assert meta["partial"] is False and meta["cycles"][1] - meta["cycles"][0] == 10_000


@pytest.mark.slow  # (the ingest waits a minute for the stopped worker)
def test_a_worker_stopped_across_the_end_gets_its_words_from_the_journal(tmp_path):
    """Issue 26.3: a histogram worker SIGSTOPped across the end of a UDP stream (the ingest
    gives up delivering its stop after 60 s, the supervisor SIGTERMs it): continued, it
    fetches its missing words from the journal before the run is done; the datasets equal
    histograms computed straight from the journal and the run finishes balanced."""
    n, cyc = 400, 64
    words, _ = pattern_words(n * cyc, N, hit_prob=0.2, rng=9)
    dgs = [datagram.encode(words[i * cyc * N:(i + 1) * cyc * N], i, i * cyc, N, GATE,
                           last=(i == n - 1)) for i in range(n)]
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (tmp_path / "udp.toml").write_text(f"""
[daemon]
state = "{tmp_path / 'state'}"
[source]
kind = "udp"
bind = "127.0.0.1:{port}"
n_tdc = {N}
[histogram]
workers = 2
measurement_cycles = 10000
artifacts = "count-as-hits"
[sink]
out = "{tmp_path / 'out'}"
""")

    def during(sup):
        deadline = time.time() + 60
        while "source" not in sup.metrics:
            assert time.time() < deadline
            time.sleep(0.1)
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        w = sup.by_name["histogram-1"]
        stopped = None
        for i, data in enumerate(dgs):
            if i == 100:
                stopped = w.popen.pid
                os.kill(stopped, signal.SIGSTOP)
            out.sendto(data, ("127.0.0.1", port))
            time.sleep(0.003)
        out.close()
        # the supervisor ends the stopped worker: SIGTERM after the end's grace, or (since
        # issue 38.4) SIGKILL past its heartbeat deadline and a restart
        deadline = time.time() + 240
        while not (sup.by_name["source"].finished and (w.terminated or w.frozen)):
            assert time.time() < deadline, "the supervisor never ended the stopped worker"
            time.sleep(0.2)
        with contextlib.suppress(ProcessLookupError):
            os.kill(stopped, signal.SIGCONT)

    res, sup = _d.run_daemon(tmp_path / "udp.toml", "s", during)
    assert res["state"] == "finished", res["problems"]
    assert res["accounting"]["balanced"] and res["accounting"]["words_in"] == words.size
    assert res["reconciled"]["rebuilt"] == [] and res["reconciled"]["recomputed"] == []
    _d.check_histograms(tmp_path, "s", n * cyc)


def test_a_stop_before_the_supervisor_is_kept_where_sigint_was_ignored(tmp_path, monkeypatch):
    """A daemon started with SIGINT ignored (a background job of a non-interactive shell:
    Python then installs no handler of its own), the signal coming while its stages'
    server starts (here sent by the server's start itself): it was lost, and the run
    went on to "finished", exit 0. Now the daemon's first step keeps it: exit 130 before
    any stage starts. (Found looking for why a clean clone's suite once saw a run go on
    after a SIGINT at 0.5 s; that one is not reproduced: 28 tries under load.)"""
    from pipeline.cli.stream import daemon
    from pipeline.stream import forkstart

    topo = _d.topology(tmp_path, cycles=400_000, rate=1.5e6)
    monkeypatch.setattr(forkstart, "warm_for", lambda config: os.kill(os.getpid(),
                                                                       signal.SIGINT))
    old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        with pytest.raises(SystemExit) as got:
            daemon.main(["--config", str(topo), "--run", "e"], standalone_mode=False)
    finally:
        for s, h in old.items():
            signal.signal(s, h)
    assert got.value.code == 130
    assert not (tmp_path / "state" / "runs" / "e.json").exists()


@pytest.mark.parametrize("at", [0.5, 1.5, "mid-run"])
def test_ctrl_c_at_any_moment_stops_the_daemon_within_seconds(tmp_path, at):
    """Issue 38.9: SIGINT in the first seconds took 62-65 s (the heartbeats were no longer
    collected after the signal, so the workers never heard from were waited on for their
    60 s start-up) and printed "source: finished". Now it exits within 3 s (asserted <= 6 s
    on the loaded machine), exit 130, and nothing says "finished"."""
    topo = _d.topology(tmp_path, cycles=400_000, rate=1.5e6)
    p = _daemon_proc(topo, "i")
    if at == "mid-run":
        _wait_words(tmp_path / "state" / "status.json", 0.7e6)
    else:
        time.sleep(at)
    t0 = time.monotonic()
    p.send_signal(signal.SIGINT)
    out, err = p.communicate(timeout=120)
    took = time.monotonic() - t0
    assert took <= 6.0, (took, err)
    # 130, as a shell shows it: exit(130), or (a signal before Python's own handler took
    # over, at 0.5 s) death by SIGINT, which the shell reports as 128 + 2 = 130 too
    assert p.returncode in (130, -signal.SIGINT), err
    assert "finished" not in err, err
