import fcntl
import os
import shutil
from pathlib import Path

import numpy as np
import pytest

# Prefect: no telemetry, and a throw-away home so tests never touch the user's profile.
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

ENGINES = ["numpy", "numba"]


@pytest.fixture(params=ENGINES)
def engine(request):
    """Every data-path test runs on both engines, so they cannot drift apart."""
    return request.param


@pytest.fixture
def rng():
    return np.random.default_rng(12345)


def built_once(tmp_path_factory, name: str, build) -> Path:
    """The directory ``build(d)`` fills, built once a test run: with pytest-xdist by the
    first worker that asks, the others waiting for it and reading it (the workers' base
    temporary directories share their parent). Its users only read it."""
    if "PYTEST_XDIST_WORKER" not in os.environ:
        d = tmp_path_factory.mktemp(name)
        build(d)
        return d
    root = tmp_path_factory.getbasetemp().parent
    d = root / name
    with open(root / f"{name}.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # (released when the file is closed)
        if not (d / ".built").exists():
            shutil.rmtree(d, ignore_errors=True)
            d.mkdir()
            build(d)
            (d / ".built").touch()
    return d


@pytest.fixture(scope="session")
def caldir(tmp_path_factory):
    """A calibration of the 16-pixel chip of scenes/small16.toml, built once for the
    daemon's and the view's tests: LSB against light from four density tests (the range's
    light differs from any one test's), and a delay."""
    from pipeline.offline.simulate import simulated_calibration

    return built_once(tmp_path_factory, "caldir", lambda d: simulated_calibration(d, 16)) / "cal"


@pytest.fixture(scope="session")
def zoo(tmp_path_factory):
    """A chip of the zoo, not the simulator's default one (``random_chip(2, 16, ...)``: a
    real chip's random DNL and INL bow, LSB 198 ps at no light and +51 ps with light, the
    chip sweep's LSB saturation; benchmarks/spatial_chip.py --zoo 2), calibrated as
    ``caldir`` is, and a 3 x 5 grid geometry (TDCs 0..14 placed, row = tdc // 5; TDC 15
    without a pixel): ``(chip, calibration directory, geometry file)``."""
    from pipeline.offline.simulate import simulated_calibration
    from stages.simulator.chip import REAL_CHIP_RANGES, random_chip

    chip, _ = random_chip(2, 16, {**REAL_CHIP_RANGES, "n_sat": (0.5, 1.5),
                                  "artifact_rate": (0.0, 6e-4)})

    def build(d):
        simulated_calibration(d, 16, chip)
        (d / "grid.toml").write_text('name = "grid3x5"\n[grid]\nrows = 3\ncols = 5\n'
                                     'fov_h_deg = 12.0\nfov_v_deg = 7.0\n')

    d = built_once(tmp_path_factory, "zoo", build)
    return chip, d / "cal", d / "grid.toml"


@pytest.fixture(scope="session")
def mirror16():
    """A simulated measurement (20,000 cycles) of scenes/small16.toml's chip and mirror at
    1.5 m, brighter (reflectivity 0.004): the return counts more than the reset peak on
    most TDCs. ``(HistogramState, the chip's true LSB at its light, window_s)``."""
    from stages import calibration as cal
    from stages.histogram import HistogramAccumulator
    from stages.models.scene import evaluate, scene_from_dict
    from stages.simulator.chip import make_chip
    from stages.simulator.source import Simulator

    n = 16
    raw = {"sensor": {"n_pixels": n}, "gate": {"t_laser_win_ns": 140.0, "delay_ns": 100.0},
           "targets": [{"pixels": [0, n - 1], "distance_m": 1.5, "surface": "mirror",
                        "reflectivity": 0.004}],
           "ambient": [{"kind": "lux", "lux": 800.0}]}
    sm = evaluate(scene_from_dict(raw))
    chip = make_chip(n, 1)
    sim = Simulator(sm, chip, 0)
    acc = HistogramAccumulator(n, cal.SecondStage(chip.n_min, chip.n_max, chip.n_th,
                                                  chip.pdm).bounds)
    for _, w in sim.batches(20_000):
        acc.update(w)
    st = acc.snapshot()
    return st, chip.window_truth(sim.light, sm.window_s)[0], sm.window_s


@pytest.fixture(scope="session")
def other_account():
    """A second local account (uid), for attacks by another user of a shared host: created
    with useradd when the tests run as root (removed at the end), else the tests skip."""
    import pwd
    import shutil
    import subprocess

    if os.geteuid() != 0 or not shutil.which("useradd"):
        pytest.skip("needs root and useradd to create a second local account")
    name = f"tcspct{os.getpid() % 100000}"
    subprocess.run(["useradd", "--no-create-home", "--shell", "/usr/sbin/nologin", name],
                   check=True, capture_output=True)
    try:
        yield pwd.getpwnam(name).pw_uid
    finally:
        subprocess.run(["userdel", name], capture_output=True)
