"""Issue 36, point 7: a stage started by hand, `stage plan` and the state directory, tried
as an attacker would (another account of the host, a peer on the network)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest


def _stage(*args, env=None, timeout=30):
    return subprocess.run([sys.executable, "-m", "pipeline.cli", "stage", *args],
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, **(env or {})})


@pytest.mark.parametrize("missing", ["both", "token", "keys"])
def test_a_tcp_stage_without_token_or_keys_refuses_to_start(tmp_path, missing):
    """Before: a sink on tcp:// without $TCSPC_TOKEN_FILE / $TCSPC_CURVE_DIR took anything
    (a forged sink got histograms and a stop). Now it exits 2 at once, naming both."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("TCSPC_TOKEN_FILE", "TCSPC_CURVE_DIR", "TCSPC_INSECURE")}
    token = tmp_path / "token"
    token.write_text("t" * 32)
    if missing == "keys":
        env["TCSPC_TOKEN_FILE"] = str(token)
    if missing == "token":
        env["TCSPC_CURVE_DIR"] = str(tmp_path)
    r = subprocess.run([sys.executable, "-m", "pipeline.cli", "stage", "sink", "--pull",
                        "tcp://127.0.0.1:1", "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=30, env=env)
    assert r.returncode == 2, r.stderr[-300:]
    assert "tcp://127.0.0.1:1: a tcp:// endpoint without" in r.stderr
    assert "--insecure" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "out").exists()


def test_insecure_lets_a_tcp_stage_start(tmp_path):
    """--insecure (the operator's choice) starts it: it then waits for input (killed)."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "stage", "--insecure",
                             "sink", "--pull", f"tcp://127.0.0.1:{port}", "--out",
                             str(tmp_path / "out")], stderr=subprocess.PIPE, text=True)
    try:
        import time

        deadline = time.time() + 60
        while time.time() < deadline:
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                assert proc.poll() is None, proc.stderr.read()[-300:]
                time.sleep(0.2)
        else:
            pytest.fail("the --insecure sink never bound its port")
    finally:
        proc.kill()
        proc.wait()


@pytest.mark.parametrize("run", ["../../escape", "..", "a/b", ""])
def test_a_run_id_that_leaves_the_journal_is_refused(tmp_path, run):
    """Before: `stage source-sim --run ../../escape` wrote its journal two levels up."""
    journal = tmp_path / "a" / "b" / "journal"
    scene = Path(__file__).parents[3] / "scenes" / "small16.toml"
    r = _stage("source-sim", str(scene), "--cycles", "10", "--push",
               f"ipc://{tmp_path}/x", "--journal", str(journal), "--run", run)
    assert r.returncode == 2 and "[A-Za-z0-9._-]" in r.stderr, r.stderr[-300:]
    assert list(tmp_path.rglob("*")) == []


def test_plan_makes_the_state_private(tmp_path, daemon_helpers):
    """Before: `stage plan` made the state directory 0755 and took one another account
    owned or could write."""
    from click.testing import CliRunner

    from pipeline.cli.app import cli

    topo = daemon_helpers.topology(tmp_path, cycles=100)
    old = os.umask(0o022)
    try:
        res = CliRunner().invoke(cli, ["stage", "plan", "--config", str(topo), "--run", "p",
                                       "--out", str(tmp_path / "units")])
    finally:
        os.umask(old)
    assert res.exit_code == 0, res.output
    state = tmp_path / "state"
    assert state.stat().st_mode & 0o777 == 0o700
    os.chmod(state, 0o777)
    res = CliRunner().invoke(cli, ["stage", "plan", "--config", str(topo), "--run", "p",
                                   "--out", str(tmp_path / "units"), "--overwrite"])
    # (one line, exit 2: the exit-code contract, docs/design.md)
    assert res.exit_code == 2 and "group- or world-writable" in res.output, res.output


def test_a_state_inside_another_accounts_folder_is_refused(tmp_path, other_account):
    """Before: a state directory inside a folder another user owns was taken: that user
    can rename it away mid-run and put their own in its place."""
    from pipeline.stream.state import StateError, open_state

    theirs = tmp_path / "theirs"
    theirs.mkdir()
    os.chown(theirs, other_account, -1)
    with pytest.raises(StateError, match=f"which uid {other_account} owns"):
        open_state(theirs / "state")
    shared = tmp_path / "shared"
    shared.mkdir()
    os.chmod(shared, 0o777)  # writable by all, no sticky bit
    with pytest.raises(StateError, match="no sticky bit"):
        open_state(shared / "state")
    os.chmod(shared, 0o1777)  # /tmp's mode: nobody may rename what is ours
    open_state(shared / "state").release()
