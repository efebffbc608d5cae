"""Faults the stream must survive (issue 16): a corrupt or truncated journal frame met by
the repair path, a truncated or bit-flipped checkpoint, a stage that keeps dying. Each
run is compared with an uninterrupted run of the same input, and the accounting is
checked exactly."""

import json
import os
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.stream.journal import (
    JournalCorrupt,
    JournalWriter,
    _entries,
    read_range,
    segment_path,
    verify,
)


def _daemon_helpers():
    # test_daemon.py's scene and helpers, loaded by path (tests/ is not a package)
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "_test_daemon_helpers", Path(__file__).with_name("test_daemon.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_h = _daemon_helpers()
N, dataset, run_daemon, topology = _h.N, _h.dataset, _h.run_daemon, _h.topology

CYCLES, MC = 200_000, 10_000


def _histograms(out: Path, run: str) -> pl.DataFrame:
    h = dataset(out, "histograms", run)
    return (h.with_columns(pl.col("measurement").str.extract(r"-m(\d+)$").cast(pl.Int64)
                           .alias("k"))
            .select("k", "tdc", "cycles", "counts", "n_hit", "n_no_hit", "n_artifact",
                    "n_invalid_phase", "n_malformed").sort("k", "tdc"))


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted run every faulty one is compared with."""
    d = tmp_path_factory.mktemp("ref")
    res, _ = run_daemon(topology(d, cycles=CYCLES), "f")
    assert res["failed"] is None and res["restarts"] == {}
    h = _histograms(d / "out", "f")
    assert h.height == CYCLES // MC * N
    return h


def _same(got: pl.DataFrame, ref: pl.DataFrame, without: set[tuple[int, int]] = frozenset()):
    """``got`` equals ``ref`` but for the (measurement, first TDC of 2 ranges) withheld."""
    half = N // 2
    keep = ref.filter(~pl.struct("k", "tdc").map_elements(
        lambda r: (r["k"], 0 if r["tdc"] < half else half) in without, return_dtype=bool))
    assert got.height == keep.height
    assert got.select(pl.exclude("counts")).equals(keep.select(pl.exclude("counts")))
    assert np.array_equal(np.stack(got["counts"].to_numpy()),
                          np.stack(keep["counts"].to_numpy()))


def test_a_truncated_checkpoint_is_discarded_and_rebuilt_from_the_journal(tmp_path,
                                                                         reference):
    ckpt = tmp_path / "state" / "checkpoints" / "c" / "histogram-1.npz"

    def chaos(sup):
        deadline = time.time() + 60
        while time.time() < deadline:
            p = sup.by_name["histogram-1"].popen
            if ckpt.exists() and sup.metrics.get("source", {}).get("words", 0) > 1e6:
                os.kill(p.pid, signal.SIGKILL)
                p.wait()
                data = ckpt.read_bytes()
                ckpt.write_bytes(data[:len(data) // 2])  # a torn write
                return
            time.sleep(0.05)
        raise AssertionError("no checkpoint to corrupt")

    res, sup = run_daemon(topology(tmp_path, cycles=CYCLES, rate=1.5e6), "c", chaos)
    assert res["failed"] is None and res["restarts"] == {"histogram-1": 1}
    assert sup.by_name["histogram-1"].exit_codes == [-signal.SIGKILL, 0]  # one crash only
    _same(_histograms(tmp_path / "out", "c"), reference)
    acc = res["accounting"]
    assert acc["balanced"] and acc["words_in"] == CYCLES * N
    assert acc["checkpoints_discarded"] == {"histogram-1": 1}
    log = (tmp_path / "state" / "logs" / "histogram-1.log").read_text()
    assert "checkpoint discarded, rebuilding from the journal" in log
    assert ckpt.with_suffix(".npz.bad").exists()


def test_a_bit_flipped_checkpoint_is_refused(tmp_path):
    from pipeline.stream.stage import CheckpointError, load_checkpoint, save_checkpoint

    state = {"hits": np.arange(64, dtype=np.uint64).reshape(4, 16),
             "counters": np.array([1, 2, 3], np.int64)}
    save_checkpoint(tmp_path / "c.npz", state)
    data = bytearray((tmp_path / "c.npz").read_bytes())
    for pos in range(0, len(data), 7):  # every 7th byte, one at a time, one bit
        bad = bytearray(data)
        bad[pos] ^= 0x10
        (tmp_path / "bad.npz").write_bytes(bytes(bad))
        try:
            got = load_checkpoint(tmp_path / "bad.npz")
        except CheckpointError:
            continue
        # a flip the file survives (zip padding, a name's case) must give the same arrays
        assert got.keys() == state.keys() and all(np.array_equal(got[k], state[k])
                                                  for k in state), pos


def test_a_corrupt_journal_met_by_the_repair_path_is_reported_never_used(
        tmp_path, reference, monkeypatch):
    """Measurements lost in flight (their dataset files removed, as with a killed sink)
    are recomputed from the journal at the end; one frame there has a flipped bit and the
    last is cut short. Those measurements are withheld and counted, the rest equal the
    uninterrupted run, and the run ends "incomplete" (a counted, named loss: exit 3), never
    left "running" nor "finished"."""
    import pipeline.stream.daemon as daemon

    real = daemon.reconcile
    lost = {(2, 0), (2, 8), (7, 8), (19, 0)}
    seen = {}

    def faulty_reconcile(topo):
        journal = topo.state / "journal"
        out = topo.state.parent / "out"
        for k, a in lost:
            for p in out.glob(f"histograms/date=*/run=g/part-{k:06d}-t{a:03d}.parquet"):
                p.unlink()
        # under load the sink may be stopped before it wrote the last measurement: what
        # reconciliation meets missing is what was removed and what was never written
        seen["missing"] = {(k, a) for k in range(CYCLES // MC) for a in (0, N // 2)
                           if not any(out.glob(f"histograms/date=*/run=g/"
                                               f"part-{k:06d}-t{a:03d}.parquet"))}
        entries = [e for e in _entries(journal / "g.index.jsonl") if not e.get("end")]
        flip = next(e for e in entries if e["first_word"] <= 2 * MC * N + 5 <
                    e["first_word"] + e["words"])
        seg = segment_path(journal, "g", flip["segment"], flip["enc"])
        data = bytearray(seg.read_bytes())
        data[flip["offset"] + flip["bytes"] // 2] ^= 0x04
        seg.write_bytes(bytes(data))
        cut = entries[-1]
        seg = segment_path(journal, "g", cut["segment"], cut["enc"])
        os.truncate(seg, cut["offset"] + cut["bytes"] - 5)
        seen.update(flip=flip, cut=cut)
        return real(topo)

    monkeypatch.setattr(daemon, "reconcile", faulty_reconcile)
    res, _ = run_daemon(topology(tmp_path, cycles=CYCLES), "g")
    bad = [seen["flip"], seen["cut"]]

    def touches(k):
        lo, hi = k * MC * N, (k + 1) * MC * N
        return any(e["first_word"] < hi and lo < e["first_word"] + e["words"] for e in bad)

    missing = seen["missing"]
    assert lost <= missing
    withheld = {(k, a) for k, a in missing if touches(k)}
    assert withheld & lost and (7, 8) not in withheld  # (7, 8) is recomputed from good frames
    rec = res["reconciled"]
    assert sorted(map(tuple, rec["corrupt"])) == sorted(withheld)
    assert sorted(map(tuple, rec["recomputed"])) == sorted(missing - withheld)
    assert rec["corrupt_words"] == sum(e["words"] for e in bad)
    reasons = " ".join(c[2] for c in rec["corrupt_chunks"])
    assert "truncated" in reasons and "does not decode" in reasons
    _same(_histograms(tmp_path / "out", "g"), reference, withheld)
    acc = res["accounting"]
    assert acc["corrupt"] == rec["corrupt_words"]
    assert acc["withheld"] == len(withheld) * MC * (N // 2)
    assert acc["balanced"] and acc["words_in"] == CYCLES * N
    st = json.loads((tmp_path / "state" / "status.json").read_text())
    assert st["state"] == "incomplete" and st["journal_corrupt_words"] == rec["corrupt_words"]
    assert st["problems"] == res["problems"] and len(res["problems"]) == 1
    assert f"{len(withheld)} measurement(s) withheld" in res["problems"][0]


@pytest.mark.parametrize("enc", ["zstd-nohit", "zstd", None])
def test_every_single_bit_flip_in_the_journal_is_detected(tmp_path, enc):
    rng = np.random.default_rng(7)
    w = JournalWriter(tmp_path, "r", 4, 140.0, compression=enc)
    words = rng.integers(0, 2**32, 4000, dtype=np.uint64).astype(np.uint32)
    for i in range(10):
        w.append(i * 400, words[i * 400:(i + 1) * 400])
    w.close()
    seg = segment_path(tmp_path, "r", 0, enc)
    clean = seg.read_bytes()
    entries = [e for e in _entries(tmp_path / "r.index.jsonl") if not e.get("end")]
    for e in rng.choice(entries, 5, replace=False):
        start = e["offset"] * (4 if enc is None else 1)
        size = e.get("bytes", 4 * e["words"])
        data = bytearray(clean)
        data[start + int(rng.integers(size))] ^= 1 << int(rng.integers(8))
        seg.write_bytes(bytes(data))
        v = verify(tmp_path, "r")
        assert [c[0] for c in v["corrupt"]] == [e["first_word"]]
        assert v["corrupt_words"] == 400 and v["unchecked_chunks"] == 0
        with pytest.raises(JournalCorrupt):
            list(read_range(tmp_path, "r", 0, 4000))
        got = list(read_range(tmp_path, "r", 0, 4000, lambda *a: None))
        assert sum(x.size for _, x in got) == 3600
        assert np.array_equal(np.concatenate([x for _, x in got]),
                              np.delete(words, np.s_[e["first_word"]:e["first_word"] + 400]))
    seg.write_bytes(clean)
    assert verify(tmp_path, "r")["corrupt"] == []


def test_a_journal_written_before_checksums_still_reads(tmp_path):
    """Old frames (pyarrow's codec, no content checksum): read as before, reported as
    unchecked; a truncated one is still caught."""
    import pyarrow as pa

    words = np.arange(800, dtype=np.uint32)
    frames = [pa.Codec("zstd").compress(words[i:i + 400].astype(">u4").tobytes())
              for i in (0, 400)]
    seg = segment_path(tmp_path, "old", 0, "zstd")
    seg.write_bytes(b"".join(f.to_pybytes() for f in frames))
    with open(tmp_path / "old.index.jsonl", "w") as fh:
        off = 0
        for i, f in enumerate(frames):
            fh.write(json.dumps({"first_word": 400 * i, "segment": 0, "offset": off,
                                 "words": 400, "bytes": f.size, "enc": "zstd"}) + "\n")
            off += f.size
    got = np.concatenate([w for _, w in read_range(tmp_path, "old", 0, 800)])
    assert np.array_equal(got, words)
    v = verify(tmp_path, "old")
    assert v["unchecked_chunks"] == 2 and v["corrupt"] == []
    os.truncate(seg, off - 3)
    assert verify(tmp_path, "old")["corrupt_words"] == 400


def test_restarts_back_off_exponentially_within_a_budget_rate(tmp_path):
    """A stage that dies at once is restarted after 0.05, 0.1, 0.2 s ... and the run fails
    when it dies more than ``restarts`` times before the budget earns one back; a stage
    that dies less often than the budget refills is restarted every time."""
    from pipeline.stream.daemon import Proc, Supervisor
    from pipeline.stream.topology import load_topology

    topo = load_topology(topology(tmp_path, cycles=1000))
    topo.restarts, topo.restart_refill_s = 3, 10.0
    topo.restart_backoff_s, topo.restart_backoff_max_s = 0.05, 0.15
    sup = Supervisor(topo, log=lambda m: None, poll_s=0.01)
    starts = []
    real_start = sup._start
    sup._start = lambda p: (starts.append(time.monotonic()), real_start(p))
    die = Proc("x", [sys.executable, "-c", "import sys; sys.exit(3)"], [])
    sup.procs, sup.by_name = [die], {"x": die}
    sup._start(die)
    t0 = time.monotonic()
    while not sup._check():
        assert time.monotonic() - t0 < 20
        time.sleep(0.01)
    assert sup.failed and "restart budget spent (3 at once, one more every 10 s" in sup.failed
    gaps = np.diff(starts)
    assert len(starts) == 4 and die.restarts == 3 and die.exit_codes == [3] * 4
    assert np.all(gaps >= [0.05, 0.1, 0.15]) and np.all(gaps < [1.0, 1.0, 1.0])

    # the same budget refilled fast: deaths spread wider than its refill never exhaust it
    topo.restart_refill_s = 0.1
    sup2 = Supervisor(topo, log=lambda m: None, poll_s=0.01)
    slow = Proc("y", [sys.executable, "-c", "import sys, time; time.sleep(0.35); "
                      "sys.exit(3)"], [])
    sup2.procs, sup2.by_name = [slow], {"y": slow}
    sup2._start(slow)
    t0 = time.monotonic()
    while time.monotonic() - t0 < 4 and slow.restarts < 6:
        assert not sup2._check(), sup2.failed
        time.sleep(0.01)
    assert slow.restarts >= 6 and sup2.failed is None
    sup2.kill_all()


def test_a_source_killed_after_it_finished_the_run_is_not_restarted(tmp_path):
    """Issue 38.6: a source that had journaled its stream's end (the end line's
    ``complete``) and was killed while it lingered over what it sent is finished, not
    restarted into a run that has ended (a UDP ingest restarted there waited for datagrams
    for ever); one killed before, or whose end was a signal's stop, is restarted. The
    journal decides, not a last heartbeat the collector may have missed."""
    from pipeline.stream.daemon import Proc, Supervisor
    from pipeline.stream.topology import load_topology

    topo = load_topology(topology(tmp_path, cycles=1000))
    topo.restart_backoff_s = 0.05
    for i, (end, restarted) in enumerate((("complete", False), ("stop", True),
                                          (None, True))):
        topo.run = f"f{i}"
        if end is not None:
            w = JournalWriter(topo.state / "journal", topo.run, N, 140.0)
            w.close(complete=end == "complete")
        logged = []
        sup = Supervisor(topo, log=logged.append, poll_s=0.01)
        src = Proc("source", [sys.executable, "-c", "import time; time.sleep(60)"], [])
        sup.procs, sup.by_name = [src], {"source": src}
        sup._start(src)
        sup.metrics["source"] = {"pid": src.popen.pid, "state": "finished", "t": time.time()}
        os.kill(src.popen.pid, signal.SIGKILL)
        src.popen.wait()
        sup._check()
        assert src.finished is not restarted and (src.restart_at is not None) is restarted
        assert any("after it finished the run" in m for m in logged) is not restarted, logged
        sup.kill_all()


def test_forged_and_poisoned_messages_in_a_running_graph_change_nothing(tmp_path, reference):
    """While the graph runs: a forged stop and a forged word batch without the run's token,
    a header lacking first_word with it, a batch from a step that is not upstream, and a
    forged heartbeat. The datasets equal the uninterrupted run; each is counted."""
    import pyarrow as pa
    import zmq

    from pipeline.stream import wire
    from schemas import RAW_WORDS

    def inject(sup):
        deadline = time.time() + 60
        while sup.metrics.get("source", {}).get("words", 0) < 5e5:
            assert time.time() < deadline
            time.sleep(0.05)
        token = sup.token_file.read_text().strip()
        ctx = zmq.Context()
        tx = ctx.socket(zmq.PUSH)
        tx.connect(sup.topo.endpoint(sup.topo.histogram, "histogram-0", 0))
        words = pa.record_batch([pa.array(np.full(N // 2 * 100, 0x200 | 2, np.uint32))],
                                schema=RAW_WORDS.schema)
        head = {"kind": "data", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
                "run": "h", "seq": 1, "step": "source", "first_word": 0, "n_tdc": N // 2,
                "t_laser_win_ns": 140.0}
        tx.send_multipart(wire.encode({**head, "kind": "stop"}, None))
        tx.send_multipart(wire.encode(head, words))
        tx.send_multipart(wire.encode({k: v for k, v in head.items() if k != "first_word"},
                                      words, token))
        tx.send_multipart(wire.encode({**head, "step": "histogram-1"}, words, token))
        pub = ctx.socket(zmq.PUB)
        pub.connect(sup.topo.metrics)
        time.sleep(0.3)  # (a PUB's subscriber joins late)
        for _ in range(3):
            pub.send(json.dumps({"stage": "histogram-0", "pid": 1, "t": time.time(),
                                 "state": "finished", "received": 10**9}).encode())
            time.sleep(0.1)
        # (a loaded machine's worker can take seconds to drain its queue: the injector
        # must not drop its own messages before they are delivered)
        tx.close(linger=30_000)
        pub.close(linger=1000)
        ctx.term()

    # (a 6 s run: the injected messages must reach the worker before its source ends,
    # on a loaded machine too)
    res, sup = run_daemon(topology(tmp_path, cycles=CYCLES, rate=0.5e6), "h", inject)
    assert res["failed"] is None and res["restarts"] == {}
    _same(_histograms(tmp_path / "out", "h"), reference)
    acc = res["accounting"]
    assert acc["balanced"] and acc["words_in"] == CYCLES * N
    assert acc["rejected_messages"] == {"histogram-0": {"bad_token": 2, "bad_header": 1,
                                                        "unknown_sender": 1}}
    st = json.loads((tmp_path / "state" / "status.json").read_text())
    assert st["forged_heartbeats"] >= 1
    assert st["stages"]["histogram-0"]["received"] < 10**9  # the forged record was dropped


def test_a_graph_under_curve_gives_the_same_datasets(tmp_path, reference):
    """CURVE turned on explicitly (on loopback): every stage socket and the heartbeats
    encrypted and authenticated, the same datasets."""
    topo = topology(tmp_path, cycles=CYCLES)
    topo.write_text(topo.read_text().replace("restarts = 3", "restarts = 3\ncurve = true"))
    res, sup = run_daemon(topo, "cv")
    assert sup.curve_dir is not None and (sup.curve_dir / "server.key_secret").exists()
    assert res["failed"] is None
    _same(_histograms(tmp_path / "out", "cv"), reference)
    assert res["accounting"]["balanced"]
    assert "source" in sup.metrics  # heartbeats came through CURVE too


def test_sigkill_of_the_daemon_leaves_no_orphan_and_a_restart_resumes(tmp_path, reference):
    """SIGKILL the daemon mid-run: its stages die with it (no orphan goes on writing the
    journal); a daemon started again on the same run resumes it, and the datasets equal the
    uninterrupted run's, every word once."""
    import subprocess

    topo = topology(tmp_path, cycles=CYCLES, rate=1e6)  # 3.2 s of words
    cmd = [sys.executable, "-m", "pipeline.cli", "daemon", "--config", str(topo), "--run",
           "d"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    status = tmp_path / "state" / "status.json"
    deadline = time.time() + 60
    pids = []
    while time.time() < deadline:
        try:
            st = json.loads(status.read_text())
            if st["stages"]["source"].get("words", 0) > 1e6:
                pids = [s["pid"] for s in st["stages"].values() if s["alive"]]
                break
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.1)
    assert len(pids) == 4  # source, two workers, sink
    p.send_signal(signal.SIGKILL)
    p.communicate(timeout=30)

    def alive(pid):
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        return Path(f"/proc/{pid}/stat").exists() and \
            Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"

    deadline = time.time() + 0.5  # (an orphan would run on for ~2 s, to the run's end)
    while any(alive(pid) for pid in pids) and time.time() < deadline:
        time.sleep(0.05)
    assert not [pid for pid in pids if alive(pid)], "orphaned stages"
    index = tmp_path / "state" / "journal" / "d.index.jsonl"
    size = index.stat().st_size
    time.sleep(1.0)
    assert index.stat().st_size == size  # nobody writes the journal any more
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    res = json.loads(out.stdout)
    assert res["failed"] is None
    _same(_histograms(tmp_path / "out", "d"), reference)
    acc = res["accounting"]
    assert acc["balanced"] and acc["words_in"] == CYCLES * N  # one writer: no word twice


def test_one_run_has_one_journal_writer(tmp_path):
    from pipeline.stream.journal import JournalLocked

    w = JournalWriter(tmp_path, "r", 4, 140.0)
    with pytest.raises(JournalLocked, match=f"pid {os.getpid()}"):
        JournalWriter(tmp_path, "r", 4, 140.0)
    JournalWriter(tmp_path, "other", 4, 140.0).close()  # another run: its own lock
    w.close()
    JournalWriter(tmp_path, "r", 4, 140.0).close()  # released with the writer


@pytest.fixture
def tmpfs(tmp_path):
    """A small RAM disk to fill up (root only: skipped elsewhere)."""
    import subprocess

    made = []

    def mount(name, size):
        d = tmp_path / name
        d.mkdir()
        # mode 700: a tmpfs mounts 1777, which the daemon refuses as its state directory
        r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size},mode=700", "tmpfs",
                            str(d)], capture_output=True)
        if r.returncode:
            pytest.skip(f"cannot mount a tmpfs here: {r.stderr.decode().strip()}")
        made.append(d)
        return d

    yield mount
    for d in made:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


def _fill(d: Path) -> Path:
    """Fill ``d`` to the last byte; the filler file to delete to free it."""
    filler = d / "filler"
    with open(filler, "wb", buffering=0) as fh:
        for size in (1 << 20, 1 << 12, 1):
            try:
                while True:
                    fh.write(b"\0" * size)
            except OSError:
                continue
    return filler


def _pause_then_free(sup, stage, filler_dir, after_words):
    deadline = time.time() + 60
    while sup.metrics.get("source", {}).get("words", 0) < after_words:
        assert time.time() < deadline
        time.sleep(0.02)
    filler = _fill(filler_dir)
    while stage not in sup.status()["paused"]:
        assert time.time() < deadline, sup.status()["stages"][stage]
        time.sleep(0.05)
    time.sleep(1.0)  # paused, not dead
    assert all(p.popen.poll() is None for p in sup.procs if not p.finished)
    filler.unlink()


@pytest.mark.slow  # (~10 s; root for the tmpfs)
def test_a_full_output_disk_pauses_the_sink_and_the_run_resumes(tmp_path, tmpfs, reference):
    out = tmpfs("out", "4m")
    topo = topology(tmp_path, cycles=CYCLES, rate=1.5e6)
    topo.write_text(topo.read_text().replace(str(tmp_path / "out"), str(out)))
    res, sup = run_daemon(topo, "o", lambda s: _pause_then_free(s, "sink", out, 5e5))
    assert res["failed"] is None and res["restarts"] == {}
    _same(_histograms(out, "o"), reference)
    assert res["accounting"]["balanced"]
    assert sup.metrics["sink"]["paused_s"] > 0


@pytest.mark.slow  # (~10 s; root for the tmpfs)
def test_a_full_state_disk_pauses_intake_and_the_run_resumes(tmp_path, tmpfs, reference):
    state = tmpfs("state", "48m")
    topo = topology(tmp_path, cycles=CYCLES, rate=1.5e6)
    topo.write_text(topo.read_text().replace(str(tmp_path / "state"), str(state)))
    res, sup = run_daemon(topo, "s", lambda s: _pause_then_free(s, "source", state, 5e5))
    assert res["failed"] is None and res["restarts"] == {}
    _same(_histograms(tmp_path / "out", "s"), reference)
    acc = res["accounting"]
    assert acc["balanced"] and acc["words_in"] == CYCLES * N
    assert json.loads((state / "status.json").read_text())["state"] == "finished"


def test_a_frozen_worker_is_named_killed_and_restarted(tmp_path, reference):
    """Issue 38.4: a histogram worker SIGSTOPped mid-run (and never continued) sends no
    heartbeat; after the deadline the daemon names it (not the source and the sink waiting
    on it), SIGKILLs it (a SIGTERM never reaches a stopped process) and restarts it: the
    run ends in bounded time with the clean run's data. On main it hung for ever."""
    from pipeline.stream.daemon import Supervisor
    from pipeline.stream.topology import load_topology

    path = topology(tmp_path, cycles=CYCLES, rate=1.5e6)
    path.write_text(path.read_text().replace("restarts = 3",
                                             "restarts = 3\nheartbeat_deadline_s = 4"))
    topo = load_topology(path, "fz")
    lines: list[str] = []
    sup = Supervisor(topo, log=lines.append)
    result: dict = {}
    t = threading.Thread(target=lambda: result.update(sup.run()))
    t0 = time.monotonic()
    t.start()
    stopped, health = None, {}
    while time.monotonic() - t0 < 60 and stopped is None:
        p = sup.by_name["histogram-1"].popen
        if sup.metrics.get("source", {}).get("words", 0) >= 600_000 and p.poll() is None:
            stopped = p.pid
            os.kill(stopped, signal.SIGSTOP)
        time.sleep(0.05)
    assert stopped is not None, "the source never got going"
    while time.monotonic() - t0 < 60 and sup.by_name["histogram-1"].frozen == 0:
        st = sup.status()["stages"]
        if (st["histogram-1"]["heartbeat_age_s"] or 0) >= 2.5 and not health:
            health = {n: (s["health"], s["heartbeat_age_s"]) for n, s in st.items()}
        time.sleep(0.1)
    t.join(timeout=120)
    assert not t.is_alive(), "daemon did not finish"
    assert time.monotonic() - t0 < 120
    named = [x for x in lines if "no heartbeat" in x]
    assert len(named) == 1 and named[0].startswith("histogram-1: "), lines
    assert f"pid {stopped}" in named[0]
    # while it is silent, the source behind it reports, "waiting" (not "silent")
    assert health["source"][0] == "waiting" and health["source"][1] < 2, health
    assert result["frozen"] == {"histogram-1": 1}
    assert result["restarts"] == {"histogram-1": 1}
    assert sup.by_name["histogram-1"].exit_codes[0] == -signal.SIGKILL
    assert result["failed"] is None and result["accounting"]["balanced"]
    _same(_histograms(tmp_path / "out", "fz"), reference)
