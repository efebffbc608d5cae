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


EDGE16 = """name = "edge16"
[sensor]
n_pixels = 16
[gate]
t_laser_win_ns = 140.0
delay_ns = 100.0
[[targets]]
pixels = [0, 7]
distance_m = 1.5
reflectivity = 0.0002
surface = "mirror"
[[targets]]
pixels = [8, 15]
distance_m = 2.5
reflectivity = 0.0002
surface = "mirror"
[[ambient]]
kind = "lux"
lux = 800.0
"""
GRID16 = """name = "grid16"
[grid]
rows = 4
cols = 4
fov_h_deg = 10.0
fov_v_deg = 10.0
"""


def _edge_topology(tmp_path, caldir, histogram: str, rest: str):
    """The edge scene's simulated capture (seed 4, 6000 cycles), its 4 x 4 geometry, and a
    daemon topology on it: a capture source, ``histogram`` (the [histogram] table's lines
    besides the calibration), then ``rest`` ([range] on). Returns (topology, capture,
    geometry)."""
    from pipeline.cli import cli

    (tmp_path / "edge16.toml").write_text(EDGE16)
    geom = tmp_path / "grid16.toml"
    geom.write_text(GRID16)
    cap = tmp_path / "cap"
    cli.main(args=["simulate", str(tmp_path / "edge16.toml"), "--cycles", "6000", "--out",
                   str(cap), "--seed", "4", "-q"], standalone_mode=False)
    topo = tmp_path / "topo.toml"
    topo.write_text(f"""
[daemon]
state = "{tmp_path / 'state'}"
[source]
kind = "capture"
capture = "{cap}"
[histogram]
{histogram}
calibration = "{caldir}"
""" + rest.format(caldir=caldir, geom=geom, out=tmp_path / "out"))
    return topo, cap, geom


@pytest.mark.parametrize("workers", [1, 3])
def test_the_daemon_ranges_with_the_neighbours_as_the_offline_command(tmp_path, caldir,
                                                                      workers):
    """`[range] spatial = true`: a simulated capture of 16 pixels as a 4 x 4 image, a depth
    edge between its top and bottom halves (1.5 and 2.5 m, few photons), run through the
    daemon (capture source, one worker or three, whose TDC ranges 0..4, 5..10, 11..15 cut
    the image's rows, the range stage gathering their parts and ranging with the
    neighbours, the sink writing point clouds) gives the ranges `tcspc range CAP
    --calibration C --spatial --geometry G` writes for the same capture, and the truth
    within 3 sigma on every pixel (detected or not), the edge kept."""
    import polars as pl

    from pipeline.cli import cli
    from pipeline.stream.daemon import Supervisor

    topo, cap, geom = _edge_topology(tmp_path, caldir, f"workers = {workers}", """
[range]
calibration = "{caldir}"
spatial = true
max_returns = 2
[sink]
out = "{out}"
pointcloud = "ply"
geometry = "{geom}"
""")
    res = Supervisor(load_topology(topo, "sp"), log=lambda m: None).run()
    assert res["failed"] is None, res
    assert res["state"] == "finished", res["problems"]
    assert res["accounting"]["spatial_incomplete_frames"] == 0
    parts = sorted((tmp_path / "out" / "ranges").rglob("*.parquet"))
    assert len(parts) == workers  # (one file a worker's part, beside its histograms)
    live = pl.read_parquet(tmp_path / "out" / "ranges" / "date=*" / "run=sp" / "*.parquet")
    cli.main(args=["range", str(cap), "--calibration", str(caldir), "--spatial",
                   "--geometry", str(geom), "--out", str(tmp_path / "off.parquet"), "-q"],
             standalone_mode=False)
    off = pl.read_parquet(tmp_path / "off.parquet")
    assert live.height == off.height >= 16
    assert set(live["estimator"]) == {"spatial"}
    on = ["tdc", "return_index"]
    both = live.sort(on).join(off.sort(on), on=on, suffix="_off")
    assert both.height == live.height
    assert (both["detected"] == both["detected_off"]).all()
    d = (both["distance_m"] - both["distance_m_off"]).abs()
    assert (d <= 0.1 * both["sigma_m"]).all(), both.select(on + ["distance_m", "distance_m_off"])
    first = live.filter(pl.col("return_index") == 0).sort("tdc")
    # (at these few photons `ml` alone detects 6-12 of the 16 and puts one or two 40
    # sigma off on 2 of 3 seeds; here 13-15 detected, every pixel within 3 sigma)
    assert first.height == 16 and first["detected"].sum() >= 13
    truth = np.where(first["tdc"].to_numpy() < 8, 1.5, 2.5)
    z = np.abs(first["distance_m"].to_numpy() - truth) / first["sigma_m"].to_numpy()
    assert z.max() < 3, z
    from plyfile import PlyData

    plys = sorted((tmp_path / "out" / "pointcloud").rglob("*.ply"))
    assert len(plys) == workers
    v = np.concatenate([PlyData.read(str(p))["vertex"].data for p in plys])
    assert len(v) == live["detected"].sum()
    # the offline ranges exported with the same geometry: the same points
    cli.main(args=["export", str(tmp_path / "off.parquet"), "--geometry", str(geom),
                   "--out", str(tmp_path / "off.ply"), "-q"], standalone_mode=False)
    w = PlyData.read(str(tmp_path / "off.ply"))["vertex"]

    def xyz(p):  # the points, in one order
        a = np.stack([p["x"], p["y"], p["z"]], 1).astype(np.float64)
        return a[np.lexsort(np.round(a, 3).T[::-1])]

    np.testing.assert_allclose(xyz(v), xyz(w), atol=1e-3)
    # the ranges lost: `tcspc reconcile` rebuilds them from the journal, spatially too
    from pipeline.stream.daemon import reconcile_offline

    # (one part's: the whole frame is gathered from the journal and ranged again)
    parts[-1].unlink()
    rec = reconcile_offline(load_topology(topo, "sp"))
    again = pl.read_parquet(tmp_path / "out" / "ranges" / "date=*" / "run=sp" / "*.parquet")
    assert again.sort(on).equals(live.sort(on))
    assert rec["reconciled"]["spatial_reranged"] == [0], rec["reconciled"]
    if workers == 1:
        return
    # a part the range stage ranged in a frame without another part (a worker's part that
    # did not come: its file says which TDCs it lacked): ranged again whole, from the
    # histograms the datasets hold
    import pyarrow.parquet as pq

    t = pq.read_table(parts[0])
    pq.write_table(t.set_column(t.column_names.index("distance_m"), "distance_m",
                                pa.array(np.full(t.num_rows, 9.0))).replace_schema_metadata(
        {**t.schema.metadata, b"tcspc.spatial_missing": b"[[5, 11]]"}), parts[0])
    rec = reconcile_offline(load_topology(topo, "sp"))
    assert rec["reconciled"]["spatial_reranged"] == [0], rec["reconciled"]
    assert rec["reconciled"]["spatial_incomplete"] == [] and rec["state"] == "finished"
    assert b"tcspc.spatial_missing" not in pq.read_schema(parts[0]).metadata
    again = pl.read_parquet(tmp_path / "out" / "ranges" / "date=*" / "run=sp" / "*.parquet")
    assert again.sort(on).equals(live.sort(on))
    # ... and when the journal cannot give the missing part back (its chunk corrupt, its
    # histograms gone): ranged with what there is, flagged, and the run is incomplete
    from pipeline.stream.journal import _entries, segment_path

    journal = tmp_path / "state" / "journal"
    (chunk,) = [e for e in _entries(journal / "sp.index.jsonl") if not e.get("end")][:1]
    seg = segment_path(journal, "sp", chunk["segment"], chunk["enc"])
    data = bytearray(seg.read_bytes())
    data[chunk["offset"] + chunk["bytes"] // 2] ^= 0x04
    seg.write_bytes(bytes(data))
    next((tmp_path / "out" / "histograms").rglob("part-000000-t005.parquet")).unlink()
    t = pq.read_table(parts[0])
    pq.write_table(t.replace_schema_metadata(
        {**t.schema.metadata, b"tcspc.spatial_missing": b"[[5, 11]]"}), parts[0])
    rec = reconcile_offline(load_topology(topo, "sp"))
    assert rec["reconciled"]["spatial_incomplete"] == [0], rec["reconciled"]
    assert [0, 5] in rec["reconciled"]["corrupt"]
    assert rec["state"] == "incomplete" and any(
        "without some workers' parts" in x for x in rec["problems"]), rec["problems"]
    again = pl.read_parquet(tmp_path / "out" / "ranges" / "date=*" / "run=sp" / "*.parquet")
    gone = again.filter(pl.col("tdc").is_between(5, 10))
    assert gone.height == 6 and not gone["detected"].any()
    assert again.filter(~pl.col("tdc").is_between(5, 10))["flag"].str.contains(
        "ranged without some TDCs").all()


def test_the_topology_checks_spatial_ranging(tmp_path):
    """`[range] spatial = true` needs a geometry and 1..4 returns, and takes any number of
    histogram workers (the range stage gathers their parts of a measurement; ``hold`` of
    them at most, >= 1): refused in one line otherwise (exit 2)."""
    import subprocess
    import sys

    cal = tmp_path / "cal"
    cal.mkdir()
    (cal / "tdc.parquet").touch()
    over = {"daemon": {"state": str(tmp_path / "s")}, "sink": {"out": str(tmp_path / "o")}}
    with pytest.raises(TopologyError, match=r"spatial = true needs a geometry"):
        load_topology(None, overrides={**over, "range": {"calibration": str(cal),
                                                         "spatial": True}})
    with pytest.raises(TopologyError, match=r"\[range\] geometry is for spatial"):
        load_topology(None, overrides={**over, "range": {"calibration": str(cal),
                                                         "geometry": "tmf8820"}})
    with pytest.raises(TopologyError, match=r"\[range\] hold"):
        load_topology(None, overrides={**over, "range": {
            "calibration": str(cal), "spatial": True, "geometry": "thesis128", "hold": 0}})
    one = tmp_path / "one.toml"  # a single pixel has no neighbours to range it by
    one.write_text('name = "one"\n[grid]\nrows = 1\ncols = 1\nfov_h_deg = 1.0\n'
                   'fov_v_deg = 1.0\n')
    with pytest.raises(TopologyError, match=r"has one pixel"):
        load_topology(None, overrides={**over, "range": {
            "calibration": str(cal), "spatial": True, "geometry": str(one)}})
    from pipeline.stream.daemon import build, spatial_args
    from pipeline.stream.topology import SOURCE_BATCH_WORDS

    for workers in (1, 2, 4):  # (the one-worker refusal of before: gone)
        topo = load_topology(None, overrides={**over, "histogram": {"workers": workers},
                                              "range": {"calibration": str(cal),
                                                        "spatial": True,
                                                        "geometry": "thesis128"}})
        # (the street's 128 TDCs: a batch of 8192 cycles, 1 of 20 000-cycle measurements,
        # times 2 x hwm 4 + 1 batches a worker may be ahead, + 2 x hwm 4 = 17)
        assert spatial_args(topo) == ["--spatial", "--geometry", "thesis128", "--hold", 17]
        (rng,) = [p for p in build(topo) if p.name == "range"]
        assert rng.argv[rng.argv.index("--workers") + 1] == str(workers)

    def hold(rng=None, **hist):
        return spatial_args(load_topology(None, overrides={
            **over, "histogram": {"workers": 2, **hist}, "range": {
                "calibration": str(cal), "spatial": True, "geometry": "thesis128",
                **(rng or {})}}))[-1]

    assert hold({"hold": 3}) == 3
    assert hold(measurement_cycles=1000) == 9 * 9 + 8 and hold(measurement_cycles=10) == 256
    from pipeline.cli.stream import REPLAY_BATCH_WORDS

    assert SOURCE_BATCH_WORDS == REPLAY_BATCH_WORDS
    assert spatial_args(load_topology(None, overrides=over)) == []
    scene = tmp_path / "small.toml"
    scene.write_text("")
    path = tmp_path / "t.toml"
    path.write_text(f"[source]\nkind = 'sim'\nscene = '{scene}'\n[daemon]\nstate = "
                    f"'{tmp_path / 's'}'\n[histogram]\nworkers = 2\n[sink]\nout = "
                    f"'{tmp_path / 'o'}'\n[range]\ncalibration = '{cal}'\nspatial = true\n"
                    "geometry = 'thesis128'\nmax_returns = 5\n")
    p = subprocess.run([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                        str(path)], capture_output=True, text=True)
    assert p.returncode == 2
    lines = [x for x in p.stderr.splitlines() if x.strip()]
    assert any("[range] spatial = true" in x and "max_returns = 5" in x for x in lines), lines
    assert not any("workers" in x for x in lines), lines
    assert "Traceback" not in p.stderr


def test_frames_pushed_out_by_hold_are_ranged_again_whole(tmp_path, caldir):
    """Three workers, four measurements, ``[range] hold = 1``: a measurement whose last
    part comes after the next measurement's first is ranged with the parts it has (how
    often depends on the workers' timing), flagged; at the run's end every such one is
    ranged again whole, so each measurement's rows are those its whole frame gives in one
    message (its histograms from the datasets, ranged apart), no row flagged, the run
    finished."""
    import polars as pl
    import pyarrow.parquet as pq

    from pipeline.io.caldir import load_calibration
    from pipeline.io.capture import Capture
    from pipeline.offline.ranging import RangeCore
    from pipeline.stream.daemon import Supervisor

    topo, cap, geom = _edge_topology(tmp_path, caldir, "workers = 3\nmeasurement_cycles = 1500",
                                     """
[range]
calibration = "{caldir}"
spatial = true
max_returns = 2
hold = 1
geometry = "{geom}"
[sink]
out = "{out}"
""")
    res = Supervisor(load_topology(topo, "h1"), log=lambda m: None).run()
    assert res["state"] == "finished", res["problems"]
    rec = res["reconciled"]
    assert rec["spatial_incomplete"] == []
    # (each frame ranged live without a part is ranged again; none is when all came whole)
    assert len(rec["spatial_reranged"]) >= min(res["accounting"]["spatial_incomplete_frames"],
                                               1)
    live = pl.read_parquet(tmp_path / "out" / "ranges" / "date=*" / "run=h1" / "*.parquet")
    assert (live["flag"] == "").all() and live["measurement"].n_unique() == 4
    meta = Capture(cap).meta
    whole = RangeCore(load_calibration(caldir), spatial=load_geometry(geom), max_returns=2,
                      forward_histograms=False)
    want = []
    for k in range(4):
        parts = sorted((tmp_path / "out" / "histograms").rglob(f"part-{k:06d}-t*.parquet"))
        t = pa.concat_tables([pq.read_table(p).replace_schema_metadata(None)
                              for p in parts]).combine_chunks()
        head = {"run": "h1", "measurement": f"h1-m{k:06d}", "measurement_index": k,
                "tdc_range": [0, 16], "n_tdc_total": 16, "window_ns": meta.window_ns,
                "t_laser_win_ns": meta.t_laser_win_ns}
        want += [pl.from_arrow(b) for _, b in whole.process(head, t.to_batches()[0])]
    on = ["measurement", "tdc", "return_index"]
    assert live.sort(on).equals(pl.concat(want).sort(on))
