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
