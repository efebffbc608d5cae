"""Two surfaces a pixel end to end: a pane in front of a wall simulated photon by photon
(the reference engine), through the chip's words, its calibration and `range`."""

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipeline.io.caldir import load_calibration
from pipeline.offline.ranging import range_capture
from pipeline.offline.simulate import simulate_capture
from stages.models.scene import scene_from_dict


@pytest.mark.slow
def test_a_wall_behind_a_pane_is_ranged_through_the_chip(tmp_path, caldir):
    """Pixels 0-7 look through glass at 1 m (transmittance 0.9) at a wall at 3 m, pixels
    8-15 at the wall alone: two detected returns and one, each near its truth (the
    calibration of this small chip holds ranges to a few cm, as in the daemon's tests)."""
    scene = scene_from_dict({
        "name": "pane", "sensor": {"n_pixels": 16},
        "gate": {"t_laser_win_ns": 140.0, "delay_ns": 100.0},
        "targets": [{"pixels": [0, 7], "distance_m": 1.0, "reflectivity": 0.0006,
                     "surface": "mirror", "transmittance": 0.9},
                    {"pixels": [0, 15], "distance_m": 3.0, "reflectivity": 0.003,
                     "surface": "mirror"}],
        "ambient": [{"kind": "lux", "lux": 500.0}]})
    simulate_capture(scene, 60_000, tmp_path / "pane", seed=4)  # reference: two surfaces
    calib = load_calibration(caldir)
    table, _ = range_capture(tmp_path / "pane", calib, tmp_path / "r.parquet", "ml",
                             max_returns=3)
    meta = pq.read_schema(tmp_path / "r.parquet").metadata  # #39.1: the output names it
    assert meta[b"tcspc.calibration_id"].decode() == calib.meta["calibration_id"] != ""
    tdc = np.asarray(table.column("tdc"))
    det = np.asarray(table.column("detected"))
    d = np.asarray(table.column("distance_m"))
    for p in range(16):
        got = np.sort(d[(tdc == p) & det])
        truth = [1.0, 3.0] if p < 8 else [3.0]
        assert got.size == len(truth), (p, got)
        assert np.all(np.abs(got - truth) < 0.05), (p, got)
