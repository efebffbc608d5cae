"""How often the range stage ranges a spatial frame without every worker's part
(``[range] hold``, docs/ranging.md "On the chip"): the daemon on a replayed 16-TDC
capture (the edge scene of ``tests/pipeline/io/test_pointcloud_sink.py``: mirrors at 1.5
and 2.5 m on a 4 x 4 grid, 6000 cycles, 800 lux), its calibration made as the tests' is
(four density tests and a delay), for each ``measurement_cycles:hold:workers`` case
(hold ``auto``: left out, :func:`pipeline.stream.topology.range_hold`);
per case the run's end state, its measurements, the frames the stage ranged without a
part (``spatial_incomplete_frames``) and the measurements the reconciliation ranged
again whole (``spatial_reranged``: those, and any lost in flight).

    python benchmarks/spatial_gather.py [--work DIR] [CASE ...]   (CASE e.g. 302:8:3, 302:auto:3)
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

EDGE16 = {"name": "edge16", "sensor": {"n_pixels": 16},
          "gate": {"t_laser_win_ns": 140.0, "delay_ns": 100.0},
          "targets": [{"pixels": [0, 7], "distance_m": 1.5, "reflectivity": 0.0002,
                       "surface": "mirror"},
                      {"pixels": [8, 15], "distance_m": 2.5, "reflectivity": 0.0002,
                       "surface": "mirror"}],
          "ambient": [{"kind": "lux", "lux": 800.0}]}
GRID16 = 'name = "grid16"\n[grid]\nrows = 4\ncols = 4\nfov_h_deg = 10.0\nfov_v_deg = 10.0\n'
CASES = ["1500:auto:3", "1500:2:3", "302:8:3", "302:16:3", "302:auto:3", "100:8:3",
         "100:auto:3"]


def _inputs(work: Path) -> tuple[Path, Path, Path]:
    """The capture, the calibration and the geometry (made once in ``work``)."""
    from pipeline.offline.simulate import simulate_capture, simulated_calibration
    from stages.models.scene import scene_from_dict

    cal, cap, geom = work / "cal", work / "cap", work / "grid16.toml"
    if not (cal / "tdc.parquet").exists():
        simulated_calibration(work, 16)
    if not cap.with_suffix(".bin").exists():
        simulate_capture(scene_from_dict(EDGE16), 6000, cap, seed=4)
    geom.write_text(GRID16)
    return cap, cal, geom


def run_case(work: Path, case: str) -> dict:
    from pipeline.stream.daemon import Supervisor
    from pipeline.stream.topology import load_topology

    mc, hold, workers = case.split(":")  # (hold "auto": left out, the daemon's default)
    cap, cal, geom = _inputs(work)
    tag = case.replace(":", "-")
    for old in (work / f"state-{tag}", work / f"out-{tag}"):  # (a fresh run each time)
        shutil.rmtree(old, ignore_errors=True)
    topo = work / f"topo-{tag}.toml"
    topo.write_text(f"""
[daemon]
state = "{work / ('state-' + tag)}"
[source]
kind = "capture"
capture = "{cap}"
[histogram]
workers = {workers}
measurement_cycles = {mc}
calibration = "{cal}"
[range]
calibration = "{cal}"
spatial = true
max_returns = 2
{"" if hold == "auto" else f"hold = {hold}"}
geometry = "{geom}"
[sink]
out = "{work / ('out-' + tag)}"
""")
    res = Supervisor(load_topology(topo, f"g{tag}"), log=lambda m: None).run()
    rec = res.get("reconciled") or {}
    return {"case": case, "state": res["state"], "measurements": rec.get("measurements"),
            "incomplete": (res.get("accounting") or {}).get("spatial_incomplete_frames"),
            "reranged": len(rec.get("spatial_reranged", [])),
            "recomputed": len(rec.get("recomputed", []))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("cases", nargs="*", default=CASES)
    ap.add_argument("--work", type=Path, default=None)
    args = ap.parse_args()
    work = args.work or Path(tempfile.mkdtemp(prefix="spatial_gather-"))
    work.mkdir(parents=True, exist_ok=True)
    print("| measurement_cycles:hold:workers | state | measurements | frames ranged "
          "without a part | measurements ranged again | parts recomputed |")
    print("|---|---|---:|---:|---:|---:|")
    for case in args.cases:
        r = run_case(work, case)
        print(f"| {r['case']} | {r['state']} | {r['measurements']} | {r['incomplete']} | "
              f"{r['reranged']} | {r['recomputed']} |", flush=True)


if __name__ == "__main__":
    main()
