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
