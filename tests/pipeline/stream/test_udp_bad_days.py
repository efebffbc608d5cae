"""The UDP ingest on bad days (issues 36 point 3, 38 points 1-3): other senders on the port
(a forger, an old rig), a duplicate with other bytes, datagrams the ring dropped, an FPGA
reset, a sequence jump, and a journal disk full longer than ``idle``. Real datagrams over
loopback from their own sockets; each run's words and counts are checked exactly, and the
run's verdict comes from the daemon's own :func:`problems` on its accounting."""

import errno
import socket
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
import zmq

from pipeline.stream import datagram
from pipeline.stream.daemon import problems, run_state
from pipeline.stream.journal import JournalWriter, read_range
from pipeline.stream.reconcile import accounting
from pipeline.stream.udp import run_udp_ingest, udp_socket
from stages.testpattern import pattern_words

N_TDC, CYC, GATE = 16, 4, 140_000


def _load(name):
    # a sibling test module, loaded by path (tests/ is not a package)
    import importlib.util
    from pathlib import Path

    spec = importlib.util.spec_from_file_location(f"_bd_{name}",
                                                  Path(__file__).with_name(f"{name}.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


_faults = _load("test_faults")
tmpfs = _faults.tmpfs  # (the fixture: a RAM disk to fill; root only)


def _stream(n, rng=3, gate=GATE, seq0=0, cycle0=0, last=True):
    words, _ = pattern_words(n * CYC, N_TDC, hit_prob=0.2, rng=rng)
    return words, [datagram.encode(words[i * CYC * N_TDC:(i + 1) * CYC * N_TDC], seq0 + i,
                                   cycle0 + i * CYC, N_TDC, gate, last=last and i == n - 1)
                   for i in range(n)]


class Port:
    """An ingest on a loopback port (in a thread, journal under ``tmp/state/journal``),
    and senders of its datagrams, each its own socket (its own address)."""

    def __init__(self, tmp_path, **kw):
        self.tmp = tmp_path
        self.ctx = zmq.Context()
        self.rx = self.ctx.socket(zmq.PULL)
        self.rx.bind(f"ipc://{tmp_path}/in.sock")
        self.sock = udp_socket("127.0.0.1:0")
        self.port = self.sock.getsockname()[1]
        self.journal = tmp_path / "state" / "journal"
        self.res = {}
        self.kw = {"idle_s": 3, "end_wait_s": 0, "n_tdc": N_TDC, **kw}
        self.thread = None
        self.senders = {}

    def sender(self, name):
        s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        s.bind(("127.0.0.1", 0))
        self.senders[name] = s
        return f"127.0.0.1:{s.getsockname()[1]}"

    def start(self, **kw):
        self.thread = threading.Thread(target=lambda: self.res.update(s=run_udp_ingest(
            self.sock, f"ipc://{self.tmp}/in.sock", run="r", journal=self.journal,
            quarantine=self.tmp / "q", context=self.ctx, **{**self.kw, **kw})))
        self.thread.start()
        self.done = threading.Event()
        self.drain = threading.Thread(target=self._drain, daemon=True)
        self.drain.start()

    def _drain(self):  # (the socket is this thread's alone: it closes it)
        while not self.done.is_set():
            if self.rx.poll(100):
                self.rx.recv_multipart()
        self.rx.close(linger=0)

    def send(self, schedule, rate=None):
        t0 = time.perf_counter()
        for i, (name, data) in enumerate(schedule):
            self.senders[name].sendto(data, ("127.0.0.1", self.port))
            if rate:
                ahead = (i + 1) / rate - (time.perf_counter() - t0)
                if ahead > 0:
                    time.sleep(ahead)
            elif i % 32 == 31:
                time.sleep(0.002)  # (loopback: the kernel buffer is not the test)

    def end(self):
        self.thread.join(timeout=120)
        assert not self.thread.is_alive()
        for s in self.senders.values():
            s.close()
        self.done.set()
        self.drain.join()
        self.ctx.term()
        return self.res["s"]

    def words(self):
        return np.concatenate([w for _, w in read_range(self.journal, "r", 0, 10**12)])

    def verdict(self, stats):
        """The daemon's verdict on this run: its accounting from the ingest's counts."""
        topo = SimpleNamespace(sink={"out": self.tmp / "out"}, run="r",
                               state=self.tmp / "state", source={"kind": "udp"}, range=None)
        acc = accounting(topo, {"source": stats.fields()})
        acc["balanced"] = True  # (no workers here: the words are checked by the test)
        res = {"reconciled": {"checked": True}, "accounting": acc}
        res["problems"] = problems(res)
        return run_state(res), res["problems"], acc


def _interleave(a, b):
    out = []
    for x, y in zip(a, b, strict=False):
        out += [x, y]
    return out + a[len(b):] + b[len(a):]


# ---------------------------------------------------------------- issue 36.3, 38.1

def test_with_peers_forged_datagrams_sent_first_never_reach_the_run(tmp_path):
    words, real = _stream(160)
    _, forged = _stream(160, rng=9, last=False)  # the same gate, sequence and cycles
    p = Port(tmp_path, gate_ps=GATE, first_seq=0)
    fpga, other = p.sender("fpga"), p.sender("forger")
    p.start(peers=[fpga])
    p.send([("forger", d) for d in forged] + [("fpga", d) for d in real])
    s = p.end()
    assert s.accepted == 160 and s.duplicates == 0 and s.conflicts == 0
    assert np.array_equal(p.words(), words)
    book = s.senders.fields()["other_senders"]
    assert book == {other: {"datagrams": 160, "consistent": True, "gate_ps": GATE,
                            "n_tdc": N_TDC}}
    state, why, acc = p.verdict(s)
    assert state == "finished", why  # named, counted, kept out; the run's words exact
    assert acc["other_senders"][other]["datagrams"] == 160


@pytest.mark.parametrize("rig_gate", [150_000, GATE])
def test_an_old_rig_left_on_the_port_never_takes_the_run(tmp_path, rig_gate):
    # the rig: another gate interleaved 1:1 and sending first, or the same stream started
    # 100 datagrams earlier; with peers the run is exact, without it ends incomplete
    # naming the second sender
    words, real = _stream(300)
    _, rig = _stream(400, rng=5, gate=rig_gate, last=False)
    lead = 1 if rig_gate != GATE else 100
    for peers in (True, False):
        d = tmp_path / f"peers{peers}"
        d.mkdir()
        p = Port(d)
        fpga, old = p.sender("fpga"), p.sender("rig")
        p.start(peers=[fpga] if peers else None)
        p.send([("rig", x) for x in rig[:lead]]
               + _interleave([("rig", x) for x in rig[lead:]], [("fpga", x) for x in real]))
        s = p.end()
        state, why, acc = p.verdict(s)
        if peers:
            assert s.accepted == 300 and np.array_equal(p.words(), words)
            assert acc["other_senders"][old]["consistent"] and state == "finished", why
        else:  # the rig sent first and formed the reference: the FPGA is named, the run
            # is never "finished"
            assert acc["sender"] == old and acc["other_senders"][fpga]["consistent"]
            assert state == "incomplete"
            assert any("second sender" in w and fpga in w and "peers" in w for w in why)


def test_a_second_sender_is_remembered_by_a_restarted_ingest(tmp_path):
    words, real = _stream(300)
    _, rig = _stream(100, rng=5, last=False)
    p = Port(tmp_path, idle_s=1)
    p.sender("fpga")
    old = p.sender("rig")
    p.start()
    p.send(_interleave([("fpga", x) for x in real[:100]], [("rig", x) for x in rig]))
    s1 = p.end()
    assert s1.senders.second_stream() == [old]
    p = Port(tmp_path)  # the rig has stopped; the ingest was restarted
    p.sender("fpga")
    p.start()
    p.send([("fpga", x) for x in real[100:]])
    s2 = p.end()
    assert s2.accepted == 200 and np.array_equal(p.words(), words)
    state, why, _ = p.verdict(s2)
    assert state == "incomplete" and any(old in w for w in why)


def test_a_duplicate_with_other_bytes_is_a_conflict_and_the_run_incomplete(tmp_path):
    # a forger who can send from the FPGA's own address (spoofed) gets there first
    words, real = _stream(60)
    fw, forged = _stream(20, rng=9, last=False)
    p = Port(tmp_path, gate_ps=GATE, first_seq=0)
    fpga = p.sender("fpga")
    p.start(peers=[fpga])
    p.send([("fpga", d) for d in forged] + [("fpga", d) for d in real])
    s = p.end()
    assert s.conflicts == 20 and s.rejected["conflict"] == 20 and s.duplicates == 0
    state, why, acc = p.verdict(s)
    assert acc["conflicting_datagrams"] == 20 and state == "incomplete"
    assert any("20 conflicting" in w for w in why)
    # an identical duplicate is what UDP does: counted, not a conflict
    d2 = tmp_path / "dup"
    d2.mkdir()
    p = Port(d2, gate_ps=GATE, first_seq=0)
    p.sender("fpga")
    p.start()
    p.send([("fpga", d) for d in real[:20]] + [("fpga", d) for d in real])
    s = p.end()
    assert s.duplicates == 20 and s.conflicts == 0 and np.array_equal(p.words(), words)
    assert p.verdict(s)[0] == "finished"


def test_datagrams_the_ring_dropped_are_losses(tmp_path):
    # a ring of 4 datagrams and a journal held back: the ring overflows
    words, real = _stream(200)
    p = Port(tmp_path, gate_ps=GATE, first_seq=0, ring_datagrams=4, rx_batch=4)
    p.sender("fpga")
    slow = JournalWriter.append

    def append(self, *a, **k):
        time.sleep(0.05)
        return slow(self, *a, **k)

    JournalWriter.append = append
    try:
        p.start()
        p.send([("fpga", d) for d in real], rate=2000)
        s = p.end()
    finally:
        JournalWriter.append = slow
    assert s.ring_dropped > 0
    state, why, acc = p.verdict(s)
    assert acc["ring_dropped_datagrams"] == s.ring_dropped and state == "incomplete"
    assert any("dropped by the ingest's full ring" in w for w in why)


def test_with_peers_a_flood_from_elsewhere_does_not_fill_the_ring(tmp_path):
    words, real = _stream(200)
    p = Port(tmp_path, gate_ps=GATE, first_seq=0, ring_datagrams=64)
    fpga, junk = p.sender("fpga"), p.sender("junk")
    p.start(peers=[fpga])
    flood = [("junk", b"x" * 1000)] * 20
    sched = []
    for d in real:
        sched += [*flood, ("fpga", d)]
    p.send(sched)
    s = p.end()
    assert s.ring_dropped == 0 and s.accepted == 200 and np.array_equal(p.words(), words)
    assert s.senders.fields()["other_senders"][junk] == {"datagrams": 4000,
                                                         "consistent": False}


# ---------------------------------------------------------------- issue 38.2

@pytest.mark.parametrize("counter", ["restarted", "continued"])
def test_an_fpga_reset_is_a_journaled_event_and_the_run_measures_on(tmp_path, counter):
    n, at = 800, 400
    words, dgs = _stream(n)
    sched = dgs[:at] + [datagram.encode(
        words[i * CYC * N_TDC:(i + 1) * CYC * N_TDC], i - at,
        (i - at) * CYC if counter == "restarted" else i * CYC, N_TDC, GATE, last=i == n - 1)
        for i in range(at, n)]
    for configured in ({}, {"gate_ps": GATE, "first_seq": 0}):
        d = tmp_path / str(bool(configured))
        d.mkdir()
        p = Port(d, **configured)
        p.sender("fpga")
        p.start()
        p.send([("fpga", x) for x in sched])
        s = p.end()
        assert s.accepted == n and s.lost_datagrams == 0 and s.gap_cycles == 0
        assert dict(s.rejected) == {}, s.rejected
        assert np.array_equal(p.words(), words)  # the new segment right after the old
        (ev,) = s.resets
        assert (ev["event"], ev["cycle_counter"], ev["at_cycle"]) == ("fpga_restart",
                                                                      counter, at * CYC)
        from pipeline.stream.journal import _entries

        assert [e["events"][0]["event"] for e in _entries(p.journal / "r.index.jsonl")
                if "events" in e] == ["fpga_restart"]  # journaled with its first chunk
        state, why, _ = p.verdict(s)
        assert state == "incomplete" and any("restarted 1 time" in w for w in why)


def test_an_ingest_restarted_after_a_reset_takes_up_the_new_segment(tmp_path):
    # reset at datagram 400 (cycle counter too); the ingest ends after 600 and a new one
    # on the same journal takes the run up on the new segment's axes
    n, at, cut = 800, 400, 600
    words, dgs = _stream(n)
    sched = dgs[:at] + [datagram.encode(words[i * CYC * N_TDC:(i + 1) * CYC * N_TDC],
                                        i - at, (i - at) * CYC, N_TDC, GATE,
                                        last=i == n - 1) for i in range(at, n)]
    p = Port(tmp_path, idle_s=1)
    p.sender("fpga")
    p.start()
    p.send([("fpga", x) for x in sched[:cut]])
    s1 = p.end()
    assert s1.accepted == cut and len(s1.resets) == 1
    p = Port(tmp_path)
    p.sender("fpga")
    p.start()
    p.send([("fpga", x) for x in sched[cut:]])
    s2 = p.end()
    assert s2.accepted == n - cut and dict(s2.rejected) == {}
    assert s2.lost_datagrams == 0 and s2.gap_cycles == 0 and len(s2.resets) == 1
    assert np.array_equal(p.words(), words)


def test_a_sequence_jump_with_contiguous_cycles_loses_nothing(tmp_path):
    n, at = 600, 300
    words, dgs = _stream(n)
    sched = dgs[:at] + [datagram.encode(words[i * CYC * N_TDC:(i + 1) * CYC * N_TDC],
                                        i + 10_000, i * CYC, N_TDC, GATE, last=i == n - 1)
                        for i in range(at, n)]
    p = Port(tmp_path)
    p.sender("fpga")
    p.start()
    p.send([("fpga", x) for x in sched])
    s = p.end()
    assert s.lost_datagrams == 0 and s.gap_cycles == 0 and dict(s.rejected) == {}
    assert np.array_equal(p.words(), words)
    assert [e["event"] for e in s.resets] == ["sequence_jump"]


def test_a_reset_after_a_lost_start_counts_what_it_lost(tmp_path):
    # the first 10 datagrams of the restarted stream never arrive: counted, not invented
    n, at = 600, 300
    words, dgs = _stream(n)
    sched = dgs[:at] + [datagram.encode(words[i * CYC * N_TDC:(i + 1) * CYC * N_TDC],
                                        i - at, (i - at) * CYC, N_TDC, GATE,
                                        last=i == n - 1) for i in range(at + 10, n)]
    p = Port(tmp_path, gate_ps=GATE, first_seq=0)
    p.sender("fpga")
    p.start()
    p.send([("fpga", x) for x in sched])
    s = p.end()
    assert s.lost_datagrams == 10 and s.gap_cycles == 10 * CYC
    got = p.words()
    assert np.array_equal(got, np.concatenate([words[:at * CYC * N_TDC],
                                               words[(at + 10) * CYC * N_TDC:]]))


# ---------------------------------------------------------------- issue 38.3

def test_a_journal_disk_full_longer_than_idle_does_not_end_the_run(tmp_path):
    # the journal refuses every write (ENOSPC) for 2.5 s, idle = 1 s, 40 datagrams/s
    words, real = _stream(160)
    full = threading.Event()
    ok = JournalWriter.append

    def append(self, *a, **k):
        if full.is_set():
            raise OSError(errno.ENOSPC, "No space left on device")
        return ok(self, *a, **k)

    p = Port(tmp_path, gate_ps=GATE, first_seq=0, idle_s=1.0)
    p.sender("fpga")
    JournalWriter.append = append
    try:
        p.start()

        def disk():
            time.sleep(1.0)
            full.set()
            time.sleep(2.5)
            full.clear()

        t = threading.Thread(target=disk)
        t.start()
        p.send([("fpga", d) for d in real], rate=40)
        t.join()
        s = p.end()
    finally:
        JournalWriter.append = ok
    assert s.paused_s >= 2.0  # it waited for the disk ...
    assert s.accepted == 160 and "after_end" not in s.rejected  # ... and ended on the last
    assert np.array_equal(p.words(), words)


@pytest.mark.slow  # (~25 s; root for the tmpfs)
def test_a_full_state_disk_is_a_health_state_and_the_run_goes_on(tmp_path, tmpfs):
    # the daemon's state (journal, status.json) on a tmpfs filled for 7 s, longer than
    # the source's idle (4 s), at 40 datagrams/s: status.json and the log say "paused",
    # and the run ends on the stream's last datagram with every datagram in
    import json

    from pipeline.stream.daemon import Supervisor
    from pipeline.stream.topology import load_topology

    state = tmpfs("state", "48m")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    (tmp_path / "t.toml").write_text(f"""
[daemon]
state = "{state}"
[source]
kind = "udp"
bind = "127.0.0.1:{port}"
n_tdc = {N_TDC}
idle = 4
[histogram]
workers = 2
measurement_cycles = 64
artifacts = "count-as-hits"
[sink]
out = "{tmp_path / 'out'}"
""")
    n = 600
    words, dgs = _stream(n)
    log, seen = [], {}
    sup = Supervisor(load_topology(tmp_path / "t.toml", "u"), log=log.append)
    res = {}
    t = threading.Thread(target=lambda: res.update(sup.run()))
    t.start()
    deadline = time.time() + 60
    while "source" not in sup.metrics:
        assert time.time() < deadline
        time.sleep(0.05)
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    t0 = time.perf_counter()
    filler = None
    for i, d in enumerate(dgs):
        if i == 100:
            filler = _faults._fill(state)
        if filler is not None and time.perf_counter() - t0 > 100 / 40 + 7:
            for _ in range(40):  # status.json, read from the full disk, says so
                st = json.loads((state / "status.json").read_text())
                if st["stages"]["source"]["health"] == "paused":
                    seen = st
                    break
                time.sleep(0.1)
            filler.unlink()
            filler = None
        out.sendto(d, ("127.0.0.1", port))
        ahead = (i + 1) / 40 - (time.perf_counter() - t0)
        if ahead > 0:
            time.sleep(ahead)
    out.close()
    t.join(timeout=120)
    assert not t.is_alive()
    assert seen and "disk full" in seen["paused"]["source"]
    assert any(m.startswith("source: paused (disk full") for m in log), log
    assert any(m == "source: resumed" for m in log)
    src = sup.metrics["source"]
    assert src["accepted"] == n and "after_end" not in src["rejected"], src
    assert res["state"] == "finished", res["problems"]
    assert res["accounting"]["words_in"] == words.size and res["accounting"]["balanced"]


def test_peers_in_the_topology_reach_the_ingest_or_are_refused_in_one_line(tmp_path):
    from pipeline.stream.daemon import build
    from pipeline.stream.topology import TopologyError, load_topology

    def topo(peers):
        (tmp_path / "t.toml").write_text(f"""
[daemon]
state = "{tmp_path / 'state'}"
[source]
kind = "udp"
bind = "127.0.0.1:9000"
n_tdc = 16
peers = {peers}
[histogram]
artifacts = "count-as-hits"
[sink]
out = "{tmp_path / 'out'}"
""")
        return load_topology(tmp_path / "t.toml", "u")

    (src,) = [p for p in build(topo('["127.0.0.1:7000", "localhost"]')) if p.name == "source"]
    argv = [str(a) for a in src.argv]
    assert [argv[i + 1] for i, a in enumerate(argv) if a == "--peer"] == [
        "127.0.0.1:7000", "localhost"]
    for bad, why in (('["10.0.0.1:99999"]', "port 1..65535"), ('[]', "no sender"),
                     ('["no such host.invalid"]', "HOST or HOST:PORT")):
        with pytest.raises(TopologyError, match=why) as exc:
            topo(bad)
        assert "\n" not in str(exc.value)


def test_status_json_is_rewritten_in_place_when_no_new_file_can_be_made(tmp_path,
                                                                          monkeypatch):
    import contextlib
    import json

    from pipeline.stream import daemon

    path = tmp_path / "status.json"
    daemon.write_status_file(path, json.dumps({"state": "running", "health": "ok"}))

    @contextlib.contextmanager
    def full(_):
        raise OSError(errno.ENOSPC, "No space left on device")
        yield

    monkeypatch.setattr(daemon, "atomic_path", full)
    daemon.write_status_file(path, json.dumps({"state": "running", "health": "paused",
                                               "paused": {"source": "disk full"}}))
    assert json.loads(path.read_text())["health"] == "paused"
    with pytest.raises(OSError):  # (more than the padding holds: never a torn file)
        daemon.write_status_file(path, json.dumps({"x": "y" * 20_000}))
    assert json.loads(path.read_text())["health"] == "paused"
