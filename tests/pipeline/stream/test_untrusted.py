"""Untrusted input (issue 16): reordered, duplicated and poisoned datagrams, headers that
break their schema, forged messages without the run's token, headers that would write
outside the output directory. Each compares with an uninterrupted run of the same input
and checks the accounting exactly."""

import json
import os
import socket
import stat
import threading
import time

import numpy as np
import pyarrow as pa
import pytest
import zmq

from pipeline.stream import datagram, wire
from pipeline.stream.journal import read_range, run_end
from pipeline.stream.stage import ParquetSink, run_stage
from pipeline.stream.udp import run_udp_ingest, udp_socket
from schemas import RAW_WORDS
from stages.stream import HistogramCore
from stages.testpattern import pattern_words

N_TDC, CYC = 16, 4  # TDCs per cycle, cycles per datagram
GATE_PS = 140_000


def _ingest(tmp_path, name, schedule, **kw):
    """Send ``schedule`` (bytes, in order) to a fresh ingest over loopback UDP; returns
    its stats, the forwarded words by stream index and the journaled words."""
    ctx = zmq.Context()
    ep = f"ipc://{tmp_path}/{name}.sock"
    rx = ctx.socket(zmq.PULL)
    rx.bind(ep)
    sock = udp_socket("127.0.0.1:0")
    port = sock.getsockname()[1]
    res = {}
    t = threading.Thread(target=lambda: res.update(s=run_udp_ingest(
        sock, ep, run=name, journal=tmp_path / name, quarantine=tmp_path / f"q-{name}",
        idle_s=5, context=ctx, end_wait_s=0, **kw)))  # (read after it ends)
    t.start()
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for data in schedule:
        out.sendto(data, ("127.0.0.1", port))
        time.sleep(0.001)
    t.join(timeout=60)
    assert not t.is_alive()
    got = {}
    while rx.poll(1000):
        head, batch = wire.decode(rx.recv_multipart(), RAW_WORDS)
        if head["kind"] == "stop":
            break
        w = batch.column("word").to_numpy()
        for i in range(0, w.size, N_TDC):  # by cycle: batching may differ between runs
            got[head["first_word"] // N_TDC + i // N_TDC] = w[i:i + N_TDC]
    rx.close(linger=0)
    out.close()
    ctx.term()
    journaled = {}
    for first, w in read_range(tmp_path / name, name, 0, 10**12):
        for i in range(0, w.size, N_TDC):
            journaled[first // N_TDC + i // N_TDC] = w[i:i + N_TDC]
    return res["s"], got, journaled


def _datagrams(n=100):
    words, _ = pattern_words(n * CYC, N_TDC, hit_prob=0.2, rng=4)
    return [datagram.encode(words[i * CYC * N_TDC:(i + 1) * CYC * N_TDC], i, i * CYC, N_TDC,
                            GATE_PS, last=(i == n - 1)) for i in range(n)]


def test_reordered_duplicated_and_poisoned_datagrams_are_reassembled_exactly(tmp_path):
    dgs = _datagrams(100)
    ref_stats, ref, ref_j = _ingest(tmp_path, "ref", dgs, reorder_window=8)
    assert ref_stats.duplicates == ref_stats.lost_datagrams == ref_stats.gap_cycles == 0
    assert sorted(ref) == list(range(100 * CYC)) and sorted(ref_j) == sorted(ref)

    order = list(range(100))
    for i in (3, 11, 17, 25, 33, 41, 55, 71, 85):  # 9 swapped pairs
        order[i], order[i + 1] = order[i + 1], order[i]
    order.remove(60)          # never sent: a true gap
    order.remove(20)
    order.insert(order.index(45), 20)  # 25 datagrams late: its window (8) has closed
    schedule = []
    dup_after = {5, 12, 30, 31, 50, 77, 90}  # 7 duplicates, a few datagrams later
    for k, i in enumerate(order):
        schedule.append(dgs[i])
        if i in dup_after:
            schedule.append(dgs[i])
        if k == 40:
            w = np.zeros(CYC * N_TDC, np.uint32)
            schedule += [datagram.encode(w, 41, 2**62, N_TDC, GATE_PS),   # OverflowError
                         datagram.encode(w, 42, 2**40, N_TDC, GATE_PS),   # a 4e9-cycle gap
                         datagram.encode(w, 2**31, 44 * CYC, N_TDC, GATE_PS),   # seq jump
                         datagram.encode(np.zeros(CYC * 8, np.uint32), 43, 44 * CYC, 8,
                                         GATE_PS),                        # other chip
                         datagram.encode(w, 43, 44 * CYC, N_TDC, 0)]      # no gate
    t0 = time.time()
    s, got, journaled = _ingest(tmp_path, "hostile", schedule, reorder_window=8)
    assert time.time() - t0 < 30  # no hang on the 2^40 jump
    assert s.duplicates == 7
    assert s.late == 1 and s.lost_datagrams == 1
    assert s.gap_cycles == 2 * CYC  # the one never sent and the late one
    assert dict(s.rejected) == {"cycle_out_of_window": 2, "seq_out_of_window": 1,
                                "n_tdc_mismatch": 1, "bad_gate": 1, "late": 1}
    assert s.datagrams == len(schedule)
    assert s.datagrams == s.accepted + s.duplicates + sum(s.rejected.values())
    missing = set(range(20 * CYC, 21 * CYC)) | set(range(60 * CYC, 61 * CYC))
    assert sorted(got) == sorted(set(ref) - missing)  # each cycle once, none invented
    for c in got:
        assert np.array_equal(got[c], ref[c]) and np.array_equal(journaled[c], ref[c])
    assert sorted(journaled) == sorted(got)
    assert run_end(tmp_path / "hostile", "hostile") == run_end(tmp_path / "ref", "ref")
    q = sorted((tmp_path / "q-hostile").glob("*.json"))
    assert len(q) == 6  # every rejected datagram quarantined, with its reason
    assert "late" in {json.loads(p.read_text())["reason"].split(":")[0] for p in q}


# ---------------------------------------------------------------- stage messages

def _batch(n):
    return pa.record_batch([pa.array(np.arange(n, dtype=np.uint32) % 7)],
                           schema=RAW_WORDS.schema)


GOOD = {"kind": "data", "schema": RAW_WORDS.name, "version": "1.0", "run": "r", "seq": 0,
        "step": "source", "first_word": 0, "n_tdc": 4, "t_laser_win_ns": 140.0}


def _run_histogram(tmp_path, messages, token=None, name="h"):
    """A histogram stage fed ``messages`` (frames); returns its stats and core."""
    ctx = zmq.Context()
    ep = f"ipc://{tmp_path}/{name}.sock"
    core = HistogramCore(4)
    res = {}
    kw = {"token": token} if token else {}  # (the keyword is new: run on old code too)
    t = threading.Thread(target=lambda: res.update(s=run_stage(
        core, ep, None, quarantine=tmp_path / f"q-{name}", context=ctx, **kw)))
    t.start()
    tx = ctx.socket(zmq.PUSH)
    tx.connect(ep)
    for frames in messages:
        tx.send_multipart(frames)
    t.join(timeout=30)
    assert not t.is_alive(), "the stage did not finish"
    tx.close(linger=0)
    ctx.term()
    return res["s"], core


def test_headers_that_break_their_schema_are_rejected_not_fatal(tmp_path):
    stop = wire.encode({**GOOD, "kind": "stop"}, None)
    good = [wire.encode({**GOOD, "seq": i, "first_word": 8 * i}, _batch(8)) for i in range(3)]
    _, ref = _run_histogram(tmp_path, [*good, stop], name="ref")
    bad = [{k: v for k, v in GOOD.items() if k != "first_word"},
           *({k: v for k, v in GOOD.items() if k != "t_laser_win_ns"} for _ in range(6)),
           {**GOOD, "first_word": "12"}, {**GOOD, "first_word": 2**70},
           {**GOOD, "first_word": -8}, {**GOOD, "n_tdc": True}, {**GOOD, "seq": None},
           {**GOOD, "date": "../../.."}, {**GOOD, "run": ".."}, {**GOOD, "kind": "boom"},
           {**GOOD, "t_laser_win_ns": float("nan")}]
    msgs = [good[0], *(wire.encode(h, _batch(8)) for h in bad), *good[1:], stop]
    s, core = _run_histogram(tmp_path, msgs)
    assert dict(s.rejected) == {"bad_header": len(bad)}
    assert s.received == len(msgs)
    assert np.array_equal(core.acc.snapshot().hits, ref.acc.snapshot().hits)
    assert core.words_total == ref.words_total == 24
    assert len(list((tmp_path / "q-h").glob("*.json"))) == len(bad)


def test_forged_stop_and_words_without_the_run_token_are_rejected(tmp_path):
    token = "t" * 32
    good = [wire.encode({**GOOD, "seq": i, "first_word": 8 * i}, _batch(8), token)
            for i in range(3)]
    stop = wire.encode({**GOOD, "kind": "stop"}, None, token)
    _, ref = _run_histogram(tmp_path, [*good, stop], token=token, name="ref")
    forged = [wire.encode({**GOOD, "kind": "stop"}, None),                    # no token
              wire.encode({**GOOD, "kind": "stop"}, None, "x" * 32),          # wrong one
              wire.encode({**GOOD, "seq": 9, "first_word": 24}, _batch(8)),   # injected
              wire.encode({**GOOD, "seq": 9, "first_word": 4}, _batch(8), "t" * 31)]
    s, core = _run_histogram(tmp_path, [good[0], *forged, *good[1:], stop], token=token)
    assert dict(s.rejected) == {"bad_token": 4}
    assert np.array_equal(core.acc.snapshot().hits, ref.acc.snapshot().hits)
    assert core.words_total == 24  # the forged stop did not end the stream early


def test_the_sink_refuses_paths_outside_its_directory(tmp_path):
    sink = ParquetSink(tmp_path / "out")
    head = {"schema": "histograms", "run": "r1", "seq": 0, "date": "2026-11-25",
            "tdc_range": [0, 4]}
    assert sink.path(head).is_relative_to(tmp_path / "out")
    for bad in ({"date": "../../.."}, {"run": "../x"}, {"run": ".."}, {"schema": "../h"},
                {"date": "2026-13-45/x"}, {"run": "a/b"}, {"date": 5}):
        with pytest.raises(wire.WireError, match="bad_path"):
            sink.path({**head, **bad})
    (tmp_path / "out").mkdir()
    os.symlink(tmp_path, tmp_path / "out" / "histograms")  # a planted link out
    with pytest.raises(wire.WireError, match="outside"):
        sink.path(head)


def test_oversized_messages_stop_at_the_socket(tmp_path):
    """A frame above the limit never reaches the stage (ZMQ_MAXMSGSIZE); the stage goes
    on with the next sender's messages."""
    ctx = zmq.Context()
    ep = f"ipc://{tmp_path}/big"
    core = HistogramCore(4)
    res = {}
    t = threading.Thread(target=lambda: res.update(s=run_stage(
        core, ep, None, context=ctx, max_bytes=1 << 16)))
    t.start()
    evil = ctx.socket(zmq.PUSH)
    evil.connect(ep)
    evil.send_multipart([json.dumps(GOOD).encode(), bytes(1 << 17)])
    time.sleep(0.3)
    tx = ctx.socket(zmq.PUSH)
    tx.connect(ep)
    tx.send_multipart(wire.encode(GOOD, _batch(8)))
    tx.send_multipart(wire.encode({**GOOD, "kind": "stop"}, None))
    t.join(timeout=30)
    assert not t.is_alive()
    for s in (evil, tx):
        s.close(linger=0)
    ctx.term()
    assert res["s"].received == 2 and core.words_total == 8


def test_quarantine_is_bounded_and_counts_what_it_drops(tmp_path):
    from pipeline.stream.stage import Quarantine

    q = Quarantine(tmp_path / "q", max_files=5, max_bytes=10_000)
    kept = [q.put("bad", bytes(100)) for _ in range(8)]
    assert kept == [True] * 5 + [False] * 3 and q.dropped == 3
    q2 = Quarantine(tmp_path / "q", max_files=5, max_bytes=10_000)  # a restarted stage
    assert (q2.kept, q2.dropped) == (5, 3)
    assert not q2.put("bad", bytes(10))
    assert Quarantine(tmp_path / "q").dropped == 4
    assert len(list((tmp_path / "q").glob("*.bin"))) == 5


def test_a_stale_ipc_file_is_removed_and_a_live_one_is_not_stolen(tmp_path):
    from pipeline.stream.stage import EndpointInUse, bind

    path = tmp_path / "s"
    raw = socket.socket(socket.AF_UNIX)
    raw.bind(str(path))  # a dead process's socket file
    raw.close()
    ctx = zmq.Context()
    a = ctx.socket(zmq.PULL)
    bind(a, f"ipc://{path}")
    b = ctx.socket(zmq.PULL)
    with pytest.raises(EndpointInUse):  # libzmq would silently take it from `a`
        bind(b, f"ipc://{path}")
    tx = ctx.socket(zmq.PUSH)
    tx.connect(f"ipc://{path}")
    tx.send(b"x")
    assert a.poll(2000) and a.recv() == b"x"
    for s in (a, b, tx):
        s.close(linger=0)
    ctx.term()
    assert stat.S_ISSOCK(path.lstat().st_mode) or not path.exists()


def test_curve_admits_only_the_graphs_keys(tmp_path):
    """CURVE on loopback, turned on explicitly: a client with the graph's keys delivers; a
    plain client and one with keys of its own do not."""
    import zmq.auth

    from pipeline.stream import curve
    from pipeline.stream.stage import connect

    keys = curve.ensure_keys(tmp_path / "state")
    assert stat.S_IMODE(keys.stat().st_mode) == 0o700
    assert stat.S_IMODE((keys / "client.key_secret").stat().st_mode) == 0o600
    ctx = zmq.Context()
    rx = ctx.socket(zmq.PULL)
    curve.serve(rx, keys)
    port = rx.bind_to_random_port("tcp://127.0.0.1")
    ep = f"tcp://127.0.0.1:{port}"
    plain = ctx.socket(zmq.PUSH)
    plain.connect(ep)
    other = ctx.socket(zmq.PUSH)
    own_pub, own_sec = zmq.auth.load_certificate(
        zmq.auth.create_certificates(str(tmp_path), "intruder")[1])
    other.curve_secretkey, other.curve_publickey = own_sec, own_pub
    other.curve_serverkey = zmq.auth.load_certificate(str(keys / "server.key"))[0]
    other.connect(ep)
    good = ctx.socket(zmq.PUSH)
    os.environ[curve.CURVE_ENV] = str(keys)
    try:
        connect(good, ep)
    finally:
        del os.environ[curve.CURVE_ENV]
    for s, msg in ((plain, b"plain"), (other, b"intruder"), (good, b"ours")):
        s.send(msg)  # queued while the handshake runs (or fails)
    got = []
    while rx.poll(1500):
        got.append(rx.recv())
    assert got == [b"ours"]
    assert curve.needs_curve(["tcp://10.0.0.2:5555"]) and curve.needs_curve(["tcp://*:1"])
    assert curve.needs_curve(["tcp://127.0.0.1:5555"])  # any local account reaches it
    assert not curve.needs_curve(["ipc:///tmp/x", "inproc://x"])
    for s in (rx, plain, other, good):
        s.close(linger=0)
    curve.stop_authenticators()
    ctx.term()


def test_a_stalled_stage_downstream_loses_no_datagram(tmp_path):
    """The histogram stage comes up only after the run's datagrams have all arrived (40 MB,
    ten times the kernel's socket buffer): receiving never waits for it, every datagram is
    journaled, and the stage fills what could not be sent from the journal. Its histograms
    equal those of the words sent."""
    from pipeline.stream.fanout import worker_reader
    from pipeline.stream.journal import run_end
    from stages.histogram import HistogramAccumulator, HistogramState

    n_tdc, cyc, n = 128, 127, 600
    words, _ = pattern_words(n * cyc, n_tdc, hit_prob=0.1, rng=9)
    ctx = zmq.Context()
    ep = f"ipc://{tmp_path}/h.sock"
    sock = udp_socket("127.0.0.1:0")
    port = sock.getsockname()[1]
    res = {}
    ingest = threading.Thread(target=lambda: res.update(s=run_udp_ingest(
        sock, ep, run="st", journal=tmp_path / "j", idle_s=10, context=ctx, send_queue=2,
        end_wait_s=0)))  # (its consumer hangs up after it ended)
    ingest.start()
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for i in range(n):
        out.sendto(datagram.encode(words[i * cyc * n_tdc:(i + 1) * cyc * n_tdc], i, i * cyc,
                                   n_tdc, GATE_PS, last=(i == n - 1)), ("127.0.0.1", port))
        time.sleep(0.001)
    out.close()
    time.sleep(1.0)  # the stage is still not there
    core = HistogramCore(n_tdc, backfill=worker_reader(
        lambda a, b: read_range(tmp_path / "j", "st", a, b), n_tdc, (0, n_tdc)))
    sink = ctx.socket(zmq.PULL)
    sink.bind(f"ipc://{tmp_path}/out.sock")
    stage = run_stage(core, ep, f"ipc://{tmp_path}/out.sock", context=ctx,
                      run_ended=lambda: run_end(tmp_path / "j", "st"),
                      end_wait_s=0)  # (this test reads its output after it returned)
    ingest.join(timeout=60)
    assert not ingest.is_alive()
    head, batch = wire.decode(sink.recv_multipart())
    sink.close(linger=0)
    ctx.term()
    s = res["s"]
    assert s.accepted == n and s.lost_datagrams == 0 and s.ring_dropped == 0
    assert s.deferred_messages > 0 and core.backfilled == s.deferred_words
    assert core.gap_words == 0 and core.duplicates == 0 and stage.rejected == {}
    ref = HistogramAccumulator(n_tdc)
    ref.update(words)
    got = HistogramState.from_table(pa.Table.from_batches([batch]))
    assert head["words"] == words.size == core.words_total
    assert np.array_equal(got.hits, ref.snapshot().hits)


def test_a_stage_whose_consumer_is_gone_still_stops_on_sigterm(tmp_path):
    """A worker restarted after its sink finished (killed just after its stop was sent)
    refolds the run and has nobody to send to: a SIGTERM must still end it (the messages
    are counted unwritten; the end of the run recomputes them from the journal). Seen: such
    a worker blocked in send for ever and the daemon never finished."""
    import signal
    import subprocess
    import sys

    pull, push = f"ipc://{tmp_path}/in", f"ipc://{tmp_path}/nobody"
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "stage", "histogram",
                             "--pull", pull, "--push", push, "--n-tdc", "4",
                             "--measurement-cycles", "10"], stderr=subprocess.PIPE,
                            text=True)
    ctx = zmq.Context()
    tx = ctx.socket(zmq.PUSH)
    tx.connect(pull)
    words, _ = pattern_words(100, 4, rng=1)
    for k in range(3):
        head = {"kind": "data", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
                "run": "r", "seq": k, "step": "source", "first_word": k * words.size,
                "n_tdc": 4, "t_laser_win_ns": 140.0}
        tx.send_multipart(wire.encode(head, pa.record_batch([pa.array(words)],
                                                            schema=RAW_WORDS.schema)))
    time.sleep(3)  # it has folded them and is blocked sending 30 measurements to nobody
    assert proc.poll() is None
    proc.send_signal(signal.SIGTERM)
    try:
        err = proc.communicate(timeout=20)[1]
    finally:
        proc.kill()
        tx.close(linger=0)
        ctx.term()
    assert proc.returncode == 0, err
