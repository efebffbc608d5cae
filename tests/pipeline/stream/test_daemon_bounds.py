"""The daemon classifies a capture's words exactly as the offline command does.

Without a calibration ``tcspc histogram`` estimates the artifact bounds from the capture;
the daemon replaying the same capture must remove the same artifacts (it once removed
none, counted them as hits and reported the run balanced)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.io.capture import Capture, CaptureWriter
from pipeline.offline.datapath import histogram_capture
from pipeline.stream.bounds import COUNTED, bounds_file, ensure_bounds, histogram_bounds
from pipeline.stream.daemon import Supervisor
from pipeline.stream.topology import TopologyError, load_topology
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


SMALL = Path(__file__).parents[3] / "scenes" / "small16.toml"
SOURCES = {"sim": f'kind = "sim"\nscene = "{SMALL}"\ncycles = 1000',
           "udp": 'kind = "udp"\nbind = "127.0.0.1:9000"\nn_tdc = 16'}


def _topo(tmp_path, kind, histogram=""):
    path = tmp_path / "topo.toml"
    path.write_text(f'[daemon]\nstate = "{tmp_path / "state"}"\n[source]\n{SOURCES[kind]}\n'
                    f'[histogram]\nworkers = 1\n{histogram}\n[sink]\nout = "{tmp_path / "o"}"\n')
    return path


@pytest.mark.parametrize("kind", ["sim", "udp"])
def test_a_stream_without_words_to_estimate_from_needs_a_calibration_or_the_opt_in(tmp_path,
                                                                                     kind):
    """A sim or udp source has no words before it starts: without a calibration its
    artifacts would be counted as hits. Refused at the door, one line naming both ways."""
    path = _topo(tmp_path, kind)
    with pytest.raises(TopologyError) as exc:
        load_topology(path)
    (line,) = str(exc.value).splitlines()
    assert line.startswith(f"{path} [histogram]: a {kind} source needs calibration = DIR")
    assert 'artifacts = "count-as-hits"' in line
    # the explicit opt-in: no bounds, and the run says so
    topo = load_topology(_topo(tmp_path, kind, 'artifacts = "count-as-hits"'), "r")
    assert bounds_file(topo) is None and histogram_bounds(topo) is None
    assert ensure_bounds(topo, log=lambda m: None) == COUNTED
    with pytest.raises(TopologyError, match="artifacts = 'hits'"):  # one value only
        load_topology(_topo(tmp_path, kind, 'artifacts = "hits"'))


def test_a_calibration_overrides_the_opt_in(tmp_path, caldir):
    """With a calibration the bounds are the calibration's, opt-in or not."""
    topo = load_topology(_topo(tmp_path, "sim", f'calibration = "{caldir}"\n'
                               'artifacts = "count-as-hits"'), "r")
    assert ensure_bounds(topo, log=lambda m: None).startswith("calibration:")
    assert histogram_bounds(topo).n_tdc == 16


def test_the_daemon_refuses_it_with_exit_2_and_starts_nothing(tmp_path):
    path = _topo(tmp_path, "udp")
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", "daemon", "--config", path],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert "needs calibration = DIR" in r.stderr and "count-as-hits" in r.stderr
    assert not (tmp_path / "state").exists()
