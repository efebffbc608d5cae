"""The daemon classifies a capture's words exactly as the offline command does.

Without a calibration ``tcspc histogram`` estimates the artifact bounds from the capture;
the daemon replaying the same capture must remove the same artifacts (it once removed
none, counted them as hits and reported the run balanced)."""

import json

import numpy as np
import polars as pl
import pytest

from pipeline.io.capture import Capture, CaptureWriter
from pipeline.offline.datapath import histogram_capture
from pipeline.stream.daemon import Supervisor
from pipeline.stream.topology import load_topology
from schemas import WORD_CLASSES
from stages.histogram import HistogramAccumulator
from stages.testpattern import pattern_words

N, CYCLES, MC = 16, 30_000, 10_000


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    """A pattern capture with every word class, artifacts among them (the generator's
    own truth, independent of the estimate)."""
    d = tmp_path_factory.mktemp("cap")
    words, truth = pattern_words(CYCLES, N, hit_prob=0.3, rng=7)
    assert truth.class_counts[WORD_CLASSES.index("artifact")].sum() > 100
    with CaptureWriter(d / "cap", N, kind="pattern") as w:
        w.write(words)
    return d / "cap", truth


def _run(tmp_path, cap, extra=""):
    topo = tmp_path / "topo.toml"
    topo.write_text(f"""
[daemon]
state = "{tmp_path / 'state'}"
[source]
kind = "capture"
capture = "{cap}"
[histogram]
workers = 2
measurement_cycles = {MC}
{extra}
[sink]
out = "{tmp_path / 'out'}"
""")
    lines = []
    sup = Supervisor(load_topology(topo, "b"), log=lines.append)
    res = sup.run()
    assert res["failed"] is None, res
    h = pl.read_parquet(tmp_path / "out" / "histograms" / "date=*" / "run=b" / "*.parquet",
                        hive_partitioning=True)
    return res, h, lines


def test_daemon_without_calibration_classifies_as_the_offline_command(tmp_path, capture):
    cap_path, truth = capture
    cap = Capture(cap_path)
    state, bounds = histogram_capture(cap)  # what `tcspc histogram` computes
    res, h, lines = _run(tmp_path, cap_path)
    assert any("estimating the artifact bounds" in m for m in lines)  # said at start
    acc = res["accounting"]
    assert acc["balanced"]
    assert acc["artifact_bounds"].startswith("estimated:")
    # the run's classes are the offline command's, artifacts removed
    assert acc["classes"] == state.totals()
    assert acc["classes"]["artifact"] > 100
    # each measurement and TDC: the offline accumulator with the offline bounds
    words = np.fromfile(cap.bin_path, ">u4").astype(np.uint32)  # (stored big-endian)
    for k in range(CYCLES // MC):
        ref = HistogramAccumulator(N, bounds)
        ref.update(words[k * MC * N:(k + 1) * MC * N], 0)
        m = h.filter(pl.col("measurement") == f"b-m{k:06d}").sort("tdc")
        assert np.array_equal(np.stack(m["counts"].to_numpy()), ref.snapshot().hits)
        assert m["n_artifact"].to_list() == ref.snapshot().class_counts[
            WORD_CLASSES.index("artifact")].tolist()
    saved = json.loads((tmp_path / "state" / "bounds" / "b.json").read_text())
    assert saved["n_min"] == bounds.n_min.tolist() and saved["n_max"] == bounds.n_max.tolist()
