"""Issue 36, point 1: `tcspc flow run --dask` and another account of the host. Before, the
local cluster listened on tcp://127.0.0.1 with no authentication: another user found its
port, submitted a function and it ran under the operator's uid."""

from __future__ import annotations

import click
import pytest


def test_the_local_cluster_is_private():
    """The local cluster speaks TLS with credentials made for this run: a plain tcp client
    and a client with credentials of its own (another user's Security.temporary()) cannot
    submit; the runner's own client can."""
    from distributed import Client, LocalCluster, Security

    from flows.cli import dask_runner

    kwargs = dask_runner("local").cluster_kwargs
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                      **kwargs) as cluster:
        assert cluster.scheduler_address.startswith("tls://")
        with Client(cluster) as own:
            assert own.submit(lambda: 6 * 7).result() == 42
        tcp = cluster.scheduler_address.replace("tls://", "tcp://")
        for attempt in ({"address": tcp},
                        {"address": cluster.scheduler_address,
                         "security": Security.temporary()}):
            with pytest.raises(Exception):  # noqa: B017 - refused, whatever form it takes
                with Client(timeout=3, **attempt) as c:
                    c.submit(lambda: 1).result(timeout=3)


@pytest.mark.parametrize("address", ["tcp://127.0.0.1:8786", "tls://127.0.0.1:8786"])
def test_a_remote_cluster_without_tls_is_refused(address):
    """A remote --dask ADDRESS without Dask's TLS configuration: refused in one line,
    unless --dask-insecure."""
    from flows.cli import dask_runner

    with pytest.raises(click.UsageError, match="--dask-insecure"):
        dask_runner(address)
    assert dask_runner(address, insecure=True).address == address


def test_the_cli_refuses_before_any_run(tmp_path):
    from click.testing import CliRunner

    from pipeline.cli.app import cli

    res = CliRunner().invoke(cli, ["flow", "run", "speed_vs_error", "--dask",
                                   "tcp://127.0.0.1:1", "-p", f"out={tmp_path}"])
    assert res.exit_code == 2 and "--dask-insecure" in res.output
    assert list(tmp_path.iterdir()) == []
