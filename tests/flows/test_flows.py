"""Each flow with small parameters through Prefect's test harness (offline, no server)."""

import json
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.offline.calibrate import quality

N_PIX = 4
SMALL_CAL = dict(n_pixels=N_PIX, cycles=150_000, delay_cycles=100_000,
                 lux=[100.0, 400.0, 1200.0, 2500.0, 3500.0], inl_rms=1.0)


@pytest.fixture(scope="module")
def campaign(harness, tmp_path_factory):
    from flows.calibration import calibration_campaign

    out = tmp_path_factory.mktemp("cal")
    return out, calibration_campaign(out=str(out), **SMALL_CAL)


def _snapshot(d: Path) -> dict:
    return {p.name: p.read_bytes() for p in sorted(d.iterdir())}


def test_calibration_campaign_publishes_a_checked_calibration(campaign):
    out, r = campaign
    assert r["published"] and r["refused_because"] == []
    current = out / "current"
    assert {p.name for p in current.iterdir()} == {"tdc.parquet", "inl.parquet", "meta.json"}
    q = quality(current)
    assert q.tdcs_ok == N_PIX and q.has_delay and np.isfinite(q.lsb_residual_ps)
    # against the simulated chip's truth: the LSB to a fraction of a ps, the delay to
    # a fraction of an LSB (~200 ps)
    assert r["truth"]["lsb_error_rms_ps"] < 0.5
    assert abs(r["truth"]["delay_error_median_ps"]) < 100
    run = Path(r["run"])
    text = (run / "report.md").read_text()
    assert "Published to `current`" in text and "![lsb](lsb.png)" in text
    for png in r["plots"]:
        assert Path(png).stat().st_size > 10_000
    tests = pl.read_parquet(run / "tests.parquet")
    assert tests.height == 5 and tests["detections_per_pixel_per_cycle"].is_sorted()


def test_a_worse_calibration_is_refused_and_the_old_one_stays(campaign):
    from flows.calibration import calibration_campaign

    out, _ = campaign
    before = _snapshot(out / "current")
    worse = calibration_campaign(out=str(out), **{**SMALL_CAL, "cycles": 40_000,
                                                  "inl_rms": 5.0, "seed": 7})
    assert not worse["published"]
    assert any("INL error" in why for why in worse["refused_because"])
    assert _snapshot(out / "current") == before
    assert "**Not published**" in Path(worse["report"]).read_text()


def test_a_failed_task_leaves_no_half_written_calibration(campaign, monkeypatch):
    import flows.calibration as fc

    out, _ = campaign
    before = _snapshot(out / "current")

    def broken(capture, caldir):
        (Path(caldir) / "tdc.parquet").write_bytes(b"half")  # a write cut short
        raise OSError("disk went away during the delay step")

    monkeypatch.setattr(fc, "add_delay", broken)
    # another delay capture: the first run's delay step is cached, and would not run
    state = fc.calibration_campaign(out=str(out), **{**SMALL_CAL, "delay_cycles": 90_000},
                                    return_state=True)
    assert state.is_failed()
    assert _snapshot(out / "current") == before
    # no temporaries left (.lock: the campaigns' lock file)
    assert not [p for p in out.iterdir() if p.name.startswith(".") and p.name != ".lock"]


def test_calibration_campaign_on_a_capture_directory(campaign, tmp_path):
    from flows.calibration import calibration_campaign

    out, r = campaign
    caps = tmp_path / "caps"
    caps.mkdir()
    used = r["captures"]["density"] + [r["captures"]["delay"]]  # the first run's
    for i, c in enumerate(used):
        for ext in (".bin", ".json"):
            (caps / f"c{i}{ext}").symlink_to(Path(c).with_suffix(ext))
    res = calibration_campaign(out=str(tmp_path / "cal2"), captures=str(caps), inl_rms=1.0)
    assert res["published"] and res["quality"]["tdcs_ok"] == N_PIX


def test_distance_sweep_against_truth(campaign, tmp_path, harness):
    from flows.distance_sweep import distance_sweep, gate_ns

    out, _ = campaign
    assert gate_ns(1.0) == 140.0 and gate_ns(60.0) == 10 * np.ceil((100 + 400.28 + 40) / 10)
    r = distance_sweep(out=str(tmp_path), calibration=str(out / "current"),
                       distances=[0.5, 2.0, 10.0], cycles=20_000, n_pixels=N_PIX)
    pts = pl.read_parquet(Path(r["run"]) / "points.parquet")
    assert pts.height == 3 * N_PIX and pts["detected"].all()
    assert pts["error_m"].abs().max() < 0.10          # within half an LSB of range (3 cm)
    assert r["median_abs_error_cm"] < 3.0
    s = pl.read_parquet(Path(r["run"]) / "summary.parquet")
    assert s["gate_ns"].to_list() == [140.0, 140.0, gate_ns(10.0)]
    assert len(r["plots"]) == 2 and "Per distance" in Path(r["report"]).read_text()


def test_performance_prediction(harness, tmp_path):
    from flows.performance import performance_prediction

    kw = dict(out=str(tmp_path), distances=[5.0, 20.0, 40.0], configs=[1, 8],
              verify_configs=[1], verify_distances=[5.0, 20.0, 40.0], runs=60)
    r = performance_prediction(**kw)
    g = pl.read_parquet(Path(r["run"]) / "grid.parquet")
    assert g.height == 3 * 2 * 2
    v = pl.read_parquet(Path(r["run"]) / "verification.parquet")
    # near: both certain; far (40 m, config 1): both near zero
    assert v["predicted"][0] > 0.99 and v["measured"][0] > 0.95
    assert v["predicted"][2] < 0.05 and v["measured"][2] < 0.2
    again = performance_prediction(**kw)  # seeded: the same numbers
    assert pl.read_parquet(Path(again["run"]) / "verification.parquet").equals(v)
    with pytest.raises(ValueError, match="Table 2.2 has 1..8"):
        performance_prediction(out=str(tmp_path), configs=[9])


def test_speed_vs_error(harness, tmp_path):
    from flows.speed_vs_error import speed_vs_error

    r = speed_vs_error(out=str(tmp_path), m=[1.0], cycles=[10_000], sbr=[100.0], pixels=30,
                       estimators=["ml", "fast"])
    cells = pl.read_parquet(Path(r["run"]) / "cells.parquet")
    assert cells.height == 1 * 1 * 1 * 3 * 2
    ml = cells.filter(pl.col("estimator") == "ml")
    assert (ml["rmse_over_crlb"] < 2.0).all() and (ml["detected"] == 1).all()
    assert json.loads((Path(r["run"]) / "summary.json").read_text())["summary"]


def test_flow_cli_lists_runs_and_checks_parameters():
    from click.testing import CliRunner

    from pipeline.cli.app import cli

    runner = CliRunner()
    res = runner.invoke(cli, ["flow", "list"])
    assert res.exit_code == 0
    for name in ("calibration_campaign", "distance_sweep", "performance_prediction",
                 "speed_vs_error"):
        assert f"{name}:" in res.output
    res = runner.invoke(cli, ["flow", "run", "speed_vs_error", "-p", "pixelz=3"])
    assert res.exit_code != 0 and "not a parameter" in res.output
    res = runner.invoke(cli, ["flow", "run", "nope"])
    assert res.exit_code != 0 and "unknown flow" in res.output


def test_serve_publishes_scheduled_deployments():
    from flows.cli import deployments

    deps = deployments("0 2 * * *", None, "data")
    names = {(d.flow_name, d.name) for d in deps}
    assert ("calibration_campaign", "nightly") in names
    nightly = next(d for d in deps if d.name == "nightly")
    assert nightly.schedules and nightly.schedules[0].schedule.cron == "0 2 * * *"
    assert nightly.parameters["out"] == "data/calibration"


def test_the_demo_story_runs_and_checks_itself(harness, tmp_path):
    """What `make demo` runs, smaller: calibration flow, the daemon, ranges against truth."""
    from flows.demo import run_story

    r = run_story(tmp_path / "data", cycles=40_000, calibration_cycles=100_000, inl_rms=1.5)
    assert r["ok"], r
    assert {x["target"] for x in r["ranges"]} == {"car", "pedestrian", "wall"}
    assert all(abs(x["error_cm"]) < 5 for x in r["ranges"])
    assert Path(r["calibration report"]).exists()


def test_a_sweep_fans_out_over_a_dask_cluster(harness, tmp_path):
    """`tcspc flow run --dask ADDRESS`: tasks on a Dask cluster (needs the [dask] extra)."""
    pytest.importorskip("prefect_dask")
    from click.testing import CliRunner
    from distributed import LocalCluster

    from pipeline.cli.app import cli

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                      dashboard_address=None) as cluster:
        res = CliRunner().invoke(cli, ["flow", "run", "speed_vs_error", "--dask",
                                       cluster.scheduler_address, "-p", f"out={tmp_path}",
                                       "-p", "pixels=10", "-p", "m=[1.0]", "-p",
                                       "cycles=[1000]", "-p", "sbr=[100.0]"])
    assert res.exit_code == 0, res.output
    cells = pl.read_parquet(next(tmp_path.glob("runs/*/cells.parquet")))
    assert cells.height == 3 * 5


def test_campaign_and_sweep_against_a_daemon(campaign, tmp_path, harness):
    """The same flows on a daemon's data: the calibration campaign on runs of its journal,
    the distance sweep on its ranges dataset."""
    from flows.calibration import calibration_campaign
    from flows.common import scene_dict
    from flows.distance_sweep import distance_sweep
    from pipeline.io.capture import Capture
    from pipeline.stream.daemon import Supervisor
    from pipeline.stream.journal import JournalWriter
    from pipeline.stream.topology import load_topology

    out, r = campaign
    journal = tmp_path / "state" / "journal"
    names = [f"dens{i}" for i in range(len(r["captures"]["density"]))]
    for name, path in zip(names + ["zero"], r["captures"]["density"] + [r["captures"]["delay"]],
                          strict=True):
        cap = Capture(path)  # as the daemon would have journaled it, run by run
        w = JournalWriter(journal, name, cap.meta.n_tdc, cap.meta.t_laser_win_ns)
        for first, words in cap.iter_chunks(1 << 16):
            w.append(first, words.copy())
        w.close()
    res = calibration_campaign(out=str(tmp_path / "cal"), journal=str(journal),
                               density_runs=names, delay_run="zero", inl_rms=1.0)
    assert res["published"] and res["quality"]["tdcs_ok"] == N_PIX
    same = quality(tmp_path / "cal" / "current")
    assert same.inl_error_lsb == pytest.approx(quality(out / "current").inl_error_lsb)

    import tomllib

    scene = tmp_path / "r.toml"
    raw = scene_dict("short_range", n_pixels=N_PIX, distance_m=1.25)
    scene.write_text(_toml(raw))
    assert tomllib.loads(scene.read_text())["targets"][0]["distance_m"] == 1.25
    topo = load_topology(None, "r1", overrides={
        "daemon": {"state": str(tmp_path / "state")},
        "source": {"scene": str(scene), "cycles": 40_000},
        "histogram": {"workers": 1, "measurement_cycles": 20_000},
        "range": {"calibration": str(out / "current")},
        "sink": {"out": str(tmp_path / "stream")}})
    assert Supervisor(topo, log=lambda m: None).run()["failed"] is None
    sweep = distance_sweep(out=str(tmp_path / "sweep"), stream=str(tmp_path / "stream"),
                           runs={"r1": 1.25})
    pts = pl.read_parquet(Path(sweep["run"]) / "points.parquet")
    assert pts.height == 2 * N_PIX and pts["detected"].all()
    assert sweep["median_abs_error_cm"] < 3.0


def _toml(d: dict, prefix: str = "") -> str:
    """A scene dict back to TOML (tables and arrays of tables, one level deep)."""
    lines, tables = [], []
    for k, v in d.items():
        if isinstance(v, dict):
            tables.append(f"[{k}]\n" + "".join(f"{a} = {_val(b)}\n" for a, b in v.items()))
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            tables += [f"[[{k}]]\n" + "".join(f"{a} = {_val(b)}\n" for a, b in t.items())
                       for t in v]
        else:
            lines.append(f"{k} = {_val(v)}\n")
    return "".join(lines) + "".join(tables)


def _val(v) -> str:
    return json.dumps(v) if not isinstance(v, bool) else str(v).lower()
