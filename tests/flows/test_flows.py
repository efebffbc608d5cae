"""Each flow with small parameters through Prefect's test harness (offline, no server);
then the campaign as a scheduler sees it (issue 28): named outcomes, artifacts and run ids,
one campaign at a time, a publish that never leaves `current` missing, what a killed run
leaves behind, Prefect's cache, typed parameters and the serve config (the real-server
versions are in test_prefect_server.py)."""

import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import polars as pl
import pytest

from pipeline.offline.calibrate import quality

N_PIX = 4
SMALL_CAL = dict(n_pixels=N_PIX, cycles=150_000, delay_cycles=100_000,
                 lux=[133.950, 535.799, 1607.398, 3348.746, 4688.244], inl_rms=1.0)


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


def test_the_campaign_takes_the_zero_capture_first_and_plans_from_it(harness, tmp_path):
    """With ``plan_budget`` the zero-distance capture is simulated first and the density
    tests' cycles are planned from it (issue 33: `calibrate plan`'s planner), within the
    budget, every lux level kept; the plan is in the result, the run's plan.json and the
    report, and the density captures hold the planned cycles."""
    from flows.calibration import calibration_campaign
    from pipeline.io.capture import Capture

    budget = 400_000
    r = calibration_campaign(out=str(tmp_path), **{**SMALL_CAL, "inl_rms": 1.5},
                             plan_budget=budget)
    plan = r["plan"]
    assert plan["budget"] == budget and len(plan["cycles"]) == len(SMALL_CAL["lux"])
    assert sum(plan["cycles"]) <= budget and min(plan["cycles"]) >= 0.05 * budget - 1
    assert plan["not_planned"] == "" and plan["expected_delay_error_ps"] > 0
    assert plan["cycles"] != [budget // 5] * 5  # spent where the delay's error comes from
    assert plan["lights"] == sorted(plan["lights"]) and 0 < plan["zero_light"] < 1
    assert [Capture(c).meta.cycles for c in r["captures"]["density"]] == plan["cycles"]
    assert json.loads((Path(r["run"]) / "plan.json").read_text()) == plan
    assert "planned from the zero capture" in (Path(r["run"]) / "report.md").read_text()
    assert r["truth"]["lsb_error_rms_ps"] < 0.5


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
    from prefect.exceptions import ParameterTypeError

    with pytest.raises(ParameterTypeError, match="configs.0: Input should be less than or "
                       "equal to 8"):
        performance_prediction(out=str(tmp_path), configs=[9])  # refused by its type


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
                 "speed_vs_error", "batch"):
        assert f"{name}:" in res.output
    res = runner.invoke(cli, ["flow", "run", "speed_vs_error", "-p", "pixelz=3"])
    assert res.exit_code != 0 and "not a parameter" in res.output
    res = runner.invoke(cli, ["flow", "run", "nope"])
    assert res.exit_code != 0 and "unknown flow" in res.output


def test_serve_publishes_scheduled_deployments():
    from flows.cli import deployments, read_serve_config

    deps = deployments(read_serve_config(None))
    nightly = next(d for d in deps if d.flow_name == "calibration_campaign")
    assert nightly.name == "128px daily at 02:00"
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
    """`tcspc flow run --dask ADDRESS`: tasks on a Dask cluster."""
    from click.testing import CliRunner
    from distributed import LocalCluster

    from pipeline.cli.app import cli

    with LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                      dashboard_address=None) as cluster:
        res = CliRunner().invoke(cli, ["flow", "run", "speed_vs_error", "--dask-insecure", "--dask",
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


@pytest.fixture(scope="module")
def captured(campaign, tmp_path_factory):
    """The module campaign's captures as a capture directory (links): a campaign on it
    reuses the cached fit and delay, so it costs seconds."""
    _, r = campaign
    caps = tmp_path_factory.mktemp("caps")
    for i, c in enumerate(r["captures"]["density"] + [r["captures"]["delay"]]):
        for ext in (".bin", ".json"):
            (caps / f"c{i}{ext}").symlink_to(Path(c).with_suffix(ext))
    return caps


def _client():
    from prefect import get_client

    return get_client(sync_client=True)


def test_the_outcome_is_a_named_state_with_its_run_linked_everywhere(campaign):
    from prefect.client.schemas.filters import ArtifactFilter, FlowRunFilter

    out, r = campaign
    fr_id = r["flow_run"]["id"]
    with _client() as c:
        fr = c.read_flow_run(fr_id)
        arts = c.read_artifacts(flow_run_filter=FlowRunFilter(id={"any_": [fr.id]}),
                                artifact_filter=ArtifactFilter())
    # Completed by type and name (#39.4): the verdict in the result, the tag and the event
    assert fr.state.name == "Completed" and fr.state.is_completed()
    assert "tcspc:published" in fr.tags and r["outcome"] == "published"
    assert r["rule"] == "first"
    assert fr.name.startswith("campaign 20") and fr.name.endswith(f" {SMALL_CAL['n_pixels']}px")
    # the run id in the published calibration's meta.json and in summary.json
    meta = json.loads((out / "versions" / Path(r["run"]).name / "meta.json").read_text())
    assert meta["flow_run"]["id"] == fr_id
    assert json.loads((Path(r["run"]) / "summary.json").read_text())["flow_run"]["id"] == fr_id
    kinds = {a.key.rsplit("-", 1)[1]: a for a in arts}
    assert set(kinds) == {"report", "figures", "flagged"}
    assert kinds["report"].type == "markdown" and "Published" in kinds["report"].description
    # the report's figures are in the artifact itself (the UI cannot reach the run's files)
    import base64
    import re

    pngs = re.findall(r"!\[(\w+)\]\(data:image/png;base64,([A-Za-z0-9+/=]+)\)",
                      kinds["report"].data)
    assert {name for name, _ in pngs} == {"density", "lsb"}
    for name, data in pngs:
        assert base64.b64decode(data) == (Path(r["run"]) / f"{name}.png").read_bytes()
    rows = {row["figure"]: row for row in json.loads(kinds["figures"].data)}
    assert rows["TDCs calibrated"]["candidate"] == SMALL_CAL["n_pixels"]
    for fig in ("INL RMS, median TDC (LSB)", "DNL RMS, median TDC (LSB)",
                "LSB fit residual (ps RMS)", "delay spread max-min (ns)"):
        assert rows[fig]["candidate"] >= 0
    assert rows["TDCs calibrated"]["current"] is None  # the first: nothing to replace


def test_a_refused_candidate_ends_completed_with_the_verdict_in_result_and_tag(campaign):
    from flows.calibration import calibration_campaign

    out, _ = campaign
    state = calibration_campaign(out=str(out), **{**SMALL_CAL, "cycles": 40_000,
                                                  "inl_rms": 5.0, "seed": 7},
                                 return_state=True)
    assert state.name == "Completed" and state.is_completed()
    r = state.result()
    assert not r["published"] and r["refused_because"] and r["outcome"] == "refused"
    assert r["rule"] == "quality" and r["age_h"] < 1  # young: the quality rule holds
    with _client() as c:
        assert "tcspc:refused" in c.read_flow_run(r["flow_run"]["id"]).tags
    assert "Not published" in state.message
    # the comparison now has the calibration it would have replaced
    assert r["figures"]["TDCs calibrated"] == SMALL_CAL["n_pixels"]


def test_a_current_that_cannot_be_read_is_not_replaced_unexamined(captured, tmp_path):
    from click.testing import CliRunner

    from flows.calibration import calibration_campaign
    from pipeline.cli.app import cli

    out = tmp_path / "cal"
    (out / "current").mkdir(parents=True)
    (out / "current" / "tdc.parquet").write_bytes(b"left by hand")  # no meta.json
    # through the command line: a refusal is its own exit status, for scripts
    res = CliRunner().invoke(cli, ["flow", "run", "calibration_campaign", "-p", f"out={out}",
                                   "-p", f"captures={captured}", "-p", "inl_rms=1.0"])
    assert res.exit_code == 3, res.output
    assert "calibration_campaign: Completed refused" in res.output
    assert "cannot be read" in json.loads(res.stdout)["refused_because"][0]
    assert (out / "current" / "tdc.parquet").read_bytes() == b"left by hand"
    forced = calibration_campaign(out=str(out), captures=str(captured), inl_rms=1.0,
                                  force=True, return_state=True)
    assert forced.name == "Completed" and forced.result()["forced"]
    assert forced.result()["rule"] == "forced"
    # the old directory was exchanged for a link in one step, and kept as a version
    assert (out / "current").is_symlink() and (out / "current" / "meta.json").is_file()
    assert any(p.name.startswith("before-") for p in (out / "versions").iterdir())


def test_two_campaigns_at_once_take_turns(captured, tmp_path, monkeypatch):
    import flows.calibration as fc

    out = tmp_path / "cal"
    inside, most, real = [0], [0], fc._campaign

    def counted(*a, **k):
        inside[0] += 1
        most[0] = max(most[0], inside[0])
        time.sleep(1.0)  # widen the window the two would overlap in
        try:
            return real(*a, **k)
        finally:
            inside[0] -= 1

    monkeypatch.setattr(fc, "_campaign", counted)
    states = []
    runs = [threading.Thread(target=lambda: states.append(fc.calibration_campaign(
        out=str(out), captures=str(captured), inl_rms=1.0, return_state=True)))
        for _ in range(2)]
    for t in runs:
        t.start()
    for t in runs:
        t.join(120)
    assert len(states) == 2 and all(s.is_completed() for s in states)
    assert most[0] == 1  # never both inside
    assert (out / "current" / "meta.json").is_file()
    assert len(list((out / "versions").iterdir())) == 2  # both published, in turn
    assert not [p for p in out.iterdir() if p.name.startswith(".") and p.name != ".lock"]


def test_a_busy_calibration_fails_naming_the_holder(tmp_path):
    from flows.calibration import calibration_campaign
    from flows.common import FlowBusy, exclusive

    with exclusive(tmp_path, 0):
        state = calibration_campaign(out=str(tmp_path), wait_s=0.3, return_state=True)
    assert state.is_failed()
    with pytest.raises(FlowBusy, match=f"pid {os.getpid()}"):
        state.result()


def _a_running_campaign(name: str):
    """A flow run the API shows Running, named as a campaign (what a killed one leaves)."""
    from prefect import flow
    from prefect.states import Running

    @flow(name="calibration_campaign")
    def stand_in():
        pass

    with _client() as c:
        return c.create_flow_run(stand_in, name=name, state=Running()).id


def _state_after_the_next_campaign(captured, out, run_id):
    """Run a campaign on ``out``; the API's state of ``run_id`` after it."""
    from flows.calibration import calibration_campaign

    state = calibration_campaign(out=str(out), captures=str(captured), inl_rms=1.0,
                                 return_state=True)
    assert state.name == "Completed" and state.result()["published"]
    with _client() as c:
        return c.read_flow_run(run_id).state


def test_a_run_that_died_holding_the_lock_is_marked_crashed(captured, tmp_path):
    out = tmp_path / "cal"
    out.mkdir()
    dead = _a_running_campaign("killed")
    # what a killed campaign leaves: its record in the lock file (the kernel dropped the
    # lock itself), a half-written capture in the cache
    (out / ".lock").write_text(json.dumps({"id": str(dead), "name": "killed",
                                           "pid": 999_999_999}))
    half = out / "cache" / ".abc.tmp-999999999"
    half.mkdir(parents=True)
    after = _state_after_the_next_campaign(captured, out, dead)
    assert after.type.value == "CRASHED" and "died holding" in after.message
    assert not half.exists()


def test_a_run_killed_while_waiting_for_the_lock_is_marked_crashed(captured, tmp_path):
    import socket
    import threading

    from flows.common import exclusive

    out = tmp_path / "cal"
    out.mkdir()
    # a waiter says so while it waits, and takes its record away when it gets the lock
    got = threading.Event()

    def wait_for_it():
        with exclusive(out, 30):
            got.set()

    with exclusive(out, 0):
        t = threading.Thread(target=wait_for_it)
        t.start()
        for _ in range(100):
            if (out / f".lock.wait-{os.getpid()}").exists():
                break
            time.sleep(0.05)
        assert (out / f".lock.wait-{os.getpid()}").exists()
    t.join(10)
    assert got.is_set() and not (out / f".lock.wait-{os.getpid()}").exists()

    # what a campaign killed while waiting leaves: its record, its process gone
    dead = _a_running_campaign("killed-waiting")
    (out / ".lock.wait-999999999").write_text(json.dumps(
        {"id": str(dead), "name": "killed-waiting", "pid": 999_999_999,
         "host": socket.gethostname()}))
    after = _state_after_the_next_campaign(captured, out, dead)
    assert after.type.value == "CRASHED" and "died waiting for" in after.message
    assert not (out / ".lock.wait-999999999").exists()


def test_leftovers_of_dead_processes_go_and_the_cache_stays_bounded(tmp_path):
    from flows.common import clean_leftovers, prune_cache

    dead = tmp_path / ".k1.tmp-999999999"
    mine = tmp_path / f".k2.tmp-{os.getpid()}"  # a live process's: left alone
    for p in (dead, mine):
        p.mkdir()
        (p / "x.bin").write_bytes(b"0" * 100)
    (tmp_path / ".current.link-0a1b").symlink_to("nowhere")
    assert sorted(Path(p).name for p in clean_leftovers(tmp_path)) == [
        ".current.link-0a1b", ".k1.tmp-999999999"]
    assert mine.exists()

    now = time.time()
    for i, (age_days, size) in enumerate([(40, 10), (3, 600), (2, 600), (1, 600)]):
        e = tmp_path / f"e{i}"
        e.mkdir()
        (e / "words.bin").write_bytes(b"0" * size)
        os.utime(e, (now - age_days * 86400,) * 2)
    # e0 too old; then the least recently used until <= 1300 bytes remain; e1 is in use
    dropped = prune_cache(tmp_path, max_gb=1300e-9, max_age_days=30, keep={"e1"})
    assert dropped == ["e0", "e2"]
    assert sorted(p.name for p in tmp_path.iterdir() if not p.name.startswith(".")) == [
        "e1", "e3"]


def test_a_pruned_cache_entry_is_remade_not_returned(campaign, tmp_path):
    """Prefect's record of a cached capture outlives the capture when the cache is pruned:
    the flow notices and simulates it again."""
    import shutil

    from flows.calibration import calibration_campaign

    out, r = campaign
    first = Path(r["captures"]["density"][0])
    shutil.rmtree(first.parent)
    state = calibration_campaign(out=str(out), **SMALL_CAL, return_state=True)
    assert state.is_completed() and first.with_suffix(".json").exists()


def test_parameters_are_checked_before_a_run_and_printed_intact():
    from click.testing import CliRunner

    from pipeline.cli.app import cli

    res = CliRunner().invoke(cli, ["flow", "run", "calibration_campaign", "-p", "cycles=-5",
                                   "-p", "lux=[100]", "-p", "inl_rms=0"])
    assert res.exit_code == 2
    msg = " ".join(res.output.split())
    assert "cycles: Input should be greater than 0" in msg
    assert "lux: List should have at least 4 items" in msg and "inl_rms" in msg


def test_a_project_error_keeps_its_brackets(monkeypatch, capsys):
    from pipeline.cli import app
    from schemas.errors import CalibrationError

    def boom(*_):
        raise CalibrationError("invalid [0, 3] for TDCs [range]")

    monkeypatch.setattr(app.cli, "invoke", boom)
    monkeypatch.setattr("sys.argv", ["tcspc", "schema"])
    with pytest.raises(SystemExit) as exc:
        app._main()
    assert exc.value.code == 2
    assert "invalid [0, 3] for TDCs [range]" in capsys.readouterr().err


def test_serve_reads_its_config(tmp_path):
    import click

    from flows.cli import deployments, read_serve_config

    cfg = tmp_path / "serve.toml"
    cfg.write_text('out = "lab"\n[calibration]\ncron = "30 1 * * *"\ntags = ["bench-1"]\n'
                   'timezone = "Europe/Berlin"\n'
                   '[calibration.parameters]\nlux = [50, 200, 900, 2000, 4000]\n'
                   'cycles = 250000\nn_pixels = 64\n[sweep]\ncron = "0 4 * * 0"\n')
    deps = {d.flow_name: d for d in deployments(read_serve_config(str(cfg)))}
    cal = deps["calibration_campaign"]
    assert cal.name == "64px daily at 01:30" and cal.tags == ["calibration", "bench-1"]
    assert cal.parameters == {"out": "lab/calibration", "lux": [50, 200, 900, 2000, 4000],
                              "cycles": 250000, "n_pixels": 64}
    assert cal.schedules[0].schedule.cron == "30 1 * * *"
    assert cal.schedules[0].schedule.timezone == "Europe/Berlin"
    # #39.6: one at a time, and a run due meanwhile (a downtime's Late runs) cancelled
    assert cal.concurrency_limit == 1
    assert cal.concurrency_options.collision_strategy.value == "CANCEL_NEW"
    assert deps["distance_sweep"].concurrency_options.collision_strategy.value == "CANCEL_NEW"
    assert deps["distance_sweep"].name == "128px Sundays at 04:00"
    assert deps["speed_vs_error"].name == "on demand" and not deps["speed_vs_error"].schedules
    # the command line overrides the file
    over = read_serve_config(str(cfg), calibration_cron="* * * * *", out="elsewhere")
    assert over["calibration"]["cron"] == "* * * * *" and over["out"] == "elsewhere"

    for text, says in [('[calibration]\ncron = "0 2 * *"\n', "not a cron expression"),
                       ('[calibration]\ncron = "0 2 * * *"\ncolour = 1\n', "colour"),
                       ('[calibrate]\ncron = "0 2 * * *"\n', "calibrate"),
                       ('[sweep]\ncron = "0 2 * * *"\ntimezone = "Mars/Olympus"\n',
                        "not a time zone"),
                       ('[calibration]\ncron = "0 2 * * *"\n[calibration.parameters]\n'
                        'cycles = 0\n', "cycles: Input should be greater than 0")]:
        cfg.write_text(text)
        with pytest.raises(click.UsageError, match=says):
            deployments(read_serve_config(str(cfg)))


def test_pruning_keeps_the_newest_versions_by_their_own_time_not_mtime(tmp_path):
    """#39.2: versions copied from the cache carry old mtimes (the newest looks oldest
    here); pruning keeps the KEEP_VERSIONS newest by the stamp in their name, and the live
    one always."""
    from flows.calibration import KEEP_VERSIONS, publish, version_time

    cand = tmp_path / "cand"
    cand.mkdir()
    (cand / "meta.json").write_text('{"created": "2026-12-04T20:00:00+00:00"}')
    stamps = [f"20261204T20{h}000Z-abc{h}" for h in range(8)]
    for i, s in enumerate(stamps):
        publish.fn(str(cand), str(tmp_path / "out"), s)
        os.utime(tmp_path / "out" / "versions" / s, (1e9 - i * 1e5, 1e9 - i * 1e5))
    kept = sorted(p.name for p in (tmp_path / "out" / "versions").iterdir())
    assert kept == stamps[-KEEP_VERSIONS:]
    assert (tmp_path / "out" / "current").resolve().name == stamps[-1]
    assert version_time(cand) == "20261204T200000Z"  # no stamp in the name: meta's created


def test_every_flow_has_a_timeout():
    """#39.6: a hung batch, prediction or grid (every Dask worker dead) ends Failed by
    Prefect's timeout, never Running forever."""
    from flows.cli import FLOWS, load

    for name in FLOWS:
        if name != "smoke":
            assert load(name).timeout_seconds and load(name).timeout_seconds <= 12 * 3600, name


def test_parameters_are_parsed_the_way_a_user_types_them():
    """#39.7: ``-p delay_run=0`` is the run named "0" (a string parameter), numbers stay
    numbers where the type is numeric, lists are JSON; a bad value is still refused."""
    import click

    from flows.cli import check_params, load, parse_params

    fl = load("calibration_campaign")
    got = parse_params(("delay_run=0", "cycles=1000", "lux=[1,2,3,4]", "force=true",
                        "density_runs=[\"123\"]"), fl.fn)
    assert got == {"delay_run": "0", "cycles": 1000, "lux": [1, 2, 3, 4], "force": True,
                   "density_runs": ["123"]}
    check_params(fl, got, "-p")
    with pytest.raises(click.UsageError, match="cycles"):
        check_params(fl, parse_params(("cycles=-1",), fl.fn), "-p")


def test_two_benches_get_distinct_artifact_keys_and_resource_ids(tmp_path):
    """#39.5: benchA/data/calibration and benchB/data/calibration, or two long paths alike
    at their end, never share an artifact key (nor the event's resource id made of it)."""
    import re

    from flows.calibration import _slug

    keys = {_slug(str(tmp_path / b / "data" / "calibration")) for b in ("benchA", "benchB")}
    keys |= {_slug(str(tmp_path / ("x" * 50 + b) / "data" / "calibration")) for b in "ab"}
    assert len(keys) == 4
    assert all(re.fullmatch(r"[a-z0-9-]{1,60}", k) for k in keys)
    assert _slug(str(tmp_path / "benchA" / "data" / "calibration")) in keys  # stable


def test_a_run_prefect_already_marked_crashed_has_its_running_tasks_marked_too():
    """#39.5: serve's runner marks its killed child Crashed but leaves the task that was
    running Running; the next campaign's clean-up marks that task Crashed as well."""
    from prefect import task
    from prefect.states import Crashed, Running

    from flows.common import mark_crashed

    @task(name="fit INL and LSB")
    def fit():
        return 1

    with _client() as c:
        f = c.create_flow_run(flow=_flow_for_crash_test(), state=Running())
        t = c.create_task_run(fit, f.id, dynamic_key="0", state=Running())
        c.set_flow_run_state(f.id, Crashed(message="killed"), force=True)
        assert mark_crashed(str(f.id), "its process died")
        assert c.read_task_run(t.id).state.type.value == "CRASHED"
        assert c.read_flow_run(f.id).state.message == "killed"  # its own word kept
        assert not mark_crashed(str(f.id), "again")  # nothing left to mark


def _flow_for_crash_test():
    from prefect import flow

    @flow(name="crash-test")
    def crash_test():
        return None

    return crash_test


BAD_PARAMETERS = [
    ("batch", "op=bogus", "op"), ("performance_prediction", "runs=-1", "runs"),
    ("performance_prediction", "configs=[99]", "configs"),
    ("speed_vs_error", "pixels=0", "pixels"),
    ("speed_vs_error", 'estimators=["nope"]', "estimators"),
    ("distance_sweep", "estimator=bogus", "estimator"),
    ("batch", "inputs=/nonexistent/captures", "inputs=/nonexistent/captures"),
    ("calibration_campaign", "captures=/nonexistent/caps", "captures"),
    ("calibration_campaign", "journal=/nonexistent/journal", "journal"),
    ("distance_sweep", "calibration=/nonexistent/cal", "calibration"),
    ("distance_sweep", "stream=/nonexistent/stream", "no such file")]

#: `tcspc flow run NAME -p PARAM` for each case, each in a process of its own forked from
#: one that imported the command once (a start-up with Prefect's imports is 4-6 s on the
#: loaded 2-core VM, 11 of them a minute): the child's own stderr (fd 2) and exit status
_FORKED_RUNS = r"""
import json, os, sys
from flows.cli import FLOWS, load
from pipeline.cli.app import main
for n in FLOWS:  # (the flows' modules and their imports, before the forks)
    load(n)
out = []
for i, (name, param) in enumerate(json.loads(sys.argv[1])):
    err = os.path.join(sys.argv[2], f"{i}.err")
    pid = os.fork()
    if pid == 0:
        os.dup2(os.open(err, os.O_WRONLY | os.O_CREAT | os.O_TRUNC), 2)
        sys.argv = ["tcspc", "flow", "run", name, "-p", param]
        code = 1
        try:
            main()
            code = 0
        except SystemExit as e:
            code = e.code if isinstance(e.code, int) else 1
        except BaseException:
            import traceback
            traceback.print_exc()
        finally:
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(code)
    _, status = os.waitpid(pid, 0)
    with open(err) as f:
        out.append([os.waitstatus_to_exitcode(status), f.read()])
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def bad_parameter_runs(tmp_path_factory):
    import subprocess
    import sys

    d = tmp_path_factory.mktemp("bad-parameters")
    r = subprocess.run([sys.executable, "-c", _FORKED_RUNS,
                        json.dumps([[name, param] for name, param, _ in BAD_PARAMETERS]),
                        str(d)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr
    return dict(zip([(name, param) for name, param, _ in BAD_PARAMETERS],
                    json.loads(r.stdout.splitlines()[-1]), strict=True))


@pytest.mark.parametrize("name, param, word", BAD_PARAMETERS)
def test_a_bad_parameter_is_refused_before_a_run_in_one_line_exit_2(bad_parameter_runs, name,
                                                                     param, word):
    """#39.7: what made a run and a long traceback is one line naming the parameter, exit
    2, and no flow run (the check comes before the flow is called)."""
    code, stderr = bad_parameter_runs[name, param]
    assert code == 2, stderr
    errs = [ln for ln in stderr.splitlines() if ln.lower().startswith("error")]
    assert len(errs) == 1 and f"{word}" in errs[0], stderr
    assert "Traceback" not in stderr and "running " not in stderr  # no run created


def test_a_candidate_that_fails_the_inl_check_is_a_refusal_with_its_report(captured, tmp_path):
    """#39.5: the captures cannot reach the INL asked: not a Failed run but a refusal, with
    its reason, report, summary and artifacts, and exit 3 from the command line."""
    from click.testing import CliRunner
    from prefect.client.schemas.filters import ArtifactFilter, FlowRunFilter

    from pipeline.cli.app import cli

    out = tmp_path / "cal"
    res = CliRunner().invoke(cli, ["flow", "run", "calibration_campaign", "-p", f"out={out}",
                                   "-p", f"captures={captured}", "-p", "inl_rms=0.01"])
    assert res.exit_code == 3, res.output
    r = json.loads(res.stdout)
    assert r["outcome"] == "refused" and r["rule"] == "quality" and not r["published"]
    assert "INL error" in r["refused_because"][0] and "> 0.01" in r["why"]
    assert "calibration_campaign: Completed refused" in res.output
    assert not (out / "current").exists()
    run = Path(r["run"])
    assert "Not published" in (run / "report.md").read_text()
    assert json.loads((run / "summary.json").read_text())["outcome"] == "refused"
    with _client() as c:
        fr = c.read_flow_run(r["flow_run"]["id"])
        arts = c.read_artifacts(flow_run_filter=FlowRunFilter(id={"any_": [fr.id]}),
                                artifact_filter=ArtifactFilter())
    assert fr.state.name == "Completed" and "tcspc:refused" in fr.tags
    assert {a.key.rsplit("-", 1)[1] for a in arts} == {"report", "figures", "flagged"}


def test_a_run_waiting_for_the_lock_says_so(captured, tmp_path):
    """#39.5: a campaign waiting on its directory's lock shows a Running-type state named
    AwaitingLock (not plain Running for up to wait_s), then Running, then Completed."""
    from prefect.client.schemas.filters import FlowRunFilter

    from flows.calibration import calibration_campaign
    from flows.common import AWAITING_LOCK, exclusive

    out = tmp_path / "cal"
    states = []
    with exclusive(out, 0):
        t = threading.Thread(target=lambda: states.append(calibration_campaign(
            out=str(out), captures=str(captured), inl_rms=1.0, wait_s=60,
            return_state=True)))
        t.start()
        deadline, waiting = time.monotonic() + 60, []
        while not waiting and time.monotonic() < deadline:
            with _client() as c:
                waiting = c.read_flow_runs(flow_run_filter=FlowRunFilter(
                    state={"name": {"any_": [AWAITING_LOCK]}}))
            time.sleep(0.3)
        assert len(waiting) == 1 and waiting[0].state.type.value == "RUNNING"
    t.join(120)
    (state,) = states
    assert state.name == "Completed" and state.result()["published"]
    with _client() as c:
        assert c.read_flow_run(waiting[0].id).state.name == "Completed"


def test_nightly_refusals_end_in_a_publish_once_the_current_calibration_is_old(captured,
                                                                              tmp_path):
    """#39.3: one long campaign, then shorter nightly ones (worse INL): refused while the
    long one is young, published by the age rule once it is older than max_age_h (time
    passing: its meta.json's `created` moved back), the report saying which rule won."""
    from flows.calibration import calibration_campaign

    out = tmp_path / "cal"
    first = calibration_campaign(out=str(out), captures=str(captured), inl_rms=5.0,
                                 max_age_h=24)
    assert first["rule"] == "first"
    nightly = {**SMALL_CAL, "cycles": 80_000, "inl_rms": 5.0, "max_age_h": 24}
    for _ in range(2):
        r = calibration_campaign(out=str(out), **nightly)
        assert r["outcome"] == "refused" and r["rule"] == "quality", r["why"]
        assert r["drift_ps"]["lsb"] < 0.5 and r["age_h"] < 1  # the same chip, young
    meta = out / "current" / "meta.json"
    m = json.loads(meta.read_text())
    m["created"] = "2020-01-01T00:00:00+00:00"
    meta.write_text(json.dumps(m))
    r = calibration_campaign(out=str(out), **nightly)
    assert r["outcome"] == "published" and r["rule"] == "age", r["why"]
    assert r["overruled"] and not r["forced"]  # what the age rule overruled
    assert "replaced although the candidate is worse" in r["why"]
    assert "rule age" in (Path(r["run"]) / "report.md").read_text()
    assert r["age_h"] > 24


def test_a_drifted_chip_is_recalibrated_by_a_worse_candidate(campaign, tmp_path):
    """#39.3: a candidate worse in quality but of a chip that moved (another chip: its
    LSBs and delays differ) replaces a young current calibration by the drift rule; with
    the drift limits wide, the quality rule refuses it."""
    from flows.calibration import calibration_campaign, verdict

    out, _ = campaign
    other = calibration_campaign(out=str(tmp_path / "other"), **{
        **SMALL_CAL, "cycles": 80_000, "inl_rms": 5.0, "chip_seed": 2})
    v = verdict.fn(other["candidate"], str(out / "current"), inl_rms=5.0)
    assert v["publish"] and v["rule"] == "drift" and v["worse"], v
    assert v["drift_ps"]["lsb"] > 0.5 or v["drift_ps"]["delay"] > 50
    wide = verdict.fn(other["candidate"], str(out / "current"), inl_rms=5.0,
                      max_lsb_drift_ps=1e9, max_delay_drift_ps=1e9)
    assert not wide["publish"] and wide["rule"] == "quality"
    strict = verdict.fn(other["candidate"], str(out / "current"), inl_rms=0.01)
    assert not strict["publish"] and strict["rule"] == "drift"  # not within the limits
    assert any("over the limit" in w for w in strict["worse"])


def test_the_streams_lsb_tracking_is_drift_evidence(campaign, tmp_path):
    """#39.3: a candidate of the same chip, worse and young, is refused on quality; when
    the daemon's range stage tracked the LSB away from the current calibration (its
    ranges files' ``tcspc.lsb_drift``, ranged with this calibration) beyond the limit by 3
    standard errors, the drift rule publishes it, and the verdict says it was the
    stream's; a tracking within its noise, or of another calibration, does not."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from flows.calibration import calibration_campaign, verdict
    from pipeline.io.caldir import load_calibration

    out, _ = campaign
    same = calibration_campaign(out=str(tmp_path / "night"), **{
        **SMALL_CAL, "cycles": 80_000, "inl_rms": 5.0})
    current = str(out / "current")
    cal_id = load_calibration(current).meta["calibration_id"]
    stream = tmp_path / "stream"

    def ranges(name, median, se, ident=cal_id):
        part = stream / "ranges" / "date=2026-12-05" / "run=r"
        part.mkdir(parents=True, exist_ok=True)
        t = pa.table({"tdc": pa.array([0], pa.uint16())}).replace_schema_metadata({
            b"tcspc.calibration_id": ident.encode(),
            b"tcspc.lsb_drift": json.dumps({"median_ps": median, "se_ps": se, "n": 100,
                                            "light": 0.05}).encode()})
        pq.write_table(t, part / f"part-{name}.parquet")

    base = verdict.fn(same["candidate"], current, inl_rms=5.0, stream_out=str(stream))
    assert not base["publish"] and base["rule"] == "quality", base
    assert base["stream_drift_ps"] is None and "no LSB tracking" in base["why"]
    ranges("a", 0.8, 0.5)  # past the 0.5 ps limit, but within 3 of its errors
    noisy = verdict.fn(same["candidate"], current, inl_rms=5.0, stream_out=str(stream))
    assert not noisy["publish"] and noisy["stream_drift_ps"]["files"] == 1, noisy
    ranges("b", 2.0, 0.1, ident="another-calibration")  # not this calibration's
    other = verdict.fn(same["candidate"], current, inl_rms=5.0, stream_out=str(stream))
    assert not other["publish"] and other["stream_drift_ps"]["files"] == 1
    ranges("c", 2.0, 0.1)
    moved = verdict.fn(same["candidate"], current, inl_rms=5.0, stream_out=str(stream))
    assert moved["publish"] and moved["rule"] == "drift", moved
    assert moved["stream_drift_ps"]["files"] == 2 and moved["stream_drift_ps"]["lsb"] > 1.5
    assert "the stream's LSB tracking +1.9" in moved["why"], moved["why"]
