"""Prefect's embedded API works in this environment (offline, no server to start)."""

def test_trivial_flow_runs_on_the_embedded_api(harness):
    from flows.smoke import smoke

    assert smoke({"hit": 3, "no_hit": 4}) == 7
    state = smoke({"hit": 1}, return_state=True)
    assert state.is_completed() and state.result() == 1
