"""The UDP ingest's batches (issue 25): a receive hands over every datagram that is ready,
and the released ones are journaled as one chunk per batch of consecutive cycles, its index
line carrying the batch's sequence numbers. A gap or a reorder inside a batch, a restart
between batches, and a partial batch that must not wait for more datagrams."""

import socket
import threading
import time

import numpy as np
import pytest
import zmq

from pipeline.stream import datagram, wire
from pipeline.stream.journal import _entries, read_range
from pipeline.stream.udp import resume_state, run_udp_ingest, udp_socket
from schemas import RAW_SPARSE, RAW_WORDS
from stages.datapath import SparseWords
from stages.testpattern import pattern_words

N_TDC, CYC, GATE_PS = 16, 4, 140_000


def _stream(n: int, rng: int):
    words, _ = pattern_words(n * CYC, N_TDC, hit_prob=0.2, rng=rng)
    dgs = [datagram.encode(words[i * CYC * N_TDC:(i + 1) * CYC * N_TDC], i, i * CYC, N_TDC,
                           GATE_PS, last=(i == n - 1)) for i in range(n)]
    return words, dgs


class Ingest:
    """An ingest on a loopback port in a thread, its messages collected from a PULL."""

    def __init__(self, tmp_path, name, journal, **kw):
        self.ctx = zmq.Context()
        ep = f"ipc://{tmp_path}/{name}.sock"
        self.rx = self.ctx.socket(zmq.PULL)
        self.rx.bind(ep)
        sock = udp_socket("127.0.0.1:0")
        self.port = sock.getsockname()[1]
        self.stop, self.res = threading.Event(), {}
        kw = {"idle_s": 5, "end_wait_s": 0, "n_tdc": N_TDC, "gate_ps": GATE_PS, **kw}
        self.thread = threading.Thread(target=lambda: self.res.update(s=run_udp_ingest(
            sock, ep, run="r", journal=journal, quarantine=tmp_path / f"q-{name}",
            context=self.ctx, stop=self.stop, **kw)))
        self.thread.start()
        self.out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)

    def send(self, schedule):
        for data in schedule:  # back to back: the receiver finds several ready at once
            self.out.sendto(data, ("127.0.0.1", self.port))

    def messages(self, timeout_ms=1000):
        got = []
        while self.rx.poll(timeout_ms):
            head, batch = wire.decode(self.rx.recv_multipart(), {
                RAW_WORDS.name: RAW_WORDS, RAW_SPARSE.name: RAW_SPARSE})
            if head["kind"] == "stop":
                return got, head
            words = batch.column("word").to_numpy()
            if head["schema"] == RAW_SPARSE.name:  # the words whole again, from the contract
                words = SparseWords(head["n_words"], batch.column("index").to_numpy(),
                                    words).dense(head["first_word"], N_TDC)
            got.append((head["first_word"], words))
        return got, None

    def end(self):
        self.thread.join(timeout=60)
        assert not self.thread.is_alive()
        got, stop = self.messages()
        self.rx.close(linger=0)
        self.out.close()
        self.ctx.term()
        return self.res["s"], got, stop


def _chunks(journal):
    return [e for e in _entries(journal / "r.index.jsonl") if "first_word" in e]


def _by_cycle(pieces):
    out = {}
    for first, w in pieces:
        for k in range(0, w.size, N_TDC):
            c = (first + k) // N_TDC
            assert c not in out, f"cycle {c} twice"
            out[c] = w[k:k + N_TDC]
    return out


@pytest.mark.parametrize("sparse", [False, True])
def test_a_gap_and_a_reorder_inside_a_batch(tmp_path, sparse):
    """Datagrams sent back to back (several per receive), two swapped and one never sent:
    the swapped pair is put back inside its batch, the missing one ends the batch (a chunk
    holds consecutive cycles) and is counted; each chunk's index line names exactly the
    datagrams whose cycles it holds. Sent whole or sparse (then the journal's frames are
    made from the sparse form), the messages and the journal give back the words sent."""
    n, missing = 40, 21
    words, dgs = _stream(n, rng=5)
    order = [i for i in range(n) if i != missing]
    a = order.index(10)
    order[a], order[a + 1] = order[a + 1], order[a]  # 11 before 10
    ing = Ingest(tmp_path, "g", tmp_path / "j", reorder_window=8, flush_s=5.0,
                 sparse=sparse, compression="zstd-nohit")
    ing.send([dgs[i] for i in order])
    s, got, stop = ing.end()
    assert s.lost_datagrams == 1 and s.gap_cycles == CYC and s.duplicates == s.late == 0
    assert s.accepted == n - 1 and s.datagrams == n - 1 and dict(s.rejected) == {}
    chunks = _chunks(tmp_path / "j")
    # flush_s far off and the batch far from full: only the gap cuts the stream in two
    assert [(c["seq_lo"], c["seq"], c["datagrams"]) for c in chunks] == [
        (0, missing - 1, missing), (missing + 1, n - 1, n - 1 - missing)]
    for c in chunks:
        assert c["first_word"] == c["seq_lo"] * CYC * N_TDC
        assert c["words"] == c["datagrams"] * CYC * N_TDC
        assert c["seq_cycle"] == c["seq"] * CYC
    journaled = _by_cycle(read_range(tmp_path / "j", "r", 0, 10**12))
    sent = _by_cycle(got)
    want = sorted(set(range(n * CYC)) - set(range(missing * CYC, (missing + 1) * CYC)))
    assert sorted(journaled) == sorted(sent) == want
    for c in want:
        ref = words[c * N_TDC:(c + 1) * N_TDC]
        assert np.array_equal(journaled[c], ref) and np.array_equal(sent[c], ref)
    assert stop["lost_datagrams"] == 1 and stop["words"] == (n - 1) * CYC * N_TDC


def test_a_restart_between_batches_resumes_without_loss_or_double(tmp_path):
    """An ingest journals the stream's first 30 datagrams (in batches, 28 and 29 swapped)
    and ends; a second one on the same journal takes the run up from the chunks' sequence
    numbers: a stale datagram of the first one's last batch is refused as late, the rest is
    journaled once, and nothing is counted lost."""
    n, cut = 60, 30
    words, dgs = _stream(n, rng=6)
    first = list(range(cut))
    first[28], first[29] = 29, 28
    one = Ingest(tmp_path, "a", tmp_path / "j", idle_s=1, first_seq=0, flush_s=0.3)
    one.send([dgs[i] for i in first])
    s1, _, _ = one.end()
    assert s1.accepted == cut and s1.lost_datagrams == 0
    state = resume_state(tmp_path / "j", "r")
    assert state["taken"] == cut and (state["seq_lo"], state["seq_hi"]) == (0, cut - 1)
    assert state["anchor"] == (cut - 1, (cut - 1) * CYC)
    assert state["next_cycle"] == cut * CYC and state["gap_cycles"] == 0
    chunks_before = len(_chunks(tmp_path / "j"))

    two = Ingest(tmp_path, "b", tmp_path / "j", flush_s=5.0)
    two.send([dgs[cut - 1], *dgs[cut:]])  # the stale one first, then the rest
    s2, got, stop = two.end()
    assert s2.late == 1 and dict(s2.rejected) == {"late": 1}
    assert s2.accepted == n - cut and s2.duplicates == 0
    assert stop["lost_datagrams"] == 0 and stop["gap_cycles"] == 0
    assert len(_chunks(tmp_path / "j")) > chunks_before
    journaled = _by_cycle(read_range(tmp_path / "j", "r", 0, 10**12))  # (each cycle once)
    assert sorted(journaled) == list(range(n * CYC))
    assert np.array_equal(np.concatenate([journaled[c] for c in range(n * CYC)]), words)
    assert sorted(_by_cycle(got)) == list(range(cut * CYC, n * CYC))
    end = resume_state(tmp_path / "j", "r")
    assert end["taken"] == n and end["seq_hi"] == n - 1 and end["gap_cycles"] == 0


def test_a_partial_batch_is_sent_within_flush_s(tmp_path):
    """A few datagrams and then nothing (the stream paused, not ended): their words are
    journaled and passed on within flush_s, not held for a full batch or the run's end."""
    words, dgs = _stream(3, rng=7)
    ing = Ingest(tmp_path, "p", tmp_path / "j", idle_s=60, linger_s=60, flush_s=0.01,
                 first_seq=0)
    try:
        t0 = time.monotonic()
        ing.send(dgs[:2])
        got = []
        while sum(w.size for _, w in got) < 2 * CYC * N_TDC:
            assert ing.rx.poll(3000), "the partial batch was held back"
            head, batch = wire.decode(ing.rx.recv_multipart(), RAW_WORDS)
            got.append((head["first_word"], batch.column("word").to_numpy()))
        assert time.monotonic() - t0 < 2.0
        assert ing.thread.is_alive()  # (the run goes on)
        assert sum(c["words"] for c in _chunks(tmp_path / "j")) == 2 * CYC * N_TDC
        sent = _by_cycle(got)
        assert np.array_equal(np.concatenate([sent[c] for c in range(2 * CYC)]),
                              words[:2 * CYC * N_TDC])
    finally:
        ing.stop.set()
    s, _, _ = ing.end()
    assert s.accepted == 2 and s.lost_datagrams == 0
