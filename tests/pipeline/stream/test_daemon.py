"""The daemon: real stage processes under the supervisor, killed and restarted."""

import json
import os
import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.stream.bounds import COUNTED
from pipeline.stream.daemon import Supervisor
from pipeline.stream.journal import read_range
from pipeline.stream.topology import TopologyError, load_topology
from stages.histogram import HistogramAccumulator

N = 16
SCENE = (Path(__file__).parents[3] / "scenes" / "small16.toml").read_text()


def topology(tmp_path, caldir=None, cycles=60_000, rate=None, workers=2, **source):
    (tmp_path / "small.toml").write_text(SCENE)
    text = f"""
[daemon]
state = "{tmp_path / 'state'}"
restarts = 3
[source]
kind = "sim"
scene = "{tmp_path / 'small.toml'}"
cycles = {cycles}
seed = 5
{f'rate = {rate}' if rate else ''}
[histogram]
workers = {workers}
measurement_cycles = 10000
artifacts = "count-as-hits"
[sink]
out = "{tmp_path / 'out'}"
"""
    if caldir:
        text += f'[range]\ncalibration = "{caldir}"\n'
    (tmp_path / "topo.toml").write_text(text)
    return tmp_path / "topo.toml"


def offline(state: Path, run: str, cycles: int, mc: int = 10_000) -> list[np.ndarray]:
    """Each measurement's histograms computed straight from the journal."""
    words = np.concatenate([w for _, w in read_range(state / "journal", run, 0, 10**12)])
    out = []
    for k in range(-(-cycles // mc)):
        acc = HistogramAccumulator(N)
        acc.update(words[k * mc * N:(k + 1) * mc * N], 0)
        out.append(acc.snapshot().hits)
    return out


def dataset(out: Path, schema: str, run: str) -> pl.DataFrame:
    return pl.read_parquet(out / schema / "date=*" / f"run={run}" / "*.parquet",
                           hive_partitioning=True)


def check_histograms(tmp_path, run, cycles):
    ref = offline(tmp_path / "state", run, cycles)
    h = dataset(tmp_path / "out", "histograms", run)
    assert h.height == len(ref) * N  # each measurement and TDC once
    for k, hits in enumerate(ref):
        m = h.filter(pl.col("measurement") == f"{run}-m{k:06d}").sort("tdc")
        assert m["tdc"].to_list() == list(range(N))
        assert np.array_equal(np.stack(m["counts"].to_numpy()), hits), f"measurement {k}"
    return h


def run_daemon(topo_path, run, during=None):
    topo = load_topology(topo_path, run)
    sup = Supervisor(topo, log=lambda m: None)
    result = {}
    t = threading.Thread(target=lambda: result.update(sup.run()))
    t.start()
    if during:
        during(sup)
    t.join(timeout=240)
    assert not t.is_alive(), "daemon did not finish"
    return result, sup


def _kill_when_running(sup, name, after_words):
    """SIGKILL stage ``name`` once the source has sent ``after_words``."""
    deadline = time.time() + 60
    while time.time() < deadline:
        src = sup.metrics.get("source", {})
        p = sup.by_name[name].popen
        if p is not None and src.get("words", 0) >= after_words and p.poll() is None:
            os.kill(p.pid, signal.SIGKILL)
            return
        time.sleep(0.05)
    raise AssertionError("the source never got going")


def test_daemon_end_to_end_with_ranges(tmp_path, caldir):
    res, sup = run_daemon(topology(tmp_path, caldir, cycles=45_000), "e2e")
    assert res["failed"] is None and res["restarts"] == {}
    check_histograms(tmp_path, "e2e", 45_000)
    r = dataset(tmp_path / "out", "ranges", "e2e")
    r = r.filter(pl.col("return_index") == 0)  # (a row per return: each TDC's strongest)
    assert r.height == 5 * N and r["detected"].all()
    assert (r["distance_m"] - 1.5).abs().median() < 0.05
    acc = res["accounting"]
    assert acc["balanced"] and acc["words_in"] == 45_000 * N
    assert acc["artifact_bounds"] == COUNTED  # the topology's opt-in, in the accounting
    assert acc["measurements_files"] == 5 * 2  # 4 whole + 1 partial, 2 TDC ranges
    st = json.loads((tmp_path / "state" / "status.json").read_text())
    assert st["state"] == "finished"
    assert set(st["stages"]) == {"source", "histogram-0", "histogram-1", "range", "sink"}
    assert st["stages"]["histogram-0"]["words_total"] == 45_000 * N // 2  # heartbeats
    from click.testing import CliRunner

    from pipeline.cli.app import cli

    out = CliRunner().invoke(cli, ["status", "--state", str(tmp_path / "state")])
    assert out.exit_code == 0, out.output
    for name in ("source", "histogram-1", "range", "sink", "finished"):
        assert name in out.output


def test_sigkill_of_a_histogram_worker_changes_nothing(tmp_path):
    cycles = 200_000
    res, sup = run_daemon(topology(tmp_path, cycles=cycles, rate=1.5e6), "k1",
                          lambda s: _kill_when_running(s, "histogram-1", 600_000))
    assert res["restarts"] == {"histogram-1": 1}
    assert sup.by_name["histogram-1"].exit_codes[0] == -signal.SIGKILL
    check_histograms(tmp_path, "k1", cycles)
    assert res["accounting"]["balanced"]


def test_sigkill_of_the_sink_and_the_source_is_reconciled(tmp_path, caldir):
    cycles = 120_000

    def chaos(sup):
        _kill_when_running(sup, "sink", 400_000)
        _kill_when_running(sup, "source", 900_000)

    res, sup = run_daemon(topology(tmp_path, caldir, cycles=cycles, rate=1.5e6), "k2", chaos)
    assert res["restarts"] == {"sink": 1, "source": 1}
    check_histograms(tmp_path, "k2", cycles)
    r = dataset(tmp_path / "out", "ranges", "k2").filter(pl.col("return_index") == 0)
    assert r.height == 12 * N  # every measurement ranged once, some recomputed
    assert res["accounting"]["balanced"]


def test_udp_daemon_accounts_for_corrupted_datagrams(tmp_path):
    from pipeline.stream import datagram
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
""")

    def feed(sup):
        deadline = time.time() + 60
        while "source" not in sup.metrics and time.time() < deadline:
            time.sleep(0.1)  # the ingest is listening once it beats
        words, _ = pattern_words(40 * 32, 128, hit_prob=0.1, malformed_prob=0.01, rng=2)
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        rng = np.random.default_rng(0)
        for i in range(40):
            if i == 7:
                continue  # lost on the way
            chunk = words[i * 32 * 128:(i + 1) * 32 * 128]
            out.sendto(datagram.encode(chunk, i, i * 32, 128, 140_000, last=(i == 39)),
                       ("127.0.0.1", port))
            if i % 5 == 0:
                junk = datagram.encode(chunk, 99, 0, 128, 140_000)
                out.sendto(b"NOPE" + junk[4:], ("127.0.0.1", port))           # bad magic
                out.sendto(junk[:100], ("127.0.0.1", port))                   # truncated
                out.sendto(rng.bytes(64), ("127.0.0.1", port))                # garbage
            time.sleep(0.003)
        out.close()

    res, sup = run_daemon(tmp_path / "udp.toml", "u", feed)
    acc = res["accounting"]
    assert acc["words_in"] == 39 * 32 * 128 and acc["balanced"]
    assert acc["artifact_bounds"] == COUNTED
    assert acc["lost_datagrams"] == 1 and acc["words_in_gaps"] == 32 * 128
    assert acc["classes"]["malformed"] > 0
    rejected = acc["rejected_messages"]["source"]
    assert sum(rejected.values()) == 8 * 3 and rejected["bad_magic"] >= 8
    assert len(list((tmp_path / "state" / "quarantine" / "u" / "ingest").glob("*.bin"))) == 24


def test_topology_errors_name_the_problem(tmp_path):
    bad = tmp_path / "t.toml"
    bad.write_text("[source]\nkind = 'sim'\n")
    with pytest.raises(TopologyError, match="needs 'scene'"):
        load_topology(bad)
    bad.write_text("[source]\nkind = 'tape'\n")
    with pytest.raises(TopologyError, match="use one of"):
        load_topology(bad)
    bad.write_text(f"[source]\nkind='sim'\nscene='{topology(tmp_path).parent / 'small.toml'}'"
                   "\n[histogram]\nworkerz = 2\n")
    with pytest.raises(TopologyError, match="unknown keys"):
        load_topology(bad)
    bad.write_text(f"[source]\nkind='sim'\nscene='{tmp_path / 'small.toml'}'\n"
                   "[range]\ncalibration = '/nope'\n")
    with pytest.raises(TopologyError, match="not a calibration directory"):
        load_topology(bad)


def test_a_reset_peak_below_the_calibrated_window_is_not_a_target(caldir):
    """A calibration's LSB too small for this light puts its x_T above the real reset
    peak; the last populated code must bound the search so the peak is not taken for a
    target (it once was, 5 m before the window)."""
    from pipeline.io.caldir import load_calibration
    from pipeline.offline.ranging import range_state
    from schemas.constants import N_CLASSES
    from stages.histogram import HistogramState

    rng = np.random.default_rng(1)
    cycles = 20_000
    calib = load_calibration(caldir)
    x_t = 80e-9 / calib.lsb_s(0.05)[0]
    hits = np.zeros((N, 512), np.uint64)
    for i in range(N):
        top = int(x_t[i]) - 15                      # the real reset peak, 15 codes lower
        hits[i, 1:top] = rng.poisson(2.0, top - 1)  # background only: no target
        hits[i, top - 1:top + 2] = (76, 500, 54)  # the TDC jitter spreads it
    cc = np.zeros((N_CLASSES, N), np.uint64)
    cc[0] = hits.sum(1)
    cc[1] = cycles - cc[0]
    est, d, _, _ = range_state(HistogramState(hits, cc, int(cc.sum())), calib, 80e-9,
                               140e-9)
    assert not est.detected.any(), d[est.detected]


@pytest.mark.parametrize("enc, ext", [("zstd-nohit", ".bin.nhz"), ("zstd", ".bin.zst"),
                                      (None, ".bin")])
def test_journal_retention_prunes_only_what_every_worker_is_past(tmp_path, enc, ext):
    from pipeline.stream.journal import (
        IndexSpans,
        JournalWriter,
        prune,
        pruned_words,
        segment_spans,
    )

    w = JournalWriter(tmp_path, "r", 4, 140.0, segment_words=1000, compression=enc)
    for i in range(10):
        w.append(i * 400, np.arange(400, dtype=np.uint32))
    spans = IndexSpans(tmp_path, "r")
    assert spans.update() == segment_spans(tmp_path, "r")
    seg = 4 * 1000  # bytes per full segment
    # consumers are past word 1600: segments ending there or before may go, and no more
    gone = prune(tmp_path, "r", keep_bytes=0, consumed_word=1600, spans=spans.update())
    assert [p.name for p in gone] == ["r-000000" + ext, "r-000001" + ext]
    assert pruned_words(tmp_path, "r", 0, 4000) == 1600
    assert list(read_range(tmp_path, "r", 1600, 2000))[0][0] == 1600  # the rest is there
    w.close()
    assert prune(tmp_path, "r", keep_bytes=10 * seg, consumed_word=10**9) == []  # under


def test_sigterm_to_the_daemon_ends_the_run_cleanly(tmp_path):
    """`tcspc daemon` under SIGTERM: the source ends the run after its batch in hand, the
    stages drain, and the words that entered are all accounted for; the run is
    interrupted (exit 128 + SIGTERM), not finished: it is resumable."""
    import subprocess
    import sys

    topo = topology(tmp_path, cycles=2_000_000, rate=2e6)
    p = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                          str(topo), "--run", "t"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 60
    status = tmp_path / "state" / "status.json"
    while time.time() < deadline:  # until words flow
        try:
            if json.loads(status.read_text())["stages"]["source"].get("words", 0) > 2e6:
                break
        except (OSError, ValueError, KeyError):
            pass
        time.sleep(0.2)
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=120)
    assert p.returncode == 128 + signal.SIGTERM, err
    res = json.loads(out)
    assert res["state"] == "interrupted" and res["interrupted"] == "SIGTERM"
    acc = res["accounting"]
    assert acc["balanced"] and 2e6 < acc["words_in"] < 2_000_000 * N
    assert res["restarts"] == {}


def test_the_documented_queries_run_on_a_daemon_dataset(tmp_path, caldir):
    """docs/outputs.md's Polars queries of the daemon's datasets, and README's, run on a
    real one."""
    import re

    run_daemon(topology(tmp_path, caldir, cycles=30_000), "q")
    root = Path(__file__).parents[3]

    def blocks(name):
        return re.findall(r"```python\n(.*?)```", (root / name).read_text(), re.S)

    def run(block, ns):
        code = block.replace("data/stream", str(tmp_path / "out"))
        code = code.replace("pl.date(2026, 11, 21)", "pl.col('date').max()")
        exec(compile(code, "docs", "exec"), ns)

    docs = blocks("docs/outputs.md")
    first = next(i for i, b in enumerate(docs) if "data/stream" in b)
    ns: dict = {}
    for block in docs[first:first + 2]:  # the queries, then the per-hour one using h
        run(block, ns)
    readme = [b for b in blocks("README.md") if "data/stream" in b]
    assert readme, "README shows no query of the daemon's datasets"
    for block in readme:
        run(block, {})
    assert "h" in ns and "r" in ns


def test_retention_waits_for_the_sink_not_only_the_workers(tmp_path):
    """A worker that checkpointed past a measurement has only sent it; a sink (or range)
    killed with it in flight loses it and the reconciliation recomputes it from the
    journal. Seen in a 54-minute soak with kills and journal_keep_gb: 19.2 M words
    unrecoverable because their segments were pruned before the sink wrote them."""
    from pipeline.stream.stage import save_checkpoint
    from pipeline.stream.topology import tdc_ranges

    topo = load_topology(topology(tmp_path, workers=2), "ret")
    sup = Supervisor(topo, log=lambda m: None)
    mc = topo.histogram["measurement_cycles"]
    for i, (a, b) in enumerate(tdc_ranges(topo)):  # both workers past measurement 5
        save_checkpoint(topo.state / "checkpoints" / "ret" / f"histogram-{i}.npz",
                        {"counters": np.array([0, -1, 6 * mc * (b - a), 6, 0], np.int64)})
    assert sup._consumed_word() == 0  # nothing is on disk yet: nothing may be pruned
    out = Path(topo.sink["out"]) / "histograms" / f"date={topo.date}" / "run=ret"
    out.mkdir(parents=True)
    for k in range(4):
        for a, _ in tdc_ranges(topo):
            if (k, a) != (2, 8):  # measurement 2 of the second range is still in flight
                (out / f"part-{k:06d}-t{a:03d}.parquet").write_bytes(b"")
    assert sup._consumed_word() == 2 * mc * N  # measurements 0 and 1 are durable
    (out / f"part-{2:06d}-t{8:03d}.parquet").write_bytes(b"")
    assert sup._consumed_word() == 4 * mc * N
