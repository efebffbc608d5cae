import pytest


@pytest.fixture(scope="session")
def harness():
    # prefect_test_harness points Prefect at a temporary database and server of its own.
    from prefect.testing.utilities import prefect_test_harness

    with prefect_test_harness(server_startup_timeout=120):
        yield
