"""The graph placed on several hosts, as a service manager starts it (issue 25.4): every
stage its own process, started from the NAME.env that `tcspc stage plan` writes for the
systemd template (docs/systemd/tcspc-stage@.service), tcp:// endpoints on 127.0.0.1 with
CURVE on, no daemon; the datasets equal the single-host daemon's."""

import os
import socket
import subprocess
import sys
from pathlib import Path

import polars as pl
import pytest

CYCLES = 60_000


def _ports(n: int) -> list[int]:
    socks = [socket.socket() for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


def _on_tcp(topo: Path) -> Path:
    """The same topology with every endpoint tcp:// on 127.0.0.1 and CURVE on."""
    p = [f"tcp://127.0.0.1:{x}" for x in _ports(5)]
    text = topo.read_text()
    text = text.replace("restarts = 3", f'restarts = 3\ncurve = true\nmetrics = "{p[0]}"')
    text = text.replace("[histogram]\n", f'[histogram]\nendpoints = ["{p[1]}", "{p[2]}"]\n')
    text = text.replace("[range]\n", f'[range]\nendpoint = "{p[3]}"\n')
    text = text.replace("[sink]\n", f'[sink]\nendpoint = "{p[4]}"\n')
    topo.write_text(text)
    return topo


def _env_file(path: Path) -> dict:
    """KEY=VALUE lines, as systemd's EnvironmentFile reads them."""
    return dict(line.split("=", 1) for line in path.read_text().splitlines() if line)


def _frames(dataset, out: Path, run: str) -> tuple[pl.DataFrame, pl.DataFrame]:
    h = dataset(out, "histograms", run).drop("date", "run").sort("measurement", "tdc")
    r = dataset(out, "ranges", run).drop("date", "run").sort("measurement", "tdc")
    return h, r


@pytest.mark.slow
def test_stages_started_one_by_one_over_tcp_with_curve_give_the_daemons_datasets(
        tmp_path, caldir, daemon_helpers):
    _h = daemon_helpers
    (tmp_path / "one").mkdir()
    res, _ = _h.run_daemon(_h.topology(tmp_path / "one", caldir, cycles=CYCLES), "h")
    assert res["failed"] is None and res["accounting"]["balanced"]
    ref_h, ref_r = _frames(_h.dataset, tmp_path / "one" / "out", "h")

    d = tmp_path / "hosts"
    d.mkdir()
    topo = _on_tcp(_h.topology(d, caldir, cycles=CYCLES))
    units = d / "units"
    root = Path(__file__).parents[3]
    env = {**os.environ, "PYTHONPATH": str(root)}
    plan = subprocess.run([sys.executable, "-m", "pipeline.cli", "stage", "plan", "--config",
                           str(topo), "--run", "h", "--out", str(units)],
                          env=env, capture_output=True, text=True, timeout=120)
    assert plan.returncode == 0, plan.stderr
    assert "CURVE on" in plan.stderr
    names = [line.split(":")[0] for line in plan.stdout.splitlines()]
    assert names == ["sink", "range", "histogram-0", "histogram-1", "source"]
    procs = {}
    for name in names:  # sink first, source last, as the docs say to start them
        e = _env_file(units / f"{name}.env")
        assert e["TCSPC_CURVE_DIR"].endswith("curve") and "tcp://127.0.0.1:" in \
            e["TCSPC_STAGE_ARGS"]
        args = e.pop("TCSPC_STAGE_ARGS").split()  # systemd splits $VAR at white space
        with open(d / f"{name}.log", "wb") as log:
            procs[name] = subprocess.Popen(
                [sys.executable, "-m", "pipeline.cli", "stage", *args],
                env={**env, **e}, stdout=log, stderr=subprocess.STDOUT)
    try:
        codes = {n: p.wait(timeout=240) for n, p in procs.items()}
    finally:
        for p in procs.values():
            if p.poll() is None:
                p.kill()
    logs = {n: (d / f"{n}.log").read_text()[-2000:] for n in procs}
    assert codes == dict.fromkeys(names, 0), (codes, logs)
    got_h, got_r = _frames(_h.dataset, d / "out", "h")
    assert got_h.height == ref_h.height == CYCLES // 10_000 * _h.N
    assert got_h.equals(ref_h)
    assert got_r.height == ref_r.height and got_r.equals(ref_r)


def test_plan_writes_an_env_file_per_stage_and_refuses_what_systemd_would_split(
        tmp_path, daemon_helpers):
    """`tcspc stage plan`: a NAME.env per stage, sink first and source last, the token and
    CURVE keys made private in the state directory; a path with a space is refused."""
    from click.testing import CliRunner

    from pipeline.cli.app import cli

    topo = _on_tcp(daemon_helpers.topology(tmp_path, cycles=CYCLES))
    res = CliRunner().invoke(cli, ["stage", "plan", "--config", str(topo), "--run", "p",
                                   "--out", str(tmp_path / "units")])
    assert res.exit_code == 0, res.output
    envs = {p.stem: _env_file(p) for p in (tmp_path / "units").glob("*.env")}
    assert sorted(envs) == ["histogram-0", "histogram-1", "sink", "source"]
    assert envs["histogram-1"]["TCSPC_STAGE_ARGS"].startswith("histogram --pull tcp://")
    assert envs["source"]["TCSPC_STAGE_ARGS"].startswith("source-sim ")
    token = Path(envs["sink"]["TCSPC_TOKEN_FILE"])
    keys = Path(envs["sink"]["TCSPC_CURVE_DIR"])
    assert token.stat().st_mode & 0o777 == 0o600 and keys.stat().st_mode & 0o777 == 0o700
    assert (keys / "server.key_secret").exists()
    spaced = tmp_path / "a b"
    spaced.mkdir()
    topo.write_text(topo.read_text().replace(str(tmp_path / "out"), str(spaced / "out")))
    res = CliRunner().invoke(cli, ["stage", "plan", "--config", str(topo), "--run", "p",
                                   "--out", str(tmp_path / "units2")])
    assert res.exit_code != 0 and "white space" in res.output
    assert not (tmp_path / "units2").exists()  # nothing half written
