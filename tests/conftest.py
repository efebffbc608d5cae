import os

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


@pytest.fixture(scope="session")
def caldir(tmp_path_factory):
    """A calibration of the 16-pixel chip of scenes/small16.toml, built once for the
    daemon's and the view's tests: LSB against light from four density tests (the range's
    light differs from any one test's), and a delay."""
    from pipeline.offline.calibrate import add_delay, lsb_campaign
    from pipeline.offline.simulate import simulate_capture
    from stages.models.scene import scene_from_dict

    n = 16
    d = tmp_path_factory.mktemp("cal")
    caps = []
    for i, lux in enumerate((133.950, 535.799, 1607.398, 4018.495)):
        dens = scene_from_dict({"name": f"d{i}", "sensor": {"n_pixels": n},
                                "ambient": [{"kind": "lux", "lux": lux}]})
        simulate_capture(dens, 300_000, d / f"d{i}", seed=3 + i)
        caps.append(d / f"d{i}")
    delay = scene_from_dict({"name": "z", "sensor": {"n_pixels": n},
                             "targets": [{"pixels": [0, n - 1], "distance_m": 0.001,
                                          "reflectivity": 0.0005, "surface": "mirror"}]})
    simulate_capture(delay, 150_000, d / "delay", seed=9)
    lsb_campaign(caps, d / "cal", inl_rms_lsb=1.0)
    add_delay(d / "delay", d / "cal")
    return d / "cal"
