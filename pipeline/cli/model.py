"""``tcspc model ...``: the chapter-2 models as tables (``--json`` for machines, ``--plot``)."""

from __future__ import annotations

import json
import math
from dataclasses import asdict
from pathlib import Path

import click
import numpy as np
from rich.table import Table

from pipeline.cli.app import _overwrite, check_out
from pipeline.cli.console import console
from stages.models import atmosphere as atm
from stages.models import noise, signal
from stages.models.performance import TABLE_2_2, predict, table_2_2_rows
from stages.models.scene import evaluate, load_scene
from stages.models.tcspc import crlb_tof, first_photon_histogram

out = console()


def _jsonable(v):
    if isinstance(v, np.generic):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return v


def _emit(rows: list[dict], title: str, as_json: bool) -> None:
    """Print rows as a table, or as JSON lines on --json."""
    if as_json:
        click.echo(json.dumps([{k: _jsonable(v) for k, v in r.items()} for r in rows],
                              indent=1))
        return
    table = Table(title=title)
    for k in rows[0]:
        table.add_column(k, justify="right")
    for r in rows:
        table.add_row(*(f"{_jsonable(v):.4g}" if isinstance(_jsonable(v), float) else str(v)
                        for v in r.values()))
    out.print(table)


_json = click.option("--json", "as_json", is_flag=True, help="Print JSON instead of a table.")


@click.group()
def model() -> None:
    """Chapter 2: link budget, ambient light, transmission, prediction, histograms."""


@model.command("link-budget", short_help="Photons per pixel per pulse: mirror and diffuse "
                                         "target (eq. 2.23-2.26).")
@click.option("--distance", "-d", multiple=True, type=float, default=(1.0, 10.0, 100.0),
              show_default=True, help="Target distance in m (repeat for several).")
@click.option("--energy-pj", default=29.0, show_default=True)
@click.option("--reflectivity", default=0.5, show_default=True)
@click.option("--pdp", default=0.25, show_default=True)
@click.option("--fill-factor", default=0.049, show_default=True)
@_json
def link_budget(distance, energy_pj, reflectivity, pdp, fill_factor, as_json) -> None:
    """Photons per pixel per pulse: mirror (eq. 2.23) and diffuse target (eq. 2.25-2.26)."""
    rows = []
    for d in distance:
        mirror = float(signal.collimated_photons_per_pixel(2 * d, energy_pj * 1e-12))
        diffuse = float(signal.diffuse_photons_per_pixel(d, reflectivity, energy_pj * 1e-12))
        rows.append({"distance_m": d, "beam_area_mm2": float(signal.beam_area_m2(d)) * 1e6,
                     "collimated_at_d": float(signal.collimated_photons_per_pixel(
                         d, energy_pj * 1e-12)),
                     "mirror_return": mirror, "diffuse_return": diffuse,
                     "m_diffuse": float(signal.signal_detections_per_cycle(
                         diffuse, pdp, fill_factor))})
    _emit(rows, "link budget (photons per pixel per pulse)", as_json)


@model.command(short_help="Background photons per pixel: sunlight, lux, lamps "
                          "(eq. 2.37-2.43).")
@click.option("--lux", default=100_000.0, show_default=True, help="Daylight illuminance.")
@click.option("--filter-nm", default=10.0, show_default=True)
@click.option("--pde", default=0.25 * 0.049, show_default=True)
@click.option("--lamp-lm", type=float, default=None, help="A lamp's luminous flux instead.")
@click.option("--lamp-distance", default=10.0, show_default=True)
@click.option("--lamp-angle", default=90.0, show_default=True, help="Half angle, degrees.")
@_json
def ambient(lux, filter_nm, pde, lamp_lm, lamp_distance, lamp_angle, as_json) -> None:
    """Background photons per pixel: sunlight (eq. 2.37-2.40), lux, lamps (eq. 2.41-2.43)."""
    rows = []
    top = float(noise.solar_irradiance_top()) * 1e-9
    sea = float(noise.solar_irradiance_sea_level()) * 1e-9
    rows.append({"source": "sun, top of atmosphere", "w_m2_nm": top,
                 "photons_hz": float(noise.photon_rate_hz(top, filter_nm))})
    rows.append({"source": "sun, sea level (Rayleigh)", "w_m2_nm": sea,
                 "photons_hz": float(noise.photon_rate_hz(sea, filter_nm))})
    e = float(noise.lux_to_spectral_irradiance(lux))
    rows.append({"source": f"{lux:g} lx daylight", "w_m2_nm": e,
                 "photons_hz": float(noise.photon_rate_hz(e, filter_nm))})
    if lamp_lm is not None:
        ill = float(noise.lamp_illuminance_lux(lamp_lm, lamp_distance, lamp_angle))
        w = float(noise.lamp_band_irradiance_w_m2(ill)) / 10.0
        rows.append({"source": f"lamp {lamp_lm:g} lm at {lamp_distance:g} m ({ill:.4g} lx)",
                     "w_m2_nm": w, "photons_hz": float(noise.photon_rate_hz(w, filter_nm))})
    for r in rows:
        r["detections_hz"] = r["photons_hz"] * pde
    _emit(rows, f"ambient light at 405 nm through a {filter_nm:g} nm filter", as_json)


@model.command(short_help="Rayleigh transmission of a horizontal path and the vertical "
                          "column (eq. 2.34-2.36).")
@click.option("--distance", "-d", multiple=True, type=float, default=(200.0,),
              show_default=True)
@click.option("--temperature", default=288.15, show_default=True, help="K")
@click.option("--altitude", default=0.0, show_default=True, help="m")
@click.option("--rh", default=0.0, show_default=True, help="relative humidity, 0..1")
@_json
def transmission(distance, temperature, altitude, rh, as_json) -> None:
    """Rayleigh transmission of a horizontal path (eq. 2.34-2.36) and the vertical column."""
    rows = []
    for d in distance:
        t = (atm.transmission(d, atm.pressure_pa(altitude), temperature) if altitude == 0
             else atm.transmission_at_altitude(d, altitude, temperature, rh))
        rows.append({"distance_m": d, "transmission": float(t),
                     "round_trip": float(t) ** 2})
    rows.append({"distance_m": "column (appendix G)",
                 "transmission": float(atm.column_transmission()), "round_trip": "-"})
    _emit(rows, f"transmission at {altitude:g} m, {temperature:g} K", as_json)


@model.command("predict", short_help="P of detecting the peak for Table 2.2's "
                                     "configurations (eq. 2.44-2.48).")
@click.option("--config", "-c", multiple=True, type=click.IntRange(1, 8),
              help="Table 2.2 configuration (default: all eight).")
@click.option("--distance", "-d", multiple=True, type=float,
              default=(1.0, 5.0, 10.0, 20.0, 30.0, 40.0), show_default=True)
@click.option("--gated/--no-gated", default=False, show_default=True)
@click.option("--out", "out_path", type=click.Path(), help="Write the full grid as parquet.")
@click.option("--plot", type=click.Path(), help="Figure 2.13 as a PNG.")
@_json
@_overwrite
def predict_cmd(config, distance, gated, out_path, plot, as_json, overwrite) -> None:
    """P of detecting the peak (eq. 2.44-2.48) for Table 2.2's configurations."""
    if out_path:
        check_out(out_path, overwrite=overwrite, fmt="parquet")
    if plot:
        check_out(plot, overwrite=overwrite, option="--plot", fmt="png")
    configs = config or tuple(range(1, 9))
    rows = []
    for c in configs:
        r = predict(TABLE_2_2[c - 1], distance, gated)
        rows.append({"config": c, **{f"{d:g} m": float(p) for d, p in
                                     zip(distance, r["p_detect"], strict=True)}})
    _emit(rows, f"P of detecting the peak ({'gated' if gated else 'no gating'})", as_json)
    if out_path:
        import polars as pl

        from pipeline.io.atomic import atomic_path

        with atomic_path(out_path) as tmp:
            pl.DataFrame(table_2_2_rows(np.arange(1.0, 61.0))).write_parquet(tmp)
        click.echo(f"wrote {out_path}", err=True)
    if plot:
        from pipeline.report.figures import figure_2_13

        figure_2_13(plot)
        click.echo(f"wrote {plot}", err=True)


@model.command("table")
@_json
def table_cmd(as_json) -> None:
    """Table 2.2 as read here (blanks carry the value from the column to the left)."""
    rows = [{"config": i, **asdict(s)} for i, s in enumerate(TABLE_2_2, start=1)]
    _emit(rows, "Table 2.2", as_json)


@model.command()
@click.argument("scene_path", type=click.Path(exists=True))
@click.option("--pixel", default=None, type=int, help="Pixel to show (default: strongest).")
@click.option("--cycles", default=40_000, show_default=True)
@click.option("--plot", type=click.Path(), help="The expected histogram as a PNG.")
@_json
@_overwrite
def histogram(scene_path, pixel, cycles, plot, as_json, overwrite) -> None:
    """Expected first-photon histogram of a scene's pixel, with the CRLB and the report."""
    if plot:
        check_out(plot, overwrite=overwrite, option="--plot", fmt="png")
    sm = evaluate(load_scene(scene_path), cycles)
    s = sm.scene.sensor
    px = int(np.argmax(sm.m_signal)) if pixel is None else pixel
    lsb = s.lsb_ps * 1e-12
    tof = sm.tof_in_window_s[px] if np.isfinite(sm.tof_in_window_s[px]) else -1.0
    h = first_photon_histogram(sm.m_signal[px], tof, sm.sigma_s, sm.bg_rate_hz[px],
                               sm.window_s, lsb, s.reset_ns * 1e-9)
    counts = h.counts(cycles)
    crlb = float(crlb_tof(cycles, sm.m_signal[px], tof, sm.sigma_s, sm.bg_rate_hz[px],
                          sm.window_s, lsb, s.reset_ns * 1e-9))
    rows = [{"pixel": px, "distance_m": float(sm.distance_m[px]),
             "m_signal": float(sm.m_signal[px]), "bg_rate_hz": float(sm.bg_rate_hz[px]),
             "peak_code": int(counts.size - 1 - np.argmax(counts)),
             "peak_count": float(counts.max()),
             "reset_peak": float(h.p_reset * cycles),
             "crlb_mm": crlb * 299_792_458 / 2 * 1e3}]
    _emit(rows, f"{sm.scene.name}: expected histogram over {cycles} cycles", as_json)
    if not as_json:
        rep = Table(title="effects")
        for col in ("effect", "status", "size", "detail", "domain"):
            rep.add_column(col)
        for e in sm.report:
            rep.add_row(e.name, e.status, f"{e.size:.3g}", e.detail, e.domain)
        out.print(rep)
    if plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(8, 4))
        codes = np.arange(counts.size)[::-1]  # reversed timing: early photons, high codes
        ax.step(codes, counts, where="mid")
        ax.set_xlabel("TDC code (D1st)")
        ax.set_ylabel("expected counts")
        ax.set_title(f"{sm.scene.name}, pixel {px}: expected histogram ({cycles} cycles)")
        Path(plot).parent.mkdir(parents=True, exist_ok=True)
        fig.savefig(plot, dpi=110, bbox_inches="tight")
        click.echo(f"wrote {plot}", err=True)


@model.command()
@click.option("--out", "out_dir", default="data/figures", show_default=True,
              type=click.Path())
@_overwrite
def figures(out_dir, overwrite) -> None:
    """Regenerate Figures 2.2, 2.13, 2.16 and 2.18 as PNGs (figure_2_2.png ...)."""
    for n in ("2_2", "2_13", "2_16", "2_18"):
        check_out(Path(out_dir) / f"figure_{n}.png", overwrite=overwrite, fmt="png")
    from pipeline.report.figures import all_figures

    for p in all_figures(out_dir):
        click.echo(str(p))
