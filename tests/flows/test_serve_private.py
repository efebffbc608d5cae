"""Issue 36, point 2: `tcspc flow serve` on a shared host. Before, another account created a
served `distance_sweep` run whose out was theirs (the served process wrote the operator's
data there), and `flow serve` failed on a runner-storage folder another account had made
first at a fixed name under /tmp."""

from __future__ import annotations

import os

import pytest


def test_serve_refuses_a_server_without_authentication(tmp_path, monkeypatch):
    from click.testing import CliRunner

    from pipeline.cli.app import cli

    monkeypatch.setenv("PREFECT_API_URL", "http://127.0.0.1:9/api")
    monkeypatch.delenv("PREFECT_API_AUTH_STRING", raising=False)
    res = CliRunner().invoke(cli, ["flow", "serve", "--out", str(tmp_path)])
    assert res.exit_code == 2 and "PREFECT_API_AUTH_STRING is not set" in res.output


def test_a_served_run_outside_the_roots_is_refused(tmp_path, monkeypatch):
    from flows.common import ROOTS_ENV, OutsideRoots, new_run_dir

    mine, theirs = tmp_path / "mine", tmp_path / "theirs"
    monkeypatch.setenv(ROOTS_ENV, str(mine))
    with pytest.raises(OutsideRoots, match="outside the roots"):
        new_run_dir(theirs, "distance_sweep")
    with pytest.raises(OutsideRoots):
        new_run_dir(mine / ".." / "theirs", "distance_sweep")
    assert not theirs.exists()
    assert new_run_dir(mine / "sweeps", "distance_sweep").is_dir()
    # every path a served run reads is held to the roots too (issue 36: another account's
    # run named the operator's stream and wrote its ranges where that account reads them)
    with pytest.raises(OutsideRoots, match="stream = "):
        new_run_dir(mine / "sweeps", "distance_sweep", stream=theirs / "stream")
    with pytest.raises(OutsideRoots, match="calibration = "):
        new_run_dir(mine / "sweeps", "distance_sweep", calibration="/etc")
    assert new_run_dir(mine / "sweeps", "distance_sweep", stream=mine / "stream",
                       calibration=None).is_dir()


def test_a_served_batch_reads_nothing_outside_the_roots(tmp_path, monkeypatch):
    from flows.batch import batch
    from flows.common import ROOTS_ENV, OutsideRoots

    mine = tmp_path / "mine"
    monkeypatch.setenv(ROOTS_ENV, str(mine))
    with pytest.raises(OutsideRoots, match="inputs = "):
        batch.fn(inputs=str(tmp_path / "theirs"), out=str(mine / "batch"))
    assert not (mine / "batch").exists()


def test_the_runner_storage_is_private(tmp_path, monkeypatch):
    """Prefect's Runner storage lands in PREFECT_HOME/tmp (0700), not /tmp/runner_storage."""
    import tempfile

    from prefect.settings import PREFECT_HOME, temporary_settings

    from flows.cli import _private_tmp

    monkeypatch.setattr(tempfile, "tempdir", tempfile.tempdir)
    monkeypatch.setenv("TMPDIR", os.environ.get("TMPDIR", "/tmp"))
    with temporary_settings({PREFECT_HOME: str(tmp_path / "home")}):
        tmp = _private_tmp()
        from prefect.runner import Runner

        runner = Runner(pause_on_shutdown=False)
    assert runner._tmp_dir.is_relative_to(tmp)
    assert tmp.stat().st_mode & 0o777 == 0o700


def test_a_private_tmp_made_by_another_account_is_refused(tmp_path, monkeypatch,
                                                           other_account):
    import tempfile

    from prefect.settings import PREFECT_HOME, temporary_settings

    from flows.cli import _private_tmp
    from pipeline.stream.state import StateError

    monkeypatch.setattr(tempfile, "tempdir", tempfile.tempdir)
    monkeypatch.setenv("TMPDIR", os.environ.get("TMPDIR", "/tmp"))
    (tmp_path / "home" / "tmp").mkdir(parents=True)
    os.chown(tmp_path / "home" / "tmp", other_account, -1)
    with temporary_settings({PREFECT_HOME: str(tmp_path / "home")}):
        with pytest.raises(StateError, match=f"owned by uid {other_account}"):
            _private_tmp()


def test_flow_run_makes_its_embedded_api_private(tmp_path):
    """Before: during a plain `tcspc flow run`, another account read past runs from the
    embedded API and cancelled the running flow. Now the embedded server asks for a secret
    made for the command: an unauthenticated request gets 401 while the flow runs."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import os, urllib.request, urllib.error
        from flows.cli import _private_embedded_api
        _private_embedded_api()
        from prefect import flow

        @flow
        def probe():
            from prefect.client.orchestration import get_client
            url = str(get_client(sync_client=True).api_url).rstrip("/")
            req = urllib.request.Request(url + "/flow_runs/filter", data=b"{}",
                                         headers={"Content-Type": "application/json"})
            try:
                urllib.request.urlopen(req, timeout=10)
                return "open"
            except urllib.error.HTTPError as e:
                return str(e.code)

        print("probe:", probe())
    """)
    env = {k: v for k, v in os.environ.items()
           if not k.startswith(("PREFECT_API_URL", "PREFECT_API_AUTH", "PREFECT_SERVER_API"))}
    env["PREFECT_HOME"] = str(tmp_path / "home")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                       timeout=300, env=env)
    assert "probe: 401" in r.stdout, (r.stdout[-300:], r.stderr[-600:])
