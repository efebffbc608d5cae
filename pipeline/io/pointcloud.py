"""Point clouds from ranges and a geometry, in the formats lidar tools open
(docs/geometry.md): LAS 1.4 (laspy), PLY (plyfile), PCD (pypcd4) and ROS 2
``sensor_msgs/PointCloud2`` messages in MCAP (mcap + mcap-ros2-support). No writer is ours:
docs/decisions.md says which libraries and why.

Every detected return with a finite distance and a pixel in the geometry is a point:
x, y, z (m, the geometry's output frame), ``intensity`` (the return's signal counts),
``sigma_m``, ``return_index`` (0 the strongest), ``tdc``, ``row``, ``col``,
``distance_m`` and its measurement. The MCAP file holds one organised cloud (rows x cols
of the geometry, NaN where a pixel has no return, ``is_dense`` false) a measurement and a
return rank: topic ``/tcspc/points`` the strongest return, ``/tcspc/points/return_K`` the
K-th further one where any pixel has one.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pyarrow as pa

from pipeline.io.atomic import atomic_path
from stages.geometry import Geometry, points

FORMATS = ("las", "ply", "pcd", "mcap")
#: the per-point fields besides x, y, z, and their types in every format
EXTRA = (("intensity", np.float32), ("sigma_m", np.float32), ("distance_m", np.float32),
         ("return_index", np.uint8), ("tdc", np.uint32), ("row", np.uint16),
         ("col", np.uint16))


@dataclass(frozen=True)
class Cloud:
    """The points of one measurement: ``xyz`` (n, 3) float64 and the :data:`EXTRA` fields,
    ``time_ns`` its time (UNIX ns)."""

    measurement: str
    time_ns: int
    xyz: np.ndarray
    fields: dict[str, np.ndarray]


def clouds(ranges: pa.Table, geom: Geometry, times_ns: dict[str, int]) -> tuple[list[Cloud], int]:
    """The clouds of a ranges table, in the table's measurement order, and how many
    detected returns had no pixel in the geometry (not exported; the caller says so)."""
    det = np.asarray(ranges.column("detected").to_numpy(zero_copy_only=False), bool)
    dist = ranges.column("distance_m").to_numpy()
    tdc = ranges.column("tdc").to_numpy().astype(np.int64)
    idx = geom.index_of(tdc)
    keep = det & np.isfinite(dist)
    missing = int((keep & (idx < 0)).sum())
    keep &= idx >= 0
    names = np.asarray(ranges.column("measurement").to_pylist(), object)
    ret = (ranges.column("return_index").to_numpy().astype(np.int64)
           if "return_index" in ranges.column_names else np.zeros(len(tdc), np.int64))
    out = []
    for name in dict.fromkeys(names.tolist()):
        m = keep & (names == name)
        i = idx[m]
        f = {"intensity": ranges.column("signal_counts").to_numpy()[m],
             "sigma_m": ranges.column("sigma_m").to_numpy()[m], "distance_m": dist[m],
             "return_index": ret[m], "tdc": tdc[m], "row": geom.row[i], "col": geom.col[i]}
        f = {k: np.asarray(f[k]).astype(t) for k, t in EXTRA}
        out.append(Cloud(name, int(times_ns[name]), points(geom, tdc[m], dist[m]), f))
    return out, missing


def measurement_times(ranges: pa.Table, path: str | Path) -> dict[str, int]:
    """Each measurement's time (UNIX ns): a ``time_ns`` column where the ranges have one
    (its first value per measurement), else the file's modification time plus one second
    per measurement in file order (the ranges file records no acquisition time)."""
    names = list(dict.fromkeys(ranges.column("measurement").to_pylist()))
    if "time_ns" in ranges.column_names:
        t = dict(zip(ranges.column("measurement").to_pylist(),
                     ranges.column("time_ns").to_pylist(), strict=True))
        return {n: int(t[n]) for n in names}
    base = os.stat(path).st_mtime_ns
    return {n: base + k * 1_000_000_000 for k, n in enumerate(names)}


def _concat(cl: list[Cloud]) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray]:
    xyz = np.concatenate([c.xyz for c in cl]) if cl else np.zeros((0, 3))
    f = {k: np.concatenate([c.fields[k] for c in cl]) if cl else np.zeros(0, t)
         for k, t in EXTRA}
    t_s = np.concatenate([np.full(len(c.xyz), c.time_ns * 1e-9) for c in cl]) if cl \
        else np.zeros(0)
    return xyz, f, t_s


def write_las(cl: list[Cloud], path: str | Path) -> int:
    """LAS 1.4, point format 6, 0.1 mm scale; ``intensity`` the signal counts rounded and
    clipped to 0..65535, ``return_number`` return_index + 1 of ``number_of_returns`` the
    pixel's detected returns, ``gps_time`` the measurement's UNIX time in seconds (not GPS
    time), ``point_source_id`` the measurement's index; extra bytes: ``sigma_m``,
    ``signal_counts`` (unrounded), ``distance_m``, ``tdc``, ``row``, ``col``."""
    import laspy

    xyz, f, t_s = _concat(cl)
    header = laspy.LasHeader(point_format=6, version="1.4")
    header.add_extra_dims([
        laspy.ExtraBytesParams("sigma_m", np.float32, "1-sigma distance uncertainty m"),
        laspy.ExtraBytesParams("signal_counts", np.float32, "signal detections"),
        laspy.ExtraBytesParams("distance_m", np.float32, "ranged distance m"),
        laspy.ExtraBytesParams("tdc", np.uint32, "histogram row (TDC)"),
        laspy.ExtraBytesParams("row", np.uint16, "row on the array"),
        laspy.ExtraBytesParams("col", np.uint16, "column on the array")])
    header.scales = np.array([1e-4, 1e-4, 1e-4])
    header.offsets = np.floor(xyz.min(axis=0)) if len(xyz) else np.zeros(3)
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    las.intensity = np.clip(np.rint(f["intensity"]), 0, 65535).astype(np.uint16)
    n_ret = _returns_per_pixel(cl)
    las.return_number = (f["return_index"].astype(np.uint8) + 1).clip(1, 15)
    las.number_of_returns = n_ret.clip(1, 15)
    las.gps_time = t_s
    las.point_source_id = np.concatenate(
        [np.full(len(c.xyz), k % 65536, np.uint16) for k, c in enumerate(cl)]) if cl \
        else np.zeros(0, np.uint16)
    for k in ("sigma_m", "distance_m", "tdc", "row", "col"):
        las[k] = f[k]
    las["signal_counts"] = f["intensity"]
    with atomic_path(path) as tmp:
        las.write(str(tmp))
    return len(xyz)


def _returns_per_pixel(cl: list[Cloud]) -> np.ndarray:
    out = []
    for c in cl:
        _, inv, cnt = np.unique(c.fields["tdc"], return_inverse=True, return_counts=True)
        out.append(cnt[inv].astype(np.uint8))
    return np.concatenate(out) if out else np.zeros(0, np.uint8)


def _structured(cl: list[Cloud], xyz_type=np.float64) -> np.ndarray:
    xyz, f, t_s = _concat(cl)
    mi = np.concatenate([np.full(len(c.xyz), k, np.uint32) for k, c in enumerate(cl)]) \
        if cl else np.zeros(0, np.uint32)
    dt = [("x", xyz_type), ("y", xyz_type), ("z", xyz_type), *EXTRA,
          ("measurement_index", np.uint32), ("time_s", np.float64)]
    a = np.empty(len(xyz), dt)
    a["x"], a["y"], a["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for k, _ in EXTRA:
        a[k] = f[k]
    a["measurement_index"], a["time_s"] = mi, t_s
    return a


def write_ply(cl: list[Cloud], path: str | Path) -> int:
    """Binary little-endian PLY, one ``vertex`` element: x, y, z as doubles, the
    :data:`EXTRA` fields, ``measurement_index`` and ``time_s`` (UNIX seconds); the
    measurements' names in comments."""
    from plyfile import PlyData, PlyElement

    a = _structured(cl)
    el = PlyElement.describe(a, "vertex")
    comments = ["tcspc-lidar export"] + [f"measurement {k} {c.measurement}"
                                         for k, c in enumerate(cl)]
    with atomic_path(path) as tmp:
        PlyData([el], text=False, byte_order="<", comments=comments).write(str(tmp))
    return len(a)


def write_pcd(cl: list[Cloud], path: str | Path) -> int:
    """Binary PCD 0.7 (unorganised), x, y, z as float32 (PCL's own type), the
    :data:`EXTRA` fields, ``measurement_index`` and ``time_s``."""
    from pypcd4 import Encoding, PointCloud

    a = _structured(cl, np.float32)
    names = a.dtype.names
    pc = PointCloud.from_points([a[n] for n in names], names, [a.dtype[n] for n in names])
    with atomic_path(path) as tmp:
        pc.save(str(tmp), encoding=Encoding.BINARY)
    return len(a)


# sensor_msgs/msg/PointCloud2 with the definitions it uses, as ROS 2 tools store it in an
# MCAP schema record (the message definitions of ROS 2's common_interfaces)
_SEP = "=" * 80
POINTCLOUD2_MSGDEF = f"""std_msgs/Header header
uint32 height
uint32 width
PointField[] fields
bool is_bigendian
uint32 point_step
uint32 row_step
uint8[] data
bool is_dense
{_SEP}
MSG: std_msgs/Header
builtin_interfaces/Time stamp
string frame_id
{_SEP}
MSG: builtin_interfaces/Time
int32 sec
uint32 nanosec
{_SEP}
MSG: sensor_msgs/PointField
uint8 INT8 = 1
uint8 UINT8 = 2
uint8 INT16 = 3
uint8 UINT16 = 4
uint8 INT32 = 5
uint8 UINT32 = 6
uint8 FLOAT32 = 7
uint8 FLOAT64 = 8
string name
uint32 offset
uint8 datatype
uint32 count
"""
_POINTFIELD = {np.dtype(np.uint8): 2, np.dtype(np.uint16): 4, np.dtype(np.uint32): 6,
               np.dtype(np.float32): 7,
               np.dtype(np.float64): 8}
TOPIC = "/tcspc/points"


def organised(c: Cloud, geom: Geometry, rank: int) -> np.ndarray:
    """The ``rank``-th returns of a measurement as a rows x cols structured array (x, y, z
    float32 and the :data:`EXTRA` fields; NaN x, y, z and zero fields where a pixel has
    none)."""
    dt = np.dtype([("x", np.float32), ("y", np.float32), ("z", np.float32), *EXTRA])
    grid = np.zeros((geom.rows, geom.cols), dt)
    for k in ("x", "y", "z", "intensity", "sigma_m", "distance_m"):
        grid[k] = np.nan
    m = c.fields["return_index"] == rank
    r, col = c.fields["row"][m], c.fields["col"][m]
    for j, k in enumerate("xyz"):
        grid[k][r, col] = c.xyz[m, j]
    for k, _ in EXTRA:
        grid[k][r, col] = c.fields[k][m]
    # (pixels without a return keep their place: tdc, row and col say which they are)
    grid["row"] = np.arange(geom.rows)[:, None]
    grid["col"] = np.arange(geom.cols)[None, :]
    grid["tdc"][geom.row, geom.col] = geom.tdc
    return grid


def pointcloud2(grid: np.ndarray, time_ns: int, frame_id: str) -> dict:
    """A ``sensor_msgs/PointCloud2`` message (as the dict mcap-ros2's writer encodes) of an
    organised structured array."""
    dt = grid.dtype
    fields = [{"name": n, "offset": dt.fields[n][1], "datatype": _POINTFIELD[dt.fields[n][0]],
               "count": 1} for n in dt.names]
    h, w = grid.shape
    sec, nsec = divmod(int(time_ns), 1_000_000_000)
    return {"header": {"stamp": {"sec": sec, "nanosec": nsec}, "frame_id": frame_id},
            "height": h, "width": w, "fields": fields, "is_bigendian": False,
            "point_step": dt.itemsize, "row_step": dt.itemsize * w,
            "data": np.ascontiguousarray(grid).tobytes(), "is_dense": False}


def write_mcap(cl: list[Cloud], geom: Geometry, path: str | Path) -> int:
    """One organised PointCloud2 a measurement and return rank (module docstring), logged
    at the measurement's time; returns the messages written."""
    from mcap_ros2.writer import Writer

    n = 0
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        w = Writer(fh)
        schema = w.register_msgdef("sensor_msgs/msg/PointCloud2", POINTCLOUD2_MSGDEF)
        ranks = max((int(c.fields["return_index"].max()) + 1 for c in cl if len(c.xyz)),
                    default=1)
        for seq, c in enumerate(cl):
            for rank in range(ranks):
                topic = TOPIC if rank == 0 else f"{TOPIC}/return_{rank}"
                msg = pointcloud2(organised(c, geom, rank), c.time_ns, geom.frame_id)
                w.write_message(topic, schema, msg, log_time=c.time_ns,
                                publish_time=c.time_ns, sequence=seq)
                n += 1
        w.finish()
    return n


def write(fmt: str, cl: list[Cloud], geom: Geometry, path: str | Path) -> int:
    """Write ``cl`` as ``fmt`` (:data:`FORMATS`); returns the points (messages for mcap)."""
    if fmt == "mcap":
        return write_mcap(cl, geom, path)
    return {"las": write_las, "ply": write_ply, "pcd": write_pcd}[fmt](cl, path)
