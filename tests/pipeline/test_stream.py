"""Real ZeroMQ stages in subprocesses, and the runner's handling of bad messages."""

import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import polars as pl
import zmq

from pipeline import wire
from pipeline.simulate import make_simulator
from pipeline.stage import run_stage
from schemas import RAW_WORDS
from stages.histogram import HistogramAccumulator
from stages.stream import HistogramCore

SCENES = Path(__file__).parents[2] / "scenes"


def test_three_processes_give_the_offline_histograms(tmp_path):
    """source-sim -> histogram -> sink over ipc://, each a real process, against the same
    words histogrammed in-process."""
    ep_h, ep_s = f"ipc://{tmp_path}/h", f"ipc://{tmp_path}/s"
    cli = [sys.executable, "-m", "pipeline.cli", "stage"]
    procs = [
        subprocess.Popen(cli + ["sink", "--pull", ep_s, "--out", str(tmp_path / "data")]),
        subprocess.Popen(cli + ["histogram", "--pull", ep_h, "--push", ep_s]),
        subprocess.Popen(cli + ["source-sim", str(SCENES / "street.toml"), "--cycles",
                                "6000", "--push", ep_h, "--seed", "3", "--run", "r1"]),
    ]
    for p in procs:
        assert p.wait(timeout=120) == 0
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
    assert core.acc.snapshot().words == 8
    assert len(list((tmp_path / "q").glob("*.json"))) == 4
