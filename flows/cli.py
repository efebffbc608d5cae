"""``tcspc flow list|run|serve`` (registered on ``tcspc`` through the ``tcspc.commands``
entry point, so the pipeline layer never imports this one).

``run`` executes a flow now: on Prefect's embedded ephemeral API by default (no server,
works offline), or on the server ``PREFECT_API_URL`` names; its parameters are checked
against the flow's typed signature before the run is created. ``serve`` publishes the flows
as deployments with schedules (from a TOML file: :func:`read_serve_config`) and runs them
when due; schedules need a Prefect server (``prefect server start`` and
``PREFECT_API_URL``), which the command checks first. Ctrl-C stops it as SIGTERM does.
"""

from __future__ import annotations

import importlib
import inspect
import json
import os
import signal
import sys
import tomllib
import zoneinfo
from pathlib import Path

import click

from pipeline.io.limits import FileTooLarge, load_toml

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
    """``key=value`` pairs; values are JSON where they parse (numbers, lists, true/false)
    and the parameter's type takes them, else the string as typed (``-p delay_run=0`` is
    the run named "0" where the parameter is a string). Unknown keys are an error naming
    the flow's parameters."""
    import typing

    from pydantic import TypeAdapter, ValidationError

    known = inspect.signature(fn).parameters
    try:
        hints = typing.get_type_hints(fn, include_extras=True)
    except (NameError, TypeError):  # pragma: no cover - an annotation that does not resolve
        hints = {}

    def typed(key: str, value: str):
        try:
            parsed = json.loads(value)
        except json.JSONDecodeError:
            return value
        if key not in hints or isinstance(parsed, str):
            return parsed
        adapter = TypeAdapter(hints[key])
        for candidate in (parsed, value):
            try:
                adapter.validate_python(candidate)
                return candidate
            except ValidationError:
                pass
        return parsed  # check_params names what is wrong with it

    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep:
            raise click.BadParameter(f"{item!r}: use key=value")
        if key not in known:
            raise click.BadParameter(f"{key!r} is not a parameter of {fn.__name__}; "
                                     f"parameters: {', '.join(known)}")
        out[key] = typed(key, value)
    return out


@click.group()
def flow() -> None:
    """Run or serve the Prefect flows (calibration, sweeps, reports)."""


def summary(doc: str | None) -> str:
    """A docstring's first paragraph as plain text, whole (not its first line, which cut a
    sentence in two): one line, reStructuredText's roles and literals unmarked."""
    import re

    first = " ".join((doc or "").strip().split("\n\n")[0].split())
    first = re.sub(r":[a-z]+:`~?([^`]+)`", r"\1", first)  # :func:`x` -> x
    return re.sub(r"``([^`]+)``", r"\1", first)  # ``x`` -> x


@flow.command("list")
def list_cmd() -> None:
    """The flows and their parameters with defaults."""
    import textwrap

    for name in FLOWS:
        fn = load(name).fn
        click.echo(textwrap.fill(f"{name}: {summary(inspect.getdoc(fn))}", width=100,
                                 subsequent_indent="  "))
        for p in inspect.signature(fn).parameters.values():
            click.echo(f"    {p.name} = {p.default!r}")


@flow.command("run")
@click.argument("name")
@click.option("-p", "--param", "params", multiple=True, metavar="KEY=VALUE",
              help="A flow parameter (JSON value), e.g. -p cycles=100000 -p lux=[500,2000].")
@click.option("--dask", "dask_address", metavar="[ADDRESS]", is_flag=False, flag_value="local",
              help="Fan tasks out over the Dask cluster at ADDRESS (tls://HOST:8786, with "
                   "the TLS files of Dask's configuration), or over a private local "
                   "cluster (TLS, credentials made for this run) with no ADDRESS.")
@click.option("--dask-insecure", is_flag=True,
              help="Take a --dask ADDRESS without TLS (anyone who reaches it runs code as "
                   "its workers' user).")
def run_cmd(name, params, dask_address, dask_insecure) -> None:
    """Run flow NAME now and print its summary as JSON."""
    _private_embedded_api()
    fl = load(name)
    kwargs = parse_params(params, fl.fn)
    if dask_address:
        fl = fl.with_options(task_runner=dask_runner(dask_address, dask_insecure))
    check_params(fl, kwargs, "-p")
    check_inputs(name, fl.fn, kwargs)
    api = os.environ.get("PREFECT_API_URL") or "Prefect's embedded ephemeral API"
    click.echo(f"running {name} on {api}", err=True)
    state = fl(**kwargs, return_state=True)
    result = state.result()  # a failed run raises its error here
    click.echo(json.dumps(result, indent=1, default=str))
    outcome = f" {result['outcome']}" if isinstance(result, dict) and "outcome" in result else ""
    click.echo(f"{name}: {state.name}{outcome}" + (f" ({state.message})" if state.message
                                                   else ""), err=True)
    if isinstance(result, dict) and result.get("outcome") == "refused":
        # completed, but nothing published: say so to scripts
        sys.exit(REFUSED_EXIT)


def dask_runner(address: str, insecure: bool = False):
    """The Dask task runner of ``--dask [ADDRESS]``. A local cluster is private: its
    scheduler and workers speak TLS with credentials made in memory for this run
    (``Security.temporary()``: a CA and a certificate no file holds), so another account
    that finds its port cannot submit a function (which would run as this user). A remote
    ADDRESS must be tls:// with Dask's TLS configuration (``distributed.comm.tls``: CA,
    client certificate and key), else it is refused unless ``insecure``."""
    from distributed import Security
    from prefect_dask import DaskTaskRunner

    if address == "local":
        return DaskTaskRunner(cluster_kwargs={"security": Security.temporary(),
                                              "dashboard_address": None})
    sec = Security()  # (from Dask's configuration)
    if address.startswith("tls://") and sec.tls_ca_file and sec.tls_client_cert:
        return DaskTaskRunner(address=address, client_kwargs={"security": sec})
    if not insecure:
        raise click.UsageError(
            f"--dask {address}: not a tls:// address with Dask's TLS configuration "
            "(distributed.comm.tls.ca-file and client cert/key): anyone who reaches it "
            "could run code as its workers' user; configure TLS, or pass --dask-insecure")
    return DaskTaskRunner(address=address)


def _private_embedded_api() -> None:
    """Without PREFECT_API_URL a run uses Prefect's embedded API on a loopback port, which
    any local account can reach: it read past runs' parameters and logs there and set a
    running flow to Cancelling. The embedded server and its clients (this process and
    the processes it starts) then share a random HTTP basic-auth secret made for this
    command (set before Prefect is imported, which reads its settings once)."""
    import secrets

    if os.environ.get("PREFECT_API_URL") or os.environ.get("PREFECT_API_AUTH_STRING") \
            or "prefect" in sys.modules:  # (a test harness's, or a caller's own API)
        return
    secret = f"tcspc:{secrets.token_urlsafe(24)}"
    os.environ["PREFECT_API_AUTH_STRING"] = os.environ["PREFECT_SERVER_API_AUTH_STRING"] = secret


def _private_tmp() -> Path:
    """A temporary directory of this user's own (PREFECT_HOME/tmp, 0700, checked as the
    daemon's state is), made the process's and its children's: Prefect's Runner puts its
    storage at TMP/runner_storage, a fixed name another account could create first in a
    shared /tmp."""
    import tempfile

    from prefect.settings import PREFECT_HOME

    from pipeline.stream.state import make_private

    tmp = Path(PREFECT_HOME.value()).expanduser() / "tmp"
    make_private(tmp, "temporary directory")
    os.environ["TMPDIR"] = tempfile.tempdir = str(tmp)
    return tmp


#: `tcspc flow run`'s exit status when a campaign refused its candidate
REFUSED_EXIT = 3


#: each flow's parameters that name an input that must exist when the run starts
INPUTS = {"batch": ("inputs", "calibration"), "calibration_campaign": ("captures", "journal"),
          "distance_sweep": ("calibration", "captures", "stream")}


def check_inputs(name: str, fn, params: dict) -> None:
    """Refuse a run (one line, exit 2, before it is created) whose input parameter (given
    with -p or its default) names a path that does not exist."""
    sig = inspect.signature(fn).parameters
    for key in INPUTS.get(name, ()):
        value = params.get(key, sig[key].default)
        if isinstance(value, str) and not Path(value).exists():
            how = "-p" if key in params else "default"
            raise click.UsageError(f"{how} {key}={value}: no such file or directory")


def check_params(fl, params: dict, where: str) -> None:
    """The flow's typed signature against ``params`` now, before a run exists: one line
    per problem, naming the parameter (and ``where`` it came from)."""
    import logging

    from prefect.exceptions import ParameterTypeError

    quiet = logging.getLogger("prefect.flows")  # it logs pydantic's raw dump first
    level = quiet.level
    quiet.setLevel(logging.CRITICAL)
    try:
        fl.validate_parameters(params)
    except ParameterTypeError as exc:
        lines = [ln.strip(" -") for ln in str(exc).splitlines()[1:]] or [str(exc)]
        raise click.UsageError(f"{where}: invalid parameters for {fl.name}: "
                               + "; ".join(lines)) from None
    finally:
        quiet.setLevel(level)


#: ``tcspc flow serve`` without ``--config``: the nightly campaign at 02:00 UTC
DEFAULT_SERVE = {"out": "data", "calibration": {"cron": "0 2 * * *"}}
_SECTIONS = {"calibration": "calibration_campaign", "sweep": "distance_sweep",
             "performance": "performance_prediction", "speed": "speed_vs_error"}
_SECTION_KEYS = {"cron", "name", "tags", "parameters", "timezone"}


def read_serve_config(path: str | None, **cli) -> dict:
    """The deployments ``serve`` publishes, from a TOML file (None: :data:`DEFAULT_SERVE`)::

        out = "data"                   # where the runs write (OUT/calibration, OUT/sweeps..)
        [calibration]                  # the campaign; a section per flow served on a cron:
        cron = "0 2 * * *"             # calibration, sweep, performance, speed
        timezone = "Europe/Berlin"     # the cron's (default UTC)
        tags = ["bench-1"]
        name = "bench-1 nightly"       # default: what it is ("128px daily at 02:00")
        [calibration.parameters]       # the flow's own parameters, checked now
        lux = [100, 300, 800, 1800, 3500]
        cycles = 400000
        n_pixels = 128

    A flow without a section is published on demand (no schedule). ``cli`` (from the
    command's options, None where not given) overrides the file: ``out``,
    ``calibration_cron``, ``sweep_cron``. Every problem is an error naming the file and
    key."""
    where = path or "<default serve config>"
    if path:
        try:
            raw = load_toml(path, "serve config")
        except FileNotFoundError:
            raise click.BadParameter(f"{path}: serve config not found") from None
        except (FileTooLarge, OSError, UnicodeDecodeError) as exc:
            raise click.BadParameter(str(exc)) from None
        except tomllib.TOMLDecodeError as exc:
            raise click.BadParameter(f"{path}: not valid TOML: {exc}") from None
    else:
        raw = json.loads(json.dumps(DEFAULT_SERVE))
    if cli.get("out"):
        raw["out"] = cli["out"]
    for sec, key in (("calibration", "calibration_cron"), ("sweep", "sweep_cron")):
        if cli.get(key):
            raw.setdefault(sec, {})["cron"] = cli[key]
    unknown = sorted(set(raw) - set(_SECTIONS) - {"out"})
    if unknown:
        raise click.BadParameter(f"{where}: unknown keys {unknown}; known: out, "
                                 f"{', '.join(_SECTIONS)}")
    if not isinstance(raw.get("out", "data"), str):
        raise click.BadParameter(f"{where}: out must be a directory name")
    for sec, body in raw.items():
        if sec == "out":
            continue
        if not isinstance(body, dict):
            raise click.BadParameter(f"{where}: [{sec}] must be a table")
        extra = sorted(set(body) - _SECTION_KEYS)
        if extra:
            raise click.BadParameter(f"{where}: [{sec}] unknown keys {extra}; known: "
                                     f"{', '.join(sorted(_SECTION_KEYS))}")
        if "cron" not in body:
            raise click.BadParameter(f"{where}: [{sec}] needs a cron")
        _check_cron(body["cron"], f"{where}: [{sec}] cron")
        tz = body.get("timezone", "UTC")
        try:
            zoneinfo.ZoneInfo(tz)
        except (zoneinfo.ZoneInfoNotFoundError, ValueError, TypeError):
            raise click.BadParameter(f"{where}: [{sec}] timezone {tz!r} is not a time zone "
                                     "(e.g. UTC, Europe/Berlin)") from None
        tags = body.get("tags", [])
        if not (isinstance(tags, list) and all(isinstance(t, str) for t in tags)):
            raise click.BadParameter(f"{where}: [{sec}] tags must be a list of strings")
    return raw


def _check_cron(cron, where: str) -> None:
    from prefect.client.schemas.schedules import CronSchedule

    try:
        CronSchedule(cron=cron)
    except (ValueError, TypeError):
        raise click.BadParameter(f"{where}: {cron!r} is not a cron expression") from None


_DAYS = ["Sundays", "Mondays", "Tuesdays", "Wednesdays", "Thursdays", "Fridays",
         "Saturdays", "Sundays"]


def describe_cron(cron: str) -> str:
    """A schedule in words for a deployment's name: "daily at 02:00", "every minute",
    "hourly at :15", "Mondays at 03:30"; else "cron <expression>"."""
    f = cron.split()
    if len(f) != 5:
        return f"cron {cron}"
    mi, hr, dom, mon, dow = f
    if f == ["*"] * 5:
        return "every minute"
    if mi.startswith("*/") and f[1:] == ["*"] * 4:
        return f"every {mi[2:]} minutes"
    if mi.isdigit() and hr == "*" and (dom, mon, dow) == ("*", "*", "*"):
        return f"hourly at :{int(mi):02d}"
    if mi.isdigit() and hr.isdigit() and (dom, mon) == ("*", "*"):
        at = f"at {int(hr):02d}:{int(mi):02d}"
        if dow == "*":
            return f"daily {at}"
        if dow.isdigit() and int(dow) < 8:
            return f"{_DAYS[int(dow)]} {at}"
    return f"cron {cron}"


def deployments(config: dict) -> list:
    """The deployments ``serve`` publishes for a :func:`read_serve_config` config, named
    for what they are: the campaign on a cron ("128px daily at 02:00"), one campaign at a
    time (a deployment concurrency limit of 1 that cancels a run due while one is running:
    after a downtime, one catch-up run, not one per missed fire); flows without a cron "on
    demand". Parameters are checked now."""
    out = config.get("out", "data")
    defaults = {"calibration_campaign": {"out": f"{out}/calibration"},
                "distance_sweep": {"out": f"{out}/sweeps",
                                   "calibration": f"{out}/calibration/current"},
                "performance_prediction": {"out": f"{out}/performance_prediction"},
                "speed_vs_error": {"out": f"{out}/speed_vs_error"}}
    deps = []
    for sec, flow_name in _SECTIONS.items():
        fl = load(flow_name)
        body = config.get(sec)
        params = {**defaults[flow_name], **((body or {}).get("parameters") or {})}
        check_params(fl, params, f"serve config [{sec}.parameters]")
        if body is None:
            deps.append(fl.to_deployment("on demand", parameters=params,
                                         tags=[sec, "on-demand"]))
            continue
        what = (f"{params.get('n_pixels', 128)}px " if flow_name in
                ("calibration_campaign", "distance_sweep") and not params.get("captures")
                else "")
        name = body.get("name") or f"{what}{describe_cron(body['cron'])}"
        from prefect.client.schemas.objects import ConcurrencyLimitConfig, ConcurrencyLimitStrategy
        from prefect.schedules import Cron

        # one run at a time; a run due while one runs is cancelled, not queued: after a
        # downtime the Late runs Prefect kept scheduling start together and one runs (#39.6)
        kw = {"concurrency_limit": ConcurrencyLimitConfig(
            limit=1, collision_strategy=ConcurrencyLimitStrategy.CANCEL_NEW)}

        deps.append(fl.to_deployment(
            name, schedules=[Cron(body["cron"], timezone=body.get("timezone", "UTC"))],
            parameters=params, tags=[sec, *body.get("tags", [])],
            description=(inspect.getdoc(fl.fn) or "").split("\n\n")[0], **kw))
    return deps


@flow.command("serve")
@click.option("--config", "config_path", type=click.Path(dir_okay=False), default=None,
              help="A TOML file of what to serve: crons, tags, each flow's parameters "
                   "(lux levels, cycles, pixels, out); see docs/flows.md.")
@click.option("--calibration-cron", default=None,
              help="When the calibration campaign runs (cron, UTC); overrides the file. "
                   "Default without a file: 0 2 * * *.")
@click.option("--sweep-cron", default=None, help="Schedule the distance sweep too (cron).")
@click.option("--out", default=None, help="Where the runs write (default: data).")
@click.option("--root", "roots", multiple=True, type=click.Path(file_okay=False),
              help="A folder a served run may write under (repeat; default: --out). A run "
                   "created on the server with an out elsewhere is refused.")
@click.option("--unauthenticated", is_flag=True,
              help="Serve through a Prefect server without PREFECT_API_AUTH_STRING (only "
                   "where no other account can reach its port).")
def serve_cmd(config_path, calibration_cron, sweep_cron, out, roots, unauthenticated) -> None:
    """Serve the flows as deployments with schedules until Ctrl-C or SIGTERM (either stops
    scheduling and cancels a run in flight, which leaves the published calibration
    as it was). Anyone who can reach the Prefect server can create runs: its API needs
    authentication (docs/flows.md, "A shared host"), and served runs write only under the
    roots."""
    config = read_serve_config(config_path, out=out, calibration_cron=calibration_cron,
                               sweep_cron=sweep_cron)
    from prefect.settings import PREFECT_API_AUTH_STRING, PREFECT_API_URL

    if not os.environ.get("PREFECT_API_URL") and not PREFECT_API_URL.value():
        raise click.ClickException(
            "schedules need a Prefect server: start one with `prefect server start` and "
            "set PREFECT_API_URL=http://127.0.0.1:4200/api (`tcspc flow run` needs none)")
    if not PREFECT_API_AUTH_STRING.value() and not unauthenticated:
        raise click.UsageError(
            "PREFECT_API_AUTH_STRING is not set: any account that reaches the Prefect "
            "server could create runs with its own paths, read past runs and cancel them; "
            "start the server with PREFECT_SERVER_API_AUTH_STRING=USER:PASSWORD and set "
            "PREFECT_API_AUTH_STRING to the same here (docs/flows.md, \"A shared host\"), "
            "or pass --unauthenticated")
    from flows.common import ROOTS_ENV

    roots = [str(Path(r).resolve()) for r in (roots or [config.get("out", "data")])]
    os.environ[ROOTS_ENV] = os.pathsep.join(roots)  # (the served runs' processes inherit it)
    _private_tmp()
    deps = deployments(config)
    from prefect.runner import Runner

    runner = Runner(pause_on_shutdown=False)
    for d in deps:
        runner.add_deployment(d)
        click.echo(f"serving {d.flow_name}/{d.name}" + (
            f" on {d.schedules[0].schedule.cron}" if d.schedules else " (on demand)"),
                   err=True)
    # Ctrl-C as SIGTERM: Prefect's graceful stop (asyncio leaves a handler set here alone)
    signal.signal(signal.SIGINT, lambda *_: runner.handle_sigterm())
    import asyncio

    asyncio.run(runner.start())
    click.echo("serve stopped", err=True)


@flow.command("automations")
@click.option("--create", "do_create", is_flag=True,
              help="Create them on the Prefect server (PREFECT_API_URL), each replacing any "
                   "of the same name; without it, print them as JSON.")
@click.option("--out", default=None, type=click.Path(file_okay=False),
              help="The calibration directory they watch (default: every one).")
@click.option("--stale-hours", type=click.FloatRange(min=1), default=None,
              help="Hours without a published calibration that make it stale (default "
                   "180: a week and a half-day).")
@click.option("--notify", default=None, type=click.UUID, metavar="BLOCK_ID",
              help="A notification block's document id to send each through (default: "
                   "they fire without sending).")
def automations_cmd(do_create, out, stale_hours, notify) -> None:
    """The automations a lab wants on its campaigns: a campaign refused, a campaign crashed
    (or failed, or timed out), a calibration stale (none published for --stale-hours)."""
    from flows.automations import STALE_H, create, lab_automations

    autos = lab_automations(out, STALE_H if stale_hours is None else stale_hours, notify)
    if not do_create:
        click.echo(json.dumps([a.model_dump(mode="json") for a in autos], indent=1))
        return
    from prefect.settings import PREFECT_API_URL

    if not os.environ.get("PREFECT_API_URL") and not PREFECT_API_URL.value():
        raise click.ClickException(
            "automations live on a Prefect server: set PREFECT_API_URL (e.g. "
            "http://127.0.0.1:4200/api)")
    for name, aid in create(autos):
        click.echo(f"created {name}: {aid}")
