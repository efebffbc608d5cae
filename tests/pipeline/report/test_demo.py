from pipeline.report.demo import run_demo


def test_demo_runs_and_checks_itself(tmp_path):
    result = run_demo(tmp_path / "data", cycles=40_000)  # bounds estimable: ~2000 hits per TDC
    assert result["exact"] and result["street_ok"]
