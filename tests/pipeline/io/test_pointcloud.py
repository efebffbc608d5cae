"""Point-cloud export: every format read back by a reader that is not its writer (LAS, PLY
and PCD parsed here from their specifications with numpy; the MCAP file by mcap-ros2's
reader), every point within 1 mm of x, y, z computed here from the geometry's definition
(docs/geometry.md), not from stages.geometry."""

from __future__ import annotations

import math
import struct

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from pipeline.io.geometry import GeometryError, load_geometry
from schemas.outputs import RANGES

ROWS, COLS, FOV_H, FOV_V = 3, 4, 40.0, 30.0
POSE = ([1.0, -2.0, 0.5], [5.0, -10.0, 30.0])


def _geometry_toml(tmp_path, distance="radial", projection="pinhole"):
    p = tmp_path / "g.toml"
    p.write_text(f'name = "test"\ndistance = "{distance}"\nframe_id = "lidar"\n'
                 f"[grid]\nrows = {ROWS}\ncols = {COLS}\nfov_h_deg = {FOV_H}\n"
                 f'fov_v_deg = {FOV_V}\nprojection = "{projection}"\nfirst_tdc = 2\n'
                 f"[pose]\nposition_m = {POSE[0]}\nrpy_deg = {POSE[1]}\n")
    return p


def _expected(tdc, d, distance="radial", projection="pinhole"):
    """x, y, z from the definition: a pinhole ray through the image plane at x = 1, or
    equal angles; then roll, pitch, yaw about x, y, z and the position."""
    k = np.asarray(tdc) - 2
    r, c = k // COLS, k % COLS
    u, v = (c + 0.5) / COLS * 2 - 1, (r + 0.5) / ROWS * 2 - 1
    if projection == "pinhole":
        ray = np.stack([np.ones_like(u), -u * math.tan(math.radians(FOV_H / 2)),
                        -v * math.tan(math.radians(FOV_V / 2))], 1)
    else:
        az, el = -u * math.radians(FOV_H / 2), -v * math.radians(FOV_V / 2)
        ray = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], 1)
    ray /= np.linalg.norm(ray, axis=1)[:, None]
    p = ray * (np.asarray(d) / (ray[:, 0] if distance == "axial" else 1.0))[:, None]
    a, b, g = np.radians(POSE[1])
    rx = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = np.array([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    rz = np.array([[math.cos(g), -math.sin(g), 0], [math.sin(g), math.cos(g), 0], [0, 0, 1]])
    return p @ (rz @ ry @ rx).T + np.array(POSE[0])


def _ranges(path, rng):
    """Two measurements of 12 pixels; some not detected, some with a second return, one
    TDC (99) outside the geometry."""
    rows = []
    for m in ("m0", "m1"):
        for t in range(2, 14):
            rows.append((m, t, rng.uniform(0.5, 80), 0, rng.random() > 0.2))
            if t % 5 == 0:
                rows.append((m, t, rng.uniform(80, 120), 1, True))
        rows.append((m, 99, 3.0, 0, True))
    n = len(rows)
    table = pa.table({
        "measurement": [r[0] for r in rows], "tdc": pa.array([r[1] for r in rows], pa.uint16()),
        "distance_m": [r[2] for r in rows], "sigma_m": rng.uniform(0.001, 0.1, n),
        "fwhm_m": np.full(n, 0.07), "signal_counts": rng.uniform(1, 5000, n),
        "background_per_bin": np.full(n, 0.1), "detected": [r[4] for r in rows],
        "estimator": ["ml"] * n, "return_index": pa.array([r[3] for r in rows], pa.uint8()),
        "flag": [""] * n}, schema=RANGES.schema)
    pq.write_table(table, path)
    return table


def _kept(table):
    d = table.to_pydict()
    keep = [i for i in range(table.num_rows) if d["detected"][i] and d["tdc"][i] != 99]
    return {k: np.array([d[k][i] for i in keep]) for k in d}


def _read_las(path):
    """LAS 1.4 point format 6 and its extra-bytes VLR, from the specification (R15)."""
    b = path.read_bytes()
    assert b[:4] == b"LASF" and b[24:26] == bytes([1, 4])
    hsize, = struct.unpack_from("<H", b, 94)
    offset, nvlr = struct.unpack_from("<II", b, 96)
    fmt, reclen = struct.unpack_from("<BH", b, 104)
    assert fmt == 6
    scale, off = struct.unpack_from("<3d", b, 131), struct.unpack_from("<3d", b, 155)
    n, = struct.unpack_from("<Q", b, 247)
    extra, pos = [], hsize
    for _ in range(nvlr):
        user = b[pos + 2:pos + 18].rstrip(b"\0")
        rid, length = struct.unpack_from("<HH", b, pos + 18)
        if user == b"LASF_Spec" and rid == 4:
            for k in range(length // 192):
                d = b[pos + 54 + 192 * k: pos + 54 + 192 * (k + 1)]
                extra.append((d[4:36].rstrip(b"\0").decode(),
                              {3: "<u2", 5: "<u4", 9: "<f4", 10: "<f8"}[d[2]]))
        pos += 54 + length
    dt = np.dtype([("X", "<i4"), ("Y", "<i4"), ("Z", "<i4"), ("intensity", "<u2"),
                   ("ret", "u1"), ("flags", "u1"), ("cls", "u1"), ("user", "u1"),
                   ("angle", "<i2"), ("source", "<u2"), ("gps", "<f8"), *extra])
    assert dt.itemsize == reclen
    a = np.frombuffer(b, dt, count=n, offset=offset)
    xyz = np.stack([a[k] * s + o for k, s, o in zip("XYZ", scale, off, strict=True)], 1)
    return xyz, a


def _header_then_data(b, end):
    i = b.index(end) + len(end)
    return b[:i].decode().splitlines(), i


def _read_ply(path):
    lines, i = _header_then_data(path.read_bytes(), b"end_header\n")
    assert "format binary_little_endian 1.0" in lines
    types = {"double": "<f8", "float": "<f4", "uchar": "u1", "ushort": "<u2", "uint": "<u4"}
    props = [(ln.split()[2], types[ln.split()[1]]) for ln in lines if ln.startswith("property")]
    n = int(next(ln for ln in lines if ln.startswith("element vertex")).split()[2])
    return np.frombuffer(path.read_bytes(), np.dtype(props), count=n, offset=i)


def _read_pcd(path):
    lines, i = _header_then_data(path.read_bytes(), b"DATA binary\n")
    h = {ln.split()[0]: ln.split()[1:] for ln in lines}
    dt = np.dtype([(n, {"F": "<f", "U": "<u", "I": "<i"}[t] + s)
                   for n, s, t in zip(h["FIELDS"], h["SIZE"], h["TYPE"], strict=True)])
    return np.frombuffer(path.read_bytes(), dt, count=int(h["POINTS"][0]), offset=i)


@pytest.fixture(scope="module")
def exported(tmp_path_factory, cli_process):
    """`tcspc export` of the same ranges to each format, once for the tests that read
    them (each a process forked from tests/conftest.py's ``CliProcess``)."""
    tmp_path = tmp_path_factory.mktemp("exported")
    rng = np.random.default_rng(3)
    table = _ranges(tmp_path / "r.parquet", rng)
    g = _geometry_toml(tmp_path)
    out = {}
    for fmt in ("las", "ply", "pcd", "mcap"):
        f = tmp_path / f"c.{fmt}"
        r = cli_process.run("export", tmp_path / "r.parquet", "--geometry", g, "--out", f)
        assert r.returncode == 0, r.stderr
        assert "2 detected return(s) of TDCs that geometry test has no pixel" in r.stderr
        out[fmt] = f
    return table, out


def _sorted(measurement_index, tdc, ret):
    return np.lexsort((ret, tdc, measurement_index))


def test_las_ply_pcd_points_within_1_mm(exported):
    table, files = exported
    k = _kept(table)
    mi = (k["measurement"] == "m1").astype(int)
    order = _sorted(mi, k["tdc"], k["return_index"])
    want = _expected(k["tdc"], k["distance_m"])[order]
    xyz, las = _read_las(files["las"])
    o = _sorted(las["source"], las["tdc"], las["ret"] & 15)
    assert len(xyz) == len(want) > 15
    assert np.abs(xyz[o] - want).max() < 1e-3
    assert np.allclose(las["sigma_m"][o], k["sigma_m"][order], rtol=1e-6)
    assert np.allclose(las["signal_counts"][o], k["signal_counts"][order], rtol=1e-6)
    assert np.array_equal((las["ret"] & 15)[o], k["return_index"][order] + 1)
    assert np.array_equal(las["intensity"][o], np.rint(k["signal_counts"][order]))
    for reader, f in ((_read_ply, "ply"), (_read_pcd, "pcd")):
        a = reader(files[f])
        o = _sorted(a["measurement_index"], a["tdc"], a["return_index"])
        got = np.stack([a["x"], a["y"], a["z"]], 1)[o].astype(np.float64)
        assert np.abs(got - want).max() < 1e-3, f
        assert np.allclose(a["sigma_m"][o], k["sigma_m"][order], rtol=1e-6), f
        assert np.allclose(a["intensity"][o], k["signal_counts"][order], rtol=1e-6), f
        assert np.array_equal(a["return_index"][o], k["return_index"][order]), f


def test_las_opens_in_laspy(exported):
    import laspy

    table, files = exported
    las = laspy.read(files["las"])
    assert las.header.version.minor == 4 and len(las.points) == len(_kept(table)["tdc"])
    assert "sigma_m" in las.point_format.extra_dimension_names


def test_mcap_organised_clouds_read_by_mcap_ros2(exported):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    table, files = exported
    k = _kept(table)
    with open(files["mcap"], "rb") as fh:
        msgs = [(ch.topic, m.log_time, ros) for _, ch, m, ros in make_reader(
            fh, decoder_factories=[DecoderFactory()]).iter_decoded_messages()]
    by = {(t, ros.header.stamp.sec * 10**9 + ros.header.stamp.nanosec): ros
          for t, _, ros in msgs}
    assert sorted({t for t, _ in by}) == ["/tcspc/points", "/tcspc/points/return_1"]
    assert len(msgs) == 4
    times = sorted({t for _, t in by})
    assert times[1] - times[0] == 10**9 and all(lt in times for _, lt, _ in msgs)
    for mi, name in enumerate(("m0", "m1")):
        for rank, topic in enumerate(("/tcspc/points", "/tcspc/points/return_1")):
            msg = by[(topic, times[mi])]
            assert (msg.height, msg.width, msg.is_dense) == (ROWS, COLS, False)
            assert msg.header.frame_id == "lidar"
            dt = np.dtype({"names": [f.name for f in msg.fields],
                           "formats": [{2: "u1", 4: "<u2", 6: "<u4", 7: "<f4", 8: "<f8"}[f.datatype]
                                       for f in msg.fields],
                           "offsets": [f.offset for f in msg.fields],
                           "itemsize": msg.point_step})
            a = np.frombuffer(bytes(msg.data), dt).reshape(ROWS, COLS)
            sel = (k["measurement"] == name) & (k["return_index"] == rank)
            tdc = k["tdc"][sel]
            r, c = (tdc - 2) // COLS, (tdc - 2) % COLS
            got = np.stack([a["x"][r, c], a["y"][r, c], a["z"][r, c]], 1).astype(float)
            assert np.abs(got - _expected(tdc, k["distance_m"][sel])).max() < 1e-3
            empty = np.ones((ROWS, COLS), bool)
            empty[r, c] = False
            assert np.isnan(a["x"][empty]).all() and empty.sum() == ROWS * COLS - sel.sum()
            assert np.array_equal(a["tdc"], 2 + np.arange(ROWS * COLS).reshape(ROWS, COLS))


@pytest.mark.parametrize("distance,projection", [("axial", "pinhole"),
                                                 ("radial", "equiangular")])
def test_axial_and_equiangular(tmp_path, distance, projection):
    from pipeline.io.pointcloud import clouds, measurement_times

    table = _ranges(tmp_path / "r.parquet", np.random.default_rng(5))
    g = load_geometry(_geometry_toml(tmp_path, distance, projection))
    cl, missing = clouds(table, g, measurement_times(table, tmp_path / "r.parquet"))
    assert missing == 2
    for c in cl:
        want = _expected(c.fields["tdc"], c.fields["distance_m"].astype(float), distance,
                         projection)
        assert np.abs(c.xyz - want).max() < 1e-3


def test_overwrite_refused_and_bad_geometry(tmp_path, cli_process):
    _ranges(tmp_path / "r.parquet", np.random.default_rng(1))
    out = tmp_path / "c.ply"
    out.write_text("keep")
    cmd = ["export", str(tmp_path / "r.parquet"), "--geometry", "tmf8820", "--out", str(out)]
    r = cli_process.run(*cmd)
    assert r.returncode == 2 and "exists; give --overwrite" in r.stderr
    assert out.read_text() == "keep"
    r = cli_process.run(*cmd, "--overwrite")
    assert r.returncode == 0, r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("[grid]\nrows = 0\ncols = 3\nfov_h_deg = 200\nfov_v_deg = 1\nwhat = 1\n")
    r = cli_process.run(*cmd[:3], bad, "--out", tmp_path / "x.las")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    for key in ("rows", "fov_h_deg", "what"):
        assert f"[grid] {key}" in r.stderr, r.stderr


def test_shipped_geometries():
    g = load_geometry("thesis128")
    assert (g.rows, g.cols) == (1, 128) and np.all(np.diff(g.azimuth_rad) < 0)
    # 3 mrad a pixel at the centre: atan(24 um / 8 mm)
    assert abs(g.azimuth_rad[63] - g.azimuth_rad[64] - math.atan(0.024 / 8)) < 1e-6
    t = load_geometry("tmf8820")
    assert (t.rows, t.cols, t.distance) == (3, 3, "axial")
    # the datasheet's 63 degrees on the diagonal: the corner zones' outer edges
    corner = np.array([1, math.tan(math.radians(31.5)) / math.sqrt(2)] * 1)
    assert abs(2 * math.degrees(math.atan(math.hypot(corner[1], corner[1]))) - 63) < 1e-9
    li = load_geometry("linospad2")
    assert (li.rows, li.cols, li.distance) == (1, 256, "radial")
    assert li.tdc.tolist() == list(range(256)) and li.col.tolist() == list(range(256))
    # 26.2 um pitch behind the assumed 8 mm lens, centred: pixel t at atan((127.5 - t) p / f)
    want = np.arctan((127.5 - np.arange(256)) * 0.0262 / 8)
    assert np.abs(np.asarray(li.azimuth_rad) - want).max() < 1e-12
    assert not np.any(li.elevation_rad)
    with pytest.raises(GeometryError, match="not a shipped geometry"):
        load_geometry("nope")
