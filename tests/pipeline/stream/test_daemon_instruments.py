"""A real instrument's file replayed through the daemon (``[source] kind = "file"``): the
live path's histograms equal the offline command's, worker killed or not, every record
accounted for."""

import os
import signal
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest
from click.testing import CliRunner

from pipeline.cli.app import cli
from pipeline.stream.topology import TopologyError, load_topology

DATA = Path(__file__).parents[2] / "data"  # tests/data: public files, see its README.md
T3 = DATA / "picoquant" / "hydraharp_v20_t3.ptu"
T2 = DATA / "picoquant" / "picoharp_v30_t2.ptu"
LINO = DATA / "linospad2" / "test_data_2212b.dat"


def topology(tmp_path, path, extra_source="", extra="", workers=1):
    text = f"""
[daemon]
state = "{tmp_path / 'state'}"
restarts = 3
[source]
kind = "file"
file = "{path}"
{extra_source}
[histogram]
workers = {workers}
[sink]
out = "{tmp_path / 'out'}"
{extra}
"""
    (tmp_path / "topo.toml").write_text(text)
    return tmp_path / "topo.toml"


def _daemon_helpers():
    # test_daemon.py's helpers, loaded by path (tests/ is not a package), as test_faults.py
    import importlib.util

    spec = importlib.util.spec_from_file_location(
        "_test_daemon_helpers", Path(__file__).with_name("test_daemon.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


run_daemon = _daemon_helpers().run_daemon


def offline_histograms(tmp_path, path, *args):
    out = tmp_path / "offline.parquet"
    res = CliRunner().invoke(cli, ["histogram", str(path), "--out", str(out), "-q", *args])
    assert res.exit_code == 0, res.output
    return pl.read_parquet(out).sort("tdc")


def live_histograms(tmp_path, run):
    return pl.read_parquet(tmp_path / "out" / "histograms" / "date=*" / f"run={run}" /
                           "*.parquet", hive_partitioning=True).sort("tdc")


def same(live, off):
    assert live["tdc"].to_list() == off["tdc"].to_list()
    assert np.array_equal(np.stack(live["counts"].to_numpy()),
                          np.stack(off["counts"].to_numpy()))
    for c in ("cycles", "n_hit", "instrument", "bin_width_ps"):
        assert live[c].to_list() == off[c].to_list(), c


def test_ptu_t3_file_live_equals_offline(tmp_path):
    res, _ = run_daemon(topology(tmp_path, T3), "hh")
    assert res["failed"] is None
    off = offline_histograms(tmp_path, T3)
    live = live_histograms(tmp_path, "hh")
    same(live, off)
    assert off["instrument"][0] == "picoquant-t3" and off["n_hit"].sum() > 0
    acc = res["accounting"]
    records = (T3.stat().st_size - _data_offset(T3)) // 4
    assert acc["words_in"] == records and acc["balanced"], acc
    assert acc["classes"]["photons"] == int(off["n_hit"].sum())
    # the sink's file lost (a sink killed with the message in flight): the end of the run
    # recomputes the one measurement from the journal with the same accumulator
    from pipeline.stream.reconcile import reconcile

    for p in (tmp_path / "out" / "histograms").rglob("*.parquet"):
        p.unlink()
    rec = reconcile(load_topology(tmp_path / "topo.toml", "hh"))
    assert rec["recomputed"] == [[0, 0]]
    same(live_histograms(tmp_path, "hh"), off)


def _data_offset(path):
    from pipeline.io.ptu import read_header

    return read_header(path).data_offset


def test_sigkill_of_the_worker_mid_file_changes_nothing(tmp_path):
    records = (T3.stat().st_size - _data_offset(T3)) // 4

    def kill(sup):
        deadline = time.time() + 60
        while time.time() < deadline:
            p = sup.by_name["histogram-0"].popen
            if p is not None and sup.metrics.get("source", {}).get("words", 0) > records // 3 \
                    and p.poll() is None:
                os.kill(p.pid, signal.SIGKILL)
                return
            time.sleep(0.02)
        raise AssertionError("the source never got going")

    res, sup = run_daemon(topology(tmp_path, T3, f"rate = {records / 4:.0f}"), "hk", kill)
    assert res["restarts"] == {"histogram-0": 1}
    same(live_histograms(tmp_path, "hk"), offline_histograms(tmp_path, T3))
    assert res["accounting"]["balanced"]


def test_linospad2_file_live_equals_offline(tmp_path):
    res, _ = run_daemon(topology(tmp_path, LINO, 'format = "linospad2"'), "lino")
    assert res["failed"] is None
    off = offline_histograms(tmp_path, LINO, "--format", "linospad2")
    same(live_histograms(tmp_path, "lino"), off)
    acc = res["accounting"]
    assert acc["balanced"] and acc["words_in"] == LINO.stat().st_size // 4


def test_file_source_refusals(tmp_path):
    with pytest.raises(TopologyError, match="one worker"):
        load_topology(topology(tmp_path, T3, workers=2))
    with pytest.raises(TopologyError, match=r"no \[range\]"):
        load_topology(topology(tmp_path, T3, extra='[range]\ncalibration = "x"'))
    with pytest.raises(TopologyError, match="T2 records"):
        load_topology(topology(tmp_path, T2))
    with pytest.raises(TopologyError, match="not found"):
        load_topology(topology(tmp_path, tmp_path / "missing.ptu"))
    (tmp_path / "junk.bin").write_bytes(os.urandom(1000))
    with pytest.raises(TopologyError, match="give --format"):
        load_topology(topology(tmp_path, tmp_path / "junk.bin"))
