import pytest


@pytest.fixture(scope="session")
def harness(tmp_path_factory):
    # prefect_test_harness points Prefect at a temporary database and server of its own;
    # persisted task results (the cache's records) go to a temporary directory too, so no
    # test reads another session's.
    from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, temporary_settings
    from prefect.testing.utilities import prefect_test_harness

    results = tmp_path_factory.mktemp("prefect-results")
    with temporary_settings({PREFECT_LOCAL_STORAGE_PATH: results}), \
            prefect_test_harness(server_startup_timeout=120):
        yield
