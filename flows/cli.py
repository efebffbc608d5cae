"""``tcspc flow list|run|serve`` (registered on ``tcspc`` through the ``tcspc.commands``
entry point, so the pipeline layer never imports this one).

``run`` executes a flow now: on Prefect's embedded ephemeral API by default (no server,
works offline), or on the server ``PREFECT_API_URL`` names. ``serve`` publishes the flows
as deployments with schedules and runs them when due; schedules need a Prefect server
(``prefect server start`` and ``PREFECT_API_URL``), which the command checks first.
"""

from __future__ import annotations

import importlib
import inspect
import json
import os

import click

#: name -> "module:function"; the modules are imported on use (Prefect is slow to import).
FLOWS = {
    "calibration_campaign": "flows.calibration:calibration_campaign",
    "distance_sweep": "flows.distance_sweep:distance_sweep",
    "performance_prediction": "flows.performance:performance_prediction",
    "speed_vs_error": "flows.speed_vs_error:speed_vs_error",
    "batch": "flows.batch:batch",
}


def load(name: str):
    if name not in FLOWS:
        raise click.BadParameter(f"unknown flow {name!r}; flows: {', '.join(FLOWS)}")
    module, attr = FLOWS[name].split(":")
    return getattr(importlib.import_module(module), attr)


def parse_params(items: tuple[str, ...], fn) -> dict:
    """``key=value`` pairs; values are JSON where they parse (numbers, lists, true/false),
    else strings. Unknown keys are an error naming the flow's parameters."""
    known = inspect.signature(fn).parameters
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise click.BadParameter(f"{item!r}: use key=value")
        if key not in known:
            raise click.BadParameter(f"{key!r} is not a parameter of {fn.__name__}; "
                                     f"parameters: {', '.join(known)}")
        try:
            out[key] = json.loads(value)
        except json.JSONDecodeError:
            out[key] = value
    return out


@click.group()
def flow() -> None:
    """Run or serve the Prefect flows (calibration, sweeps, reports)."""


@flow.command("list")
def list_cmd() -> None:
    """The flows and their parameters with defaults."""
    for name in FLOWS:
        fn = load(name).fn
        doc = (inspect.getdoc(fn) or "").splitlines()[0]
        click.echo(f"{name}: {doc}")
        for p in inspect.signature(fn).parameters.values():
            click.echo(f"    {p.name} = {p.default!r}")


@flow.command("run")
@click.argument("name")
@click.option("-p", "--param", "params", multiple=True, metavar="KEY=VALUE",
              help="A flow parameter (JSON value), e.g. -p cycles=100000 -p lux=[500,2000].")
@click.option("--dask", "dask_address", metavar="[ADDRESS]", is_flag=False, flag_value="local",
              help="Fan tasks out over the Dask cluster at ADDRESS (tcp://HOST:8786), or "
                   "over a local cluster of one worker process per core with no ADDRESS.")
def run_cmd(name, params, dask_address) -> None:
    """Run flow NAME now and print its summary as JSON."""
    fl = load(name)
    kwargs = parse_params(params, fl.fn)
    if dask_address:
        from prefect_dask import DaskTaskRunner

        fl = fl.with_options(task_runner=DaskTaskRunner() if dask_address == "local"
                             else DaskTaskRunner(address=dask_address))
    api = os.environ.get("PREFECT_API_URL") or "Prefect's embedded ephemeral API"
    click.echo(f"running {name} on {api}", err=True)
    result = fl(**kwargs)
    click.echo(json.dumps(result, indent=1, default=str))


def deployments(calibration_cron: str, sweep_cron: str | None, out: str) -> list:
    """The deployments ``serve`` publishes: the nightly calibration campaign, a distance
    sweep (scheduled when ``sweep_cron`` is given), and the rest on demand."""
    cal = load("calibration_campaign").to_deployment(
        "nightly", cron=calibration_cron, parameters={"out": f"{out}/calibration"},
        description="Nightly calibration campaign; publishes only a calibration that is not "
                    "worse than the current one.")
    sweep = load("distance_sweep").to_deployment(
        "sweep", cron=sweep_cron, parameters={"out": f"{out}/sweeps",
                                              "calibration": f"{out}/calibration/current"})
    rest = [load(n).to_deployment("on-demand", parameters={"out": f"{out}/{n}"})
            for n in ("performance_prediction", "speed_vs_error")]
    return [cal, sweep, *rest]


@flow.command("serve")
@click.option("--calibration-cron", default="0 2 * * *", show_default=True,
              help="When the calibration campaign runs (cron, server time zone).")
@click.option("--sweep-cron", default=None, help="Schedule the distance sweep too (cron).")
@click.option("--out", default="data", show_default=True, help="Where the runs write.")
def serve_cmd(calibration_cron, sweep_cron, out) -> None:
    """Serve the flows as deployments with schedules until interrupted."""
    if not os.environ.get("PREFECT_API_URL"):
        from prefect.settings import PREFECT_API_URL

        if not PREFECT_API_URL.value():
            raise click.ClickException(
                "schedules need a Prefect server: start one with `prefect server start` and "
                "set PREFECT_API_URL=http://127.0.0.1:4200/api (`tcspc flow run` needs none)")
    from prefect import serve

    serve(*deployments(calibration_cron, sweep_cron, out))
