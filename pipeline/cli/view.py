"""``tcspc view``: the live web page of a daemon and its datasets (loaded when named)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from pipeline.cli.console import err
from pipeline.io.limits import load_toml


def _from_config(config: str | None) -> dict:
    """state, out, calibration, run and the [view] keys of a daemon topology."""
    if not config:
        return {}
    from pipeline.stream.topology import load_topology

    topo = load_topology(config, writable=False)  # (the page only reads)
    raw = load_toml(config, "topology file")  # (load_topology read it already)
    cal = (topo.range or {}).get("calibration") or topo.histogram.get("calibration")
    return {"state": str(topo.state), "out": str(topo.sink["out"]), "calibration": cal,
            "run": (raw.get("daemon") or {}).get("run"), **(topo.view or {})}


@click.command()
@click.option("--config", type=click.Path(exists=True, dir_okay=False),
              help="A daemon topology: take its state, datasets, calibration and [view] keys.")
@click.option("--state", default=None, type=click.Path(file_okay=False),
              help="The daemon's state directory (status.json)  [default: data/daemon]")
@click.option("--out", default=None, type=click.Path(file_okay=False),
              help="The datasets' directory (the sink's out)  [default: data/stream]")
@click.option("--calibration", default=None, type=click.Path(),
              help="The calibration in use  [default: the topology's, else "
                   "data/calibration/current when there is one]")
@click.option("--run", "run_id", default=None,
              help="The run shown first  [default: the daemon's, else the newest]")
@click.option("--port", type=click.IntRange(0, 65535), default=None,
              help="TCP port (0: any free one)  [default: 5006]")
@click.option("--bind", default=None,
              help="Address to listen on (the URL carries a token on every address)  "
                   "[default: 127.0.0.1]")
@click.option("--layout", default=None,
              help="The array as COLUMNSxROWS, TDC t at column t % COLUMNS  [default: 16x8 "
                   "for 128 TDCs]")
@click.option("--geometry", default=None,
              help="Lay the maps out as this geometry's array (rows x cols, each TDC at its "
                   "row and col; docs/geometry.md); overrides --layout.")
@click.option("--open", "open_browser", is_flag=True, help="Open the page in a browser too.")
@click.option("--nice", type=click.IntRange(0, 19), default=10, show_default=True,
              help="Lower the server's CPU priority by this much: on a busy machine the "
                   "daemon's stages go first.")
def view(config, state, out, calibration, run_id, port, bind, layout, geometry, open_browser,
         nice) -> None:
    """Serve the live web page of a daemon and its datasets: per-stage health, the sensor's
    latest measurement (histograms, distance and counts maps), the calibration in use and
    the drift of the online LSB estimate. Works the same on a running daemon, a replayed
    capture or a finished run (pick it on the page). Ctrl-C stops it.

    After `make demo`: `.venv/bin/tcspc view`, then open the printed URL.
    """
    import os
    import signal

    from pipeline.view.model import ViewModel
    from pipeline.view.sensor import parse_layout
    from pipeline.view.server import make_server, write_url

    cfg = _from_config(config)
    state = Path(state or cfg.get("state") or "data/daemon")
    out = Path(out or cfg.get("out") or "data/stream")
    calibration = calibration or cfg.get("calibration")
    if calibration is None and Path("data/calibration/current/tdc.parquet").exists():
        calibration = "data/calibration/current"
    layout = layout or cfg.get("layout")
    if layout:
        try:
            parse_layout(layout, 1)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--layout") from None
    geometry = geometry or cfg.get("geometry")
    if geometry:
        from pipeline.io.geometry import load_geometry

        geometry = load_geometry(geometry)  # (a bad one: one line, exit 2)
    port = cfg.get("port", 5006) if port is None else port
    bind = bind or cfg.get("bind") or "127.0.0.1"
    if nice:
        os.nice(nice)  # (the LSB estimate's thread too: it starts later, with this)
    model = ViewModel(state, out, calibration, run_id or cfg.get("run"), layout)
    model.geometry = geometry or None
    try:
        server, url = make_server(model, port, bind)
    except OSError as exc:
        raise click.ClickException(f"cannot listen on {bind}:{port}: {exc.strerror or exc} "
                                   "(another `tcspc view`? use --port)") from None
    # a stop from here on ends the loop cleanly (before view.url exists: a SIGTERM that
    # follows it must find the handler, not the default action)
    loop = server.io_loop
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: loop.add_callback_from_signal(loop.stop))
    where = write_url(state, url) if state.exists() else None
    # the token is a secret: in the 0600 file, and printed whole once, to the operator's
    # terminal (never to a log under the daemon) or where no 0600 file could hold it
    shown = url.split("?token=")[0] + "?token=(in " + str(where) + ")" \
        if where and "?token=" in url else url
    click.echo(url if sys.stdout.isatty() else shown, nl=True)
    err.print(f"tcspc view: open {shown} (state {state}, datasets {out}, calibration "
              f"{calibration or 'none'}){f'; URL in {where}' if where else ''}; Ctrl-C stops",
              highlight=False, soft_wrap=True)
    if open_browser:
        import webbrowser

        loop.add_callback(lambda: webbrowser.open(url))  # (with its token, if any)
    try:
        loop.start()
    finally:
        server.stop()
        model.close()
        _forget_url(where, url)


def _forget_url(where: Path | None, url: str) -> None:
    """STATE/view.url names a page that is gone once the server stops: removed, unless
    another `tcspc view` has written its own URL there since."""
    try:
        if where is not None and where.read_text().strip() == url:
            where.unlink()
    except OSError:
        pass
