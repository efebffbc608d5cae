"""The daemon's sink writes each ranges message as a point cloud too (``[sink] pointcloud``,
``geometry``; issue 35), and the topology checks the pair."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest

from pipeline.io.geometry import load_geometry
from pipeline.stream.stage import ParquetSink
from pipeline.stream.topology import TopologyError, load_topology
from schemas.outputs import RANGES


def _ranges(n=9):
    return pa.table({
        "measurement": ["m"] * n, "tdc": pa.array(range(n), pa.uint16()),
        "distance_m": np.linspace(0.1, 0.3, n), "sigma_m": np.full(n, 1e-3),
        "fwhm_m": np.full(n, 0.04), "signal_counts": np.full(n, 100.0),
        "background_per_bin": np.zeros(n), "detected": [True] * (n - 1) + [False],
        "estimator": ["ml"] * n, "return_index": pa.array([0] * n, pa.uint8()),
        "flag": [""] * n}, schema=RANGES.schema)


@pytest.mark.parametrize("fmt", ["ply", "mcap"])
def test_sink_writes_a_cloud_per_ranges_message(tmp_path, fmt):
    sink = ParquetSink(tmp_path, cloud=(fmt, load_geometry("tmf8820")))
    header = {"schema": RANGES.name, "run": "r1", "seq": 7, "date": "2026-12-04",
              "tdc_range": [0, 9]}
    sink.process(header, _ranges().to_batches()[0])
    (cloud,) = (tmp_path / "pointcloud").rglob(f"*.{fmt}")
    assert cloud.name == f"part-000007-t000.{fmt}" and "run=r1" in str(cloud)
    if fmt == "ply":
        from plyfile import PlyData

        v = PlyData.read(str(cloud))["vertex"]
        assert len(v.data) == 8 and np.allclose(np.sort(v["x"])[-1], 0.3 * 7 / 8, atol=0.1)
    else:
        from mcap.reader import make_reader
        from mcap_ros2.decoder import DecoderFactory

        with open(cloud, "rb") as fh:
            (msg,) = [m for *_, m in make_reader(
                fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
        assert (msg.height, msg.width, msg.is_dense) == (3, 3, False)


def test_topology_checks_the_pair(tmp_path):
    def load(**sink):
        return load_topology(None, overrides={"daemon": {"state": str(tmp_path / "s")},
                                              "sink": {"out": str(tmp_path / "o"), **sink}})

    with pytest.raises(TopologyError, match="pointcloud and geometry go together"):
        load(pointcloud="las")
    with pytest.raises(TopologyError, match="not a shipped geometry"):
        load(pointcloud="las", geometry="nope")
    with pytest.raises(TopologyError, match="pointcloud"):
        load(pointcloud="xyz", geometry="tmf8820")
    from pipeline.stream.daemon import _cloud_args

    assert _cloud_args(load(pointcloud="mcap", geometry="tmf8820").sink) == [
        "--pointcloud", "mcap", "--geometry", "tmf8820"]
    assert _cloud_args(load().sink) == []


def test_the_view_lays_the_maps_out_as_the_geometry(tmp_path):
    from pipeline.stream.sidecar import view_args
    from pipeline.view.sensor import geometry_xy

    x, y, layout = geometry_xy([0, 4, 8, 9], load_geometry("tmf8820"))
    assert layout == (3, 3)
    assert x[:3].tolist() == [0, 1, 2] and y[:3].tolist() == [0, 1, 2]
    assert np.isnan(x[3]) and np.isnan(y[3])     # the reference channel has no pixel
    topo = load_topology(None, "r", overrides={
        "daemon": {"state": str(tmp_path / "s")}, "sink": {"out": str(tmp_path / "o")},
        "view": {"geometry": "tmf8820"}})
    assert view_args(topo)[-2:] == ["--geometry", "tmf8820"]


def test_the_daemon_refuses_spatial_ranging(tmp_path):
    """`[range] spatial = true` is refused in one line (exit 2), not ignored: the range
    stage's histograms are the chip's, each TDC on its own INL time axis, and spatial
    ranging needs one time axis (docs/ranging.md)."""
    import subprocess
    import sys

    cal = tmp_path / "cal"
    cal.mkdir()
    (cal / "tdc.parquet").touch()
    over = {"daemon": {"state": str(tmp_path / "s")}, "sink": {"out": str(tmp_path / "o")},
            "range": {"calibration": str(cal)}}
    with pytest.raises(TopologyError, match=r"\[range\] spatial = true: not in the daemon"):
        load_topology(None, overrides={**over, "range": {"calibration": str(cal),
                                                         "spatial": True}})
    assert load_topology(None, overrides=over).range is not None   # without it: fine
    scene = tmp_path / "small.toml"
    scene.write_text("")
    topo = tmp_path / "t.toml"
    topo.write_text(f"[source]\nkind = 'sim'\nscene = '{scene}'\n[daemon]\nstate = "
                    f"'{tmp_path / 's'}'\n[sink]\nout = '{tmp_path / 'o'}'\n[range]\n"
                    f"calibration = '{cal}'\nspatial = true\n")
    p = subprocess.run([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                        str(topo)], capture_output=True, text=True)
    assert p.returncode == 2
    lines = [x for x in p.stderr.splitlines() if x.strip()]
    assert any("[range] spatial = true" in x and "INL time axis" in x for x in lines), lines
    assert "Traceback" not in p.stderr
