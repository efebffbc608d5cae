"""The campaign against a real local Prefect server (`prefect server start` on 127.0.0.1,
a free port), as a lab runs it unattended: a kill -9 mid-run and the rerun that resumes
from Prefect's cache and marks the dead run Crashed; two campaigns started at once; the
served schedule, stopped by Ctrl-C (SIGINT). Slow: a server start and real processes."""

import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
TCSPC = [sys.executable, "-c", "from pipeline.cli.app import main; main()"]
SMALL = ["-p", "n_pixels=4", "-p", "cycles=150000", "-p", "delay_cycles=100000",
         "-p", "lux=[100,400,1200,2500,3500]", "-p", "inl_rms=1.0"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    home = tmp_path_factory.mktemp("prefect-home")
    port = _free_port()
    url = f"http://127.0.0.1:{port}/api"
    env = {**os.environ, "PREFECT_HOME": str(home), "PREFECT_API_URL": url,
           "PREFECT_LOCAL_STORAGE_PATH": str(home / "results"),
           "PREFECT_SERVER_ANALYTICS_ENABLED": "false", "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen([sys.executable, "-m", "prefect", "server", "start", "--host",
                             "127.0.0.1", "--port", str(port)], env=env, cwd=home,
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 180
        while True:
            try:
                with urllib.request.urlopen(f"{url}/health", timeout=2) as r:
                    if r.status == 200:
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"prefect server did not start on {url}")
            time.sleep(0.5)
        yield env
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()


def _api(env, method: str, path: str, body: dict | None = None):
    req = urllib.request.Request(env["PREFECT_API_URL"] + path, method=method,
                                 data=json.dumps(body or {}).encode(),
                                 headers={"Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=30) as r:
        return json.loads(r.read() or b"null")


def _runs(env, flow_name="calibration_campaign") -> list[dict]:
    return _api(env, "POST", "/flow_runs/filter",
                {"flows": {"name": {"any_": [flow_name]}}, "limit": 200})


def _task_states(env, run_id: str) -> dict:
    trs = _api(env, "POST", "/task_runs/filter",
               {"flow_runs": {"id": {"any_": [run_id]}}, "limit": 200})
    return {t["name"]: t["state"]["name"] for t in trs}


def _events(env, out: str, wait_s: float = 30) -> list[dict]:
    """The tcspc.calibration.* events about campaigns on ``out`` (the server stores events
    a moment after it receives them: polled)."""
    deadline = time.monotonic() + wait_s
    while True:
        ev = _api(env, "POST", "/events/filter", {"filter": {
            "event": {"prefix": ["tcspc.calibration."]},
            "occurred": {"since": "2020-01-01T00:00:00Z"}}, "limit": 50})
        mine = [e for e in ev["events"] if e["payload"]["run"].startswith(out)]
        if mine or time.monotonic() > deadline:
            return mine
        time.sleep(0.5)


def _campaign(env, out, *extra):
    return subprocess.Popen([*TCSPC, "flow", "run", "calibration_campaign", "-p",
                             f"out={out}", *SMALL, *extra], env=env, cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def test_a_killed_run_is_marked_crashed_and_the_rerun_resumes(server, tmp_path_factory):
    out = tmp_path_factory.mktemp("killed") / "cal"
    made = subprocess.run([*TCSPC, "flow", "automations", "--create", "--out", str(out)],
                          env=server, cwd=ROOT, capture_output=True, text=True)
    assert made.returncode == 0, made.stderr
    crashed = next(a["id"] for a in _api(server, "POST", "/automations/filter", {})
                   if a["name"].startswith("tcspc campaign crashed"))
    proc = _campaign(server, out)
    deadline = time.monotonic() + 300
    # kill -9 once the fit is under way: it starts when all six captures are made and
    # their results recorded (a capture killed before its record is reused from disk by
    # the rerun, without the Cached state)
    while not list((out / "cache").glob("*fit-*")):
        assert proc.poll() is None, proc.communicate()
        assert time.monotonic() < deadline, "the fit never started"
        time.sleep(0.02)
    proc.kill()
    proc.wait()
    (dead,) = _runs(server)
    assert dead["state"]["type"] == "RUNNING"  # nobody told the API
    rerun = _campaign(server, out)
    _, err = rerun.communicate(timeout=600)
    assert rerun.returncode == 0, err
    runs = {r["id"]: r for r in _runs(server)}
    assert runs[dead["id"]]["state"]["type"] == "CRASHED"
    assert not [t for t in _task_states(server, dead["id"]).values()
                if t in ("Running", "Pending")]
    (new,) = [r for r in runs.values() if r["id"] != dead["id"]]
    assert new["state"]["name"] == "Completed" and "tcspc:published" in new["tags"]
    states = _task_states(server, new["id"])
    sims = [s for name, s in states.items() if name.startswith("simulate ")]
    assert len(sims) == 6 and set(sims) == {"Cached"}, states  # resumed, not redone
    assert not list((out / "cache").glob(".*.tmp-*"))  # the killed run's leftovers
    assert (out / "current" / "meta.json").is_file()
    # the event an automation triggers on, about this calibration
    (pub,) = _events(server, str(out))
    assert pub["event"] == "tcspc.calibration.published"
    assert pub["resource"]["prefect.resource.name"] == str(out.resolve())
    # the dead run marked Crashed fired the lab's crashed automation (#39.4)
    assert _poll_events(server, "prefect.automation.triggered",
                        lambda e: e["resource"]["prefect.resource.id"].endswith(crashed))


def test_two_campaigns_started_at_once_take_turns(server, tmp_path_factory):
    out = tmp_path_factory.mktemp("overlap") / "cal"
    sys.path.insert(0, str(ROOT))
    from flows.common import exclusive

    # the lock held here until both wait for it (two processes' start-up times differ by
    # more than a small campaign lasts on a loaded machine: they might never overlap)
    with exclusive(out, 0):
        a, b = _campaign(server, out), _campaign(server, out)
        deadline = time.monotonic() + 300
        while len(list(out.glob(".lock.wait-*"))) < 2:
            assert a.poll() is None and b.poll() is None, (a.communicate(), b.communicate())
            assert time.monotonic() < deadline, "the campaigns never waited"
            time.sleep(0.2)
    results = [p.communicate(timeout=900) for p in (a, b)]
    assert a.returncode == 0 and b.returncode == 0, results
    assert all("waiting for run" in err for _, err in results)
    outs = [json.loads(o) for o, _ in results]
    # a run waiting for the lock says so (#39.5): a Running state named AwaitingLock in
    # its history, then Running once it holds the lock, then Completed
    for o in outs:
        hist = [(st["type"], st["name"]) for st in sorted(_api(
            server, "GET", f"/flow_run_states/?flow_run_id={o['flow_run']['id']}"),
            key=lambda st: st["timestamp"])]
        assert hist[-3:] == [("RUNNING", "AwaitingLock"), ("RUNNING", "Running"),
                             ("COMPLETED", "Completed")], hist
    assert all(o["published"] for o in outs)
    assert len(list((out / "versions").iterdir())) == 2
    assert (out / "current").is_symlink() and (out / "current" / "meta.json").is_file()


def test_the_served_schedule_runs_and_ctrl_c_stops_it(server, tmp_path_factory):
    tmp = tmp_path_factory.mktemp("served")
    cfg = tmp / "serve.toml"
    cfg.write_text(f'out = "{tmp / "data"}"\n[calibration]\ncron = "* * * * *"\n'
                   'tags = ["bench-test"]\n[calibration.parameters]\nn_pixels = 4\n'
                   'cycles = 150000\ndelay_cycles = 100000\ninl_rms = 1.0\n'
                   'lux = [100, 400, 1200, 2500, 3500]\n')
    serve = subprocess.Popen([*TCSPC, "flow", "serve", "--unauthenticated", "--config", str(cfg)],
                             env=server,
                             cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    try:
        deadline = time.monotonic() + 300
        done = None
        while done is None:
            assert serve.poll() is None, serve.communicate()
            assert time.monotonic() < deadline, "no scheduled run completed"
            deps = _api(server, "POST", "/deployments/filter", {})
            mine = [d for d in deps if d["name"] == "4px every minute"]
            if mine:
                runs = _api(server, "POST", "/flow_runs/filter", {
                    "deployments": {"id": {"any_": [mine[0]["id"]]}}})
                done = next((r for r in runs if r["state"]["name"] == "Completed"
                             and "tcspc:published" in r["tags"]), None)
            time.sleep(2)
        assert "bench-test" in mine[0]["tags"] and "calibration" in mine[0]["tags"]
        # a run with a broken parameter is refused at creation, naming it
        with pytest.raises(urllib.error.HTTPError) as bad:
            _api(server, "POST", f"/deployments/{mine[0]['id']}/create_flow_run",
                 {"parameters": {"cycles": -5}})
        assert "cycles" in bad.value.read().decode()
        assert done["name"].startswith("campaign ") and done["name"].endswith(" 4px")
        assert (tmp / "data" / "calibration" / "current" / "meta.json").is_file()
        serve.send_signal(signal.SIGINT)
        _, err = serve.communicate(timeout=60)
    finally:
        if serve.poll() is None:
            serve.kill()
            serve.wait()
    assert serve.returncode == 0, err
    assert "serve stopped" in err
    # nothing of ours is left running
    runs = _api(server, "POST", "/flow_runs/filter", {
        "deployments": {"id": {"any_": [mine[0]["id"]]}}})
    assert not [r for r in runs if r["state"]["type"] in ("RUNNING", "PENDING")]


def test_a_downtimes_late_runs_make_one_catch_up_run(server, tmp_path):
    """#39.6: the served campaign's deployment as `deployments()` builds it, on a real
    server; three Late runs of it start together (what `serve` does on restart): the first
    gets the slot, the others end Cancelled instead of running back to back."""
    sys.path.insert(0, str(ROOT))
    from flows.cli import deployments, read_serve_config

    (dep,) = [d for d in deployments(read_serve_config(None, out=str(tmp_path)))
              if d.flow_name == "calibration_campaign"]
    flow_id = _api(server, "POST", "/flows/", {"name": "calibration_campaign"})["id"]
    dep_id = _api(server, "POST", "/deployments/", {
        "name": "catch-up", "flow_id": flow_id, "concurrency_limit": dep.concurrency_limit,
        "concurrency_options": {
            "collision_strategy": dep.concurrency_options.collision_strategy.value}})["id"]
    late = {"type": "SCHEDULED", "name": "Late",
            "state_details": {"scheduled_time": "2026-01-01T02:00:00Z"}}
    runs = [_api(server, "POST", f"/deployments/{dep_id}/create_flow_run", {"state": late})
            ["id"] for _ in range(3)]

    def to(run, kind):
        return _api(server, "POST", f"/flow_runs/{run}/set_state",
                    {"state": {"type": kind}})

    assert to(runs[0], "PENDING")["status"] == "ACCEPT"
    assert to(runs[0], "RUNNING")["status"] == "ACCEPT"
    for r in runs[1:]:
        to(r, "PENDING")
        assert _api(server, "GET", f"/flow_runs/{r}")["state"]["type"] == "CANCELLED"
    assert _api(server, "GET", f"/flow_runs/{runs[0]}")["state"]["type"] == "RUNNING"


#: Prefect's documented "detect zombie flows" automation's trigger: a flow run that sent a
#: heartbeat is a zombie unless one of these follows within 90 s
ZOMBIE_EXPECT = {"prefect.flow-run.heartbeat", "prefect.flow-run.Completed",
                 "prefect.flow-run.Failed", "prefect.flow-run.Cancelled",
                 "prefect.flow-run.Crashed"}


def _poll_events(env, prefix: str, keep, wait_s: float = 60) -> list[dict]:
    deadline = time.monotonic() + wait_s
    while True:
        ev = _api(env, "POST", "/events/filter", {"filter": {
            "event": {"prefix": [prefix]},
            "occurred": {"since": "2020-01-01T00:00:00Z"}}, "limit": 50})["events"]
        mine = [e for e in ev if keep(e)]
        if mine or time.monotonic() > deadline:
            return mine
        time.sleep(1)


def test_the_lab_automations_exist_and_a_refusal_fires_its_own(server, tmp_path):
    """#39.4: `tcspc flow automations --create` makes the three on a real server (again:
    replaced, not doubled); a refused campaign ends Completed with the verdict in its tag,
    result and event, and that event fires the refused automation (the server's
    prefect.automation.triggered), not the crashed one; the run's state event is
    prefect.flow-run.Completed, which Prefect's zombie automation expects."""
    out = tmp_path / "cal"
    cmd = [*TCSPC, "flow", "automations", "--create", "--out", str(out), "--stale-hours", "2"]
    for _ in range(2):
        made = subprocess.run(cmd, env=server, cwd=ROOT, capture_output=True, text=True)
        assert made.returncode == 0, made.stderr
    sys.path.insert(0, str(ROOT))
    from flows.calibration import _slug

    mine = [a for a in _api(server, "POST", "/automations/filter", {})
            if a["name"].endswith(f"({_slug(str(out))})")]
    autos = {a["name"].split(" (")[0]: a for a in mine}
    assert len(mine) == 3 and set(autos) == {
        "tcspc campaign refused", "tcspc campaign crashed", "tcspc calibration stale"}
    stale = autos["tcspc calibration stale"]["trigger"]
    assert stale["posture"] == "Proactive" and stale["within"] == 7200
    zombie = _api(server, "POST", "/automations/", {
        "name": "Crash zombie flows", "trigger": {
            "type": "event", "posture": "Proactive", "after": ["prefect.flow-run.heartbeat"],
            "expect": sorted(ZOMBIE_EXPECT), "for_each": ["prefect.resource.id"],
            "match": {"prefect.resource.id": ["prefect.flow-run.*"]}, "threshold": 1,
            "within": 90}, "actions": [{"type": "do-nothing"}]})["id"]
    # a current calibration that cannot be read: the campaign refuses (the quickest refusal)
    (out / "current").mkdir(parents=True)
    (out / "current" / "tdc.parquet").write_bytes(b"left by hand")
    proc = _campaign(server, out)
    stdout, err = proc.communicate(timeout=600)
    assert proc.returncode == 3, err
    result = json.loads(stdout)
    assert result["outcome"] == "refused" and result["rule"] == "unreadable"
    run = _api(server, "GET", f"/flow_runs/{result['flow_run']['id']}")
    assert run["state"]["type"] == "COMPLETED" and run["state"]["name"] == "Completed"
    assert "tcspc:refused" in run["tags"]
    (ev,) = _events(server, str(out))
    assert ev["event"] == "tcspc.calibration.refused" and ev["payload"]["rule"] == "unreadable"
    fired = _poll_events(server, "prefect.automation.triggered",
                         lambda e: e["resource"]["prefect.resource.id"].endswith(
                             autos["tcspc campaign refused"]["id"]))
    assert fired, "the refused automation did not fire"
    crashed = autos["tcspc campaign crashed"]["id"]
    assert not [e for e in _poll_events(server, "prefect.automation.triggered", lambda e: True, 0)
                if e["resource"]["prefect.resource.id"].endswith(crashed)]
    states = _poll_events(server, "prefect.flow-run.", lambda e: e["resource"][
        "prefect.resource.id"] == f"prefect.flow-run.{run['id']}")
    names = {e["event"] for e in states}
    assert "prefect.flow-run.Completed" in names
    assert not names - {"prefect.flow-run.Pending", "prefect.flow-run.Running",
                        "prefect.flow-run.heartbeat", "prefect.flow-run.Completed"}, names
    # captures that cannot reach the INL asked (#39.5): a refusal too, with its event
    proc = _campaign(server, out, "-p", "inl_rms=0.01")
    stdout, err = proc.communicate(timeout=600)
    assert proc.returncode == 3, err
    assert json.loads(stdout)["rule"] == "quality"
    deadline = time.monotonic() + 30
    while len(evs := _events(server, str(out))) < 2 and time.monotonic() < deadline:
        time.sleep(0.5)
    assert sorted(e["payload"]["rule"] for e in evs) == ["quality", "unreadable"]
    assert all(e["event"] == "tcspc.calibration.refused" for e in evs)
    # the zombie automation, past its 90 s after the run's last heartbeat, did not fire
    time.sleep(100)
    assert not [e for e in _poll_events(server, "prefect.automation.triggered",
                                        lambda e: True, 0)
                if e["resource"]["prefect.resource.id"].endswith(zombie)]


def test_a_nightly_on_a_real_server_reads_the_streams_drift(server, tmp_path):
    """#39.3 (with #39.2, #39.7) as a lab runs it through `tcspc flow run` on a real
    server: a first campaign publishes; a shorter nightly one of the same chip, worse and
    young, is refused on quality (exit 3); once the daemon's ranges with the current
    calibration record an LSB tracked 2 ps away, the same nightly publishes by the drift
    rule (exit 0) and says it was the stream's; `current` is the newest of the versions by
    their own time; the report artifact on the server embeds its figures; a drift limit
    of -1 is refused before any run (exit 2)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    sys.path.insert(0, str(ROOT))
    from flows.calibration import _slug, version_time
    from pipeline.io.caldir import load_calibration

    out, stream = tmp_path / "cal", tmp_path / "stream"

    def run(*extra, code=0):
        proc = _campaign(server, out, *extra)
        stdout, err = proc.communicate(timeout=900)
        assert proc.returncode == code, err[-3000:]
        return json.loads(stdout) if code != 2 else err

    assert run()["outcome"] == "published"
    nightly = ("-p", "cycles=80000", "-p", "inl_rms=5.0", "-p", f"stream_out={stream}")
    refused = run(*nightly, code=3)
    assert refused["rule"] == "quality" and refused["stream_drift_ps"] is None
    part = stream / "ranges" / "date=2026-12-05" / "run=r"
    part.mkdir(parents=True)
    ident = load_calibration(out / "current").meta["calibration_id"]
    pq.write_table(pa.table({"tdc": pa.array([0], pa.uint16())}).replace_schema_metadata({
        b"tcspc.calibration_id": ident.encode(),
        b"tcspc.lsb_drift": json.dumps({"median_ps": 2.0, "se_ps": 0.1, "n": 4}).encode()}),
        part / "part-m1.parquet")
    moved = run(*nightly)
    assert moved["outcome"] == "published" and moved["rule"] == "drift", moved["why"]
    assert moved["stream_drift_ps"]["files"] == 1 and "stream's LSB tracking" in moved["why"]
    versions = sorted((out / "versions").iterdir(), key=version_time)
    assert (out / "current").resolve() == versions[-1].resolve()
    arts = _api(server, "POST", "/artifacts/filter",
                {"artifacts": {"key": {"any_": [f"{_slug(str(out))}-report"]}}})
    assert arts and all("data:image/png;base64," in a["data"] for a in arts)
    before = len(_runs(server))
    err = run("-p", "max_lsb_drift_ps=-1", code=2)
    assert "max_lsb_drift_ps" in err and len(_runs(server)) == before
