"""Real ZeroMQ stages in subprocesses, and the runner's handling of bad messages."""

import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import polars as pl
import zmq

from pipeline.offline.simulate import make_simulator
from pipeline.stream import wire
from pipeline.stream.stage import run_stage
from schemas import RAW_SPARSE, RAW_WORDS
from stages.datapath import SparseWords
from stages.histogram import HistogramAccumulator
from stages.stream import HistogramCore

SCENES = Path(__file__).parents[3] / "scenes"


def test_a_source_a_histogram_and_a_sink_give_the_offline_histograms(tmp_path, run_stages):
    """source-sim -> histogram -> sink over ipc://, as three processes and as three threads
    (the same commands), against the same words histogrammed offline."""
    ep_h, ep_s = f"ipc://{tmp_path}/h", f"ipc://{tmp_path}/s"
    run_stages(["sink", "--pull", ep_s, "--out", str(tmp_path / "data")],
               ["histogram", "--pull", ep_h, "--push", ep_s],
               ["source-sim", str(SCENES / "street.toml"), "--cycles", "6000", "--push", ep_h,
                "--seed", "3", "--run", "r1"])
    got = pl.read_parquet(tmp_path / "data" / "histograms", hive_partitioning=True)
    assert got["run"].unique().to_list() == ["r1"]
    sim = make_simulator(SCENES / "street.toml", 6000, seed=3)
    acc = HistogramAccumulator(128)
    for _, w in sim.batches(6000):
        acc.update(w)
    ref = acc.snapshot()
    got = got.sort("tdc")
    assert np.array_equal(np.stack(got["counts"].to_numpy()), ref.hits)
    assert got["cycles"].to_list() == [6000] * 128
    assert int(got["n_hit"].sum()) == int(ref.class_counts[0].sum())


def test_bad_messages_are_counted_and_quarantined(tmp_path):
    ctx = zmq.Context()
    ep = f"ipc://{tmp_path}/in"
    core = HistogramCore(4)
    result = {}
    t = threading.Thread(target=lambda: result.update(
        s=run_stage(core, ep, None, quarantine=tmp_path / "q", context=ctx)))
    t.start()
    tx = ctx.socket(zmq.PUSH)
    tx.connect(ep)
    good = {"kind": "data", "schema": RAW_WORDS.name, "version": "1.0", "run": "r",
            "seq": 0, "step": "t", "first_word": 0, "n_tdc": 4, "t_laser_win_ns": 140.0}
    import pyarrow as pa
    batch = pa.record_batch([pa.array(np.zeros(8, np.uint32))], schema=RAW_WORDS.schema)
    frames = wire.encode(good, batch)
    tx.send_multipart([b"garbage"])
    tx.send_multipart([b"{bad json", b""])
    tx.send_multipart([frames[0], frames[1].to_pybytes()[:20]])
    tx.send_multipart(wire.encode({**good, "version": "9.0"}, batch))
    tx.send_multipart(frames)
    tx.send_multipart(wire.encode({**good, "kind": "stop"}, None))
    t.join(timeout=30)
    tx.close(linger=0)
    ctx.term()
    s = result["s"]
    assert dict(s.rejected) == {"bad_frames": 1, "bad_header": 1, "bad_payload": 1,
                                "schema_version": 1}
    assert s.received == 6
    assert core.words_total == 8
    assert len(list((tmp_path / "q").glob("*.json"))) == 4


def test_udp_ingest_accounts_for_every_datagram(tmp_path):
    """Good, garbage and out-of-sequence datagrams over loopback UDP: every one counted,
    the words journaled and forwarded exactly."""
    import socket as pysocket

    from pipeline.io.capture import Capture
    from pipeline.stream import datagram
    from pipeline.stream.udp import run_udp_ingest, udp_socket
    from stages.testpattern import pattern_words

    ctx = zmq.Context()
    ep = f"ipc://{tmp_path}/ingest"
    rx = ctx.socket(zmq.PULL)
    rx.bind(ep)
    sock = udp_socket("127.0.0.1:0")
    port = sock.getsockname()[1]
    result = {}
    t = threading.Thread(target=lambda: result.update(s=run_udp_ingest(
        sock, ep, run="u1", journal=tmp_path / "journal", quarantine=tmp_path / "q",
        idle_s=10, context=ctx, end_wait_s=0)))  # (read after it ended)
    t.start()
    words, _ = pattern_words(40 * 32, 128, hit_prob=0.1, rng=2)
    out = pysocket.socket(pysocket.AF_INET, pysocket.SOCK_DGRAM)
    sent_words = []
    for i in range(40):
        chunk = words[i * 32 * 128:(i + 1) * 32 * 128]
        if i == 7:
            continue  # lost on the way: a sequence gap
        out.sendto(datagram.encode(chunk, i, i * 32, 128, 140_000, last=(i == 39)),
                   ("127.0.0.1", port))
        time.sleep(0.002)  # loopback UDP drops under a burst into a small socket buffer
        sent_words.append(chunk)
        if i == 10:
            out.sendto(b"garbage!", ("127.0.0.1", port))
            out.sendto(b"XXXX" + bytes(60), ("127.0.0.1", port))
    t.join(timeout=30)
    got, stopped = [], None
    while rx.poll(1000):
        head, batch = wire.decode(rx.recv_multipart(), RAW_WORDS)
        if head["kind"] == "stop":
            stopped = head
            break
        got.append((head["first_word"], batch.column("word").to_numpy()))
    rx.close(linger=0)
    out.close()
    ctx.term()
    s = result["s"]
    assert s.lost_datagrams == 1 and dict(s.rejected) == {"truncated": 1, "bad_magic": 1}
    assert s.datagrams == 39 + 2
    forwarded = np.concatenate([w for _, w in got])
    assert np.array_equal(forwarded, np.concatenate(sent_words))
    # the batch after the gap starts at its first word (how the datagrams before it are
    # batched depends on their timing: a loaded machine flushes more, smaller batches)
    firsts = [f for f, _ in got]
    assert 8 * 32 * 128 in firsts
    assert all(not (f < 8 * 32 * 128 < f + w.size) for f, w in got)
    assert stopped["words"] == forwarded.size and stopped["lost_datagrams"] == 1
    from pipeline.stream.journal import read_range, run_end

    journaled = np.concatenate([w for _, w in read_range(tmp_path / "journal", "u1", 0,
                                                         10**12)])
    assert np.array_equal(journaled, forwarded)
    assert run_end(tmp_path / "journal", "u1") == 40 * 32 * 128  # the gap is inside the run
    assert all(Capture(p).n_words > 0 for p in s.journal)  # closed segments are captures
    assert len(list((tmp_path / "q").glob("*.bin"))) == 2


def test_sigkill_of_the_middle_stage_loses_and_double_counts_nothing(tmp_path):
    """Kill the histogram stage with SIGKILL mid-run, restart it from its checkpoint: the
    final histograms equal those of an uninterrupted run (journal fills the gap)."""
    import signal

    ep_h, ep_s = f"ipc://{tmp_path}/h", f"ipc://{tmp_path}/s"
    cli = [sys.executable, "-m", "pipeline.cli", "stage"]
    ckpt, journal = tmp_path / "hist.ckpt.npz", tmp_path / "journal"
    hist_cmd = cli + ["histogram", "--pull", ep_h, "--push", ep_s, "--checkpoint", str(ckpt),
                      "--quarantine", str(tmp_path / "q"),
                      "--journal", str(journal), "--run", "k1"]
    sink = subprocess.Popen(cli + ["sink", "--pull", ep_s, "--out", str(tmp_path / "data")])
    hist = subprocess.Popen(hist_cmd)
    source = subprocess.Popen(cli + ["source-sim", str(SCENES / "street.toml"), "--cycles",
                                     "8192", "--push", ep_h, "--seed", "5", "--run", "k1",
                                     "--rate", "600000", "--journal", str(journal)])
    deadline = time.time() + 60
    while not ckpt.exists() and time.time() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)
    hist.send_signal(signal.SIGKILL)
    hist.wait(timeout=10)
    hist = subprocess.Popen(hist_cmd)  # the supervisor's restart
    for p in (source, hist, sink):
        assert p.wait(timeout=120) == 0
    got = pl.read_parquet(tmp_path / "data" / "histograms", hive_partitioning=True).sort("tdc")
    # a worker restarted after its source ended labels its output from the journal's run
    # meta (it once wrote a bogus run=run partition, then a header without the gate)
    assert got["run"].unique().to_list() == ["k1"]
    sim = make_simulator(SCENES / "street.toml", 8192, seed=5)
    acc = HistogramAccumulator(128)
    for _, w in sim.batches(8192):
        acc.update(w)
    ref = acc.snapshot()
    assert np.array_equal(np.stack(got["counts"].to_numpy()), ref.hits)
    assert got["cycles"].to_list() == [8192] * 128
    assert int(got["n_no_hit"].sum()) == int(ref.class_counts[1].sum())


def test_a_stage_that_exits_delivers_what_it_queued_for_a_slow_consumer(tmp_path):
    """ZeroMQ sends from a background thread: a stage process that exits with messages
    queued for a slower consumer must deliver them (its last batches and its stop), not
    leave them to the journal and the supervisor's SIGTERM."""
    from pipeline.io.capture import CaptureWriter
    from stages.testpattern import pattern_words

    words, _ = pattern_words(40 * 2048, 16, hit_prob=0.1, rng=3)
    with CaptureWriter(tmp_path / "cap", 16, kind="pattern") as w:
        w.write(words)
    ep = f"ipc://{tmp_path}/slow"
    ctx = zmq.Context()
    rx = ctx.socket(zmq.PULL)
    rx.set_hwm(1)
    rx.bind(ep)
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "stage", "source-capture",
                             str(tmp_path / "cap.bin"), "--push", ep, "--run", "r"],
                            stderr=subprocess.DEVNULL)
    got, stopped, parts = 0, False, []
    try:
        while rx.poll(30_000):
            head, batch = wire.decode(rx.recv_multipart(), {RAW_WORDS.name: RAW_WORDS,
                                                            RAW_SPARSE.name: RAW_SPARSE})
            if head["kind"] == "stop":
                stopped = True
                break
            assert head["schema"] == RAW_SPARSE.name  # the chip's words go sparse
            sw = SparseWords(head["n_words"], batch.column("index").to_numpy(),
                             batch.column("word").to_numpy())
            assert sw.problem() is None and head["first_word"] == got
            parts.append(sw.dense(head["first_word"], 16))
            got += sw.size
            time.sleep(0.05)  # a consumer slower than the source: its queue is full
        rx.close(linger=0)  # a stage hangs up once it has its stop: the source then ends
        assert proc.wait(timeout=60) == 0
    finally:
        proc.kill()
        rx.close(linger=0)
        ctx.term()
    assert stopped and got == words.size
    # the sparse messages carry every word (its own data, not the code's no_hit pattern)
    np.testing.assert_array_equal(np.concatenate(parts), words.ravel())
