"""``tcspc calibrate density|lsb|plan|delay`` (docs/design.md "Command line")."""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from pipeline.cli.app import _overwrite, check_out
from pipeline.cli.console import console, note, warn
from pipeline.io.capture import Capture
from pipeline.offline.calibrate import (
    add_delay,
    density_from_capture,
    lsb_campaign,
    write_caldir,
)
from schemas.errors import CalibrationError
from stages import calibration as cal
from stages.histogram import HistogramAccumulator

err = console(stderr=True)


@click.group()
def calibrate() -> None:
    """Density test, LSB against light, zero-distance delay; distance (any instrument)."""


_inl = click.option("--inl-rms", default=0.5, show_default=True, type=float,
                    help="Refuse a capture whose INL would be worse than this (LSB RMS).")


def _check_outs(out: str, plot: str | None, overwrite: bool,
                contents: tuple[str, ...] = ("tdc.parquet", "meta.json")) -> None:
    """A calibration directory and its figure, checked before any work."""
    check_out(out, "dir", overwrite, contents=contents)
    if plot:
        check_out(plot, overwrite=overwrite, option="--plot", fmt="png")


def _report(res: cal.DensityResult, second: cal.SecondStage) -> None:
    ok = res.ok
    err.print(f"TDCs calibrated: {ok.sum()} of {ok.size}"
              + (f"; flagged: {np.flatnonzero(~ok).tolist()}" if (~ok).any()
                 else ""))
    for t in np.flatnonzero(~ok)[:16]:  # why, where the density test said
        if res.reasons[t]:
            err.print(f"  TDC {t}: {res.reasons[t]}")
    if ok.any():
        err.print(f"LSB {np.nanmin(res.lsb_s) * 1e12:.2f}..{np.nanmax(res.lsb_s) * 1e12:.2f} ps;"
                  f" worst |DNL| {np.nanmax(np.abs(res.dnl_lsb)):.2f} LSB, worst |INL| "
                  f"{np.nanmax(np.abs(res.inl_lsb)):.2f} LSB; INL statistical error "
                  f"~{np.nanmax(res.inl_error_lsb):.2f} LSB RMS; light "
                  f"{np.nanmean(res.detections_per_cycle):.3f} STARTs/pixel/cycle")
        err.print(f"Nmin {second.n_min.min()}..{second.n_min.max()}, Nmax "
                  f"{second.n_max.min()}..{second.n_max.max()}")


@calibrate.command()
@click.argument("capture", type=click.Path())
@click.option("--out", required=True, type=click.Path(), help="calibration directory")
@click.option("--plot", type=click.Path(), help="DNL/INL of all TDCs as a PNG.")
@click.option("--fill", "fill", multiple=True, type=click.Path(),
              help="A density test at dimmer light (repeatable): it measures the codes "
                   "under CAPTURE's reset peak, whose random DNL otherwise tilts the INL "
                   "by up to ~0.1 LSB.")
@_inl
@_overwrite
def density(capture, out, plot, fill, inl_rms, overwrite) -> None:
    """Density test of a uniform-light CAPTURE: DNL, INL, LSB, Nmin/Nmax/Nth/PDM."""
    _check_outs(out, plot, overwrite)
    cap = Capture(capture)
    others = [Capture(p) for p in fill]
    var: dict = {}
    res, second = density_from_capture(cap, inl_rms, fill=others, variance=var)
    write_caldir(out, res, second, [cap.bin_path] + [c.bin_path for c in others],
                 width_var=var.get("width_var"))
    _report(res, second)
    if plot:
        from pipeline.report.figures import density_figure

        density_figure(res, plot)
    err.print(f"wrote {out}")


@calibrate.command(short_help="Density tests at several light levels: LSB per TDC against "
                              "light (eq. 5.1).")
@click.argument("captures", nargs=-1, required=True, type=click.Path())
@click.option("--out", required=True, type=click.Path(), help="calibration directory")
@click.option("--plot", type=click.Path(), help="LSB against light as a PNG.")
@_inl
@_overwrite
def lsb(captures, out, plot, inl_rms, overwrite) -> None:
    """Density tests at several light levels: LSB per TDC as a cubic in eq. 5.1's n."""
    _check_outs(out, plot, overwrite)
    try:
        _, fit, n, lsbs = lsb_campaign(captures, out, inl_rms, log=err.print)
    except CalibrationError as exc:
        raise click.ClickException(str(exc)) from None
    err.print(f"cubic fit over n = {n.min():.3f}..{n.max():.3f}; residuals up to "
              f"{np.nanmax(np.abs(fit.residual_ps)):.3f} ps")
    if plot:
        from pipeline.report.figures import lsb_figure

        lsb_figure(n, lsbs, fit, plot)
    err.print(f"wrote {out}")


@calibrate.command(short_help="The density tests to take, planned from a zero-distance "
                              "capture.")
@click.argument("zero", type=click.Path())
@click.option("--cycles-budget", required=True, type=click.FloatRange(min=1e4),
              help="Cycles all the density tests may take together.")
@click.option("--out", required=True, type=click.Path(dir_okay=False),
              help="The plan as JSON: {\"tests\": [{\"light\": X, \"cycles\": N}, ...]}.")
@_overwrite
def plan(zero, cycles_budget, out, overwrite) -> None:
    """The density tests to take, planned from a zero-distance capture ZERO: the LSB fit's
    light levels (and one at ZERO's light where it helps), the budget spent where the
    delay's counting error comes from (docs/calibration.md). Prints the delay error per
    TDC it expects from counting."""
    import json
    from pathlib import Path

    from pipeline.offline.calibrate import density_histograms

    check_out(out, overwrite=overwrite)
    cap = Capture(zero)
    state, _ = density_histograms(cap)
    p = cal.plan_tests(state.hits, state.cycles, cycles_budget, cap.meta.window_ns * 1e-9)
    Path(out).write_text(json.dumps(p.to_json(), indent=1) + "\n")
    for n, c in zip(p.lights, p.cycles, strict=True):
        err.print(f"density test at {n:.4g} detections/pixel/cycle: {int(c):,} cycles",
                  highlight=False)
    e = p.delay_error_ps
    if np.isfinite(e).any():
        err.print(f"expected delay error from counting: {np.nanmedian(e):.1f} ps median, "
                  f"{np.nanmax(e):.1f} ps worst (TDC {int(np.nanargmax(e))}); per TDC: "
                  + " ".join(f"{v:.0f}" if np.isfinite(v) else "-" for v in e),
                  highlight=False)
    missing = np.flatnonzero(~np.isfinite(e))
    if missing.size:
        warn(f"no return found on TDC(s) {missing[:12].tolist()} of {zero}: no delay "
             "error expected for them", err)
    err.print(f"wrote {out}")


@calibrate.command(short_help="System delay per TDC from a zero-distance capture "
                              "(eq. 5.3).")
@click.argument("capture", type=click.Path())
@click.option("--out", required=True, type=click.Path(exists=True, file_okay=False),
              help="calibration directory with a density test; the delay is added to it")
@click.option("--distance-m", default=0.0, show_default=True, type=float,
              help="The target's distance in CAPTURE (eq. 5.3 with its round trip).")
def delay(capture, out, distance_m) -> None:
    """System delay per TDC from a zero-distance CAPTURE (eq. 5.3), into CALDIR; or from
    a capture of a target at a known --distance-m.

    The peak is found as the range stage finds it (ML, pile-up exact), anywhere in the
    window. Give the capture ambient light brighter than the density test's (its reset
    peak ~10 codes lower): its own reset peak then scales the time axis at its exact light
    where the return keeps clear of it; otherwise the LSB polynomial does (within the
    statistics of the density tests' INL either way). That ambient light, clear of the
    return and the reset peak, is also counted as one more density test: the table's code
    widths take its counts (once per capture; docs/calibration.md). Prints how many TDCs
    got a delay and why the others did not; exits non-zero, leaving CALDIR as it was, when
    none did."""
    from collections import Counter

    from pipeline.io.atomic import OutputError

    if not (Path(out) / "tdc.parquet").is_file():
        raise OutputError(f"--out {out}: not a calibration directory (no tdc.parquet; "
                          "`tcspc calibrate density` or `lsb` makes one)")
    check_out(Path(out) / "tdc.parquet", overwrite=True, schema="calibration_tdc")
    calib = add_delay(capture, out, log=lambda m: err.print(f"delay: {m}", highlight=False),
                      distance_m=distance_m)
    d, used = calib.delay_s, calib.meta["delay"]
    got = np.isfinite(d)
    err.print(f"delay on {int(got.sum())} of {d.size} TDCs: "
              f"{np.nanmin(d) * 1e9:.4f}..{np.nanmax(d) * 1e9:.4f} ns; time axis from the "
              f"capture's reset peak on {used['scale_from_reset_peak']} of {d.size} TDCs; "
              f"wrote {out}", highlight=False)
    if not got.all():
        why = Counter(r for r in calib.delay_reasons if r)
        warn(f"no delay on {int((~got).sum())} TDC(s) {np.flatnonzero(~got)[:12].tolist()}: "
             + "; ".join(f"{n} {r}" for r, n in why.most_common()), err)


@calibrate.command()
@click.argument("histograms", type=click.Path(exists=True, dir_okay=False))
@click.option("--truth", required=True, type=click.Path(exists=True, dir_okay=False),
              help="CSV: measurement,distance_m (and optionally tdc, a row's own distance).")
@click.option("--out", required=True, type=click.Path(), help="calibration directory")
@click.option("--p-fa", default=1e-3, show_default=True, help="False-alarm probability.")
@_overwrite
def distance(histograms, truth, out, p_fa, overwrite) -> None:
    """Delay and bin width per row of generic HISTOGRAMS from targets at known distances.

    For every estimator and row: the delay (eq. 5.3 at the target's distance) and, from
    two or more distances, the real bin width (one distance: the file's bin_width_ps);
    the instrument response measured on the reference channel (or the rows at the middle
    distance, aligned and summed); from three or more distances, where the background
    behind the returns is thinned (pile-up, p < 0.01), the effective laser pulses of an
    instrument that does not report them. Prints the fit's residuals and RMS, and what
    pile-up model was chosen and why."""
    from pipeline.offline.generic import CALIBRATION_FILE, calibrate_distance

    _check_outs(out, None, overwrite, contents=(CALIBRATION_FILE,))
    try:
        cal = calibrate_distance(histograms, truth, p_fa=p_fa)
    except (CalibrationError, ValueError) as exc:
        from pipeline.cli.instruments import BadInput

        raise BadInput(str(exc)) from None
    if cal.missing:
        warn(f"{truth}: {len(cal.missing)} measurement(s) not in {histograms}, left out: "
             f"{', '.join(cal.missing[:8])}" + (" ..." if len(cal.missing) > 8 else ""), err)
    cal.save(out)
    err.print(f"{len(cal.measurements)} measurement(s) at "
              f"{', '.join(f'{d:.4g}' for d in sorted(set(cal.distances_m)))} m; "
              f"{len(cal.tdc)} rows; response: {cal.response.source}; pile-up: {cal.pileup}",
              highlight=False)
    for name, fit in cal.fits.items():
        w = np.asarray(fit["bin_width_ps"], float)
        res = np.asarray(fit["residual_mm"], float)
        worst = np.nanmax(np.abs(res)) if np.isfinite(res).any() else np.nan
        err.print(f"  {name:9s} residual RMS {fit['rms_mm']:.3f} mm (worst {worst:.3f} mm); "
                  f"bin width {np.nanmin(w):.2f}..{np.nanmax(w):.2f} ps; delay "
                  f"{np.nanmin(fit['delay_ps']):.1f}..{np.nanmax(fit['delay_ps']):.1f} ps",
                  highlight=False)
    for name in ("matched", "ml"):
        if name in cal.fits and cal.preferred(name) != name:
            err.print(f"  {name}: the Gaussian of the response's FWHM fits better than the "
                      "measured shape; range uses it", highlight=False)
    none = [t for t, d in zip(cal.tdc, cal.fits["ml"]["delay_ps"], strict=True)
            if not np.isfinite(d)]
    if none:
        warn(f"no delay (no detection) on rows {none}")
    err.print(f"wrote {out}")


@calibrate.command()
@click.argument("capture", type=click.Path())
@click.option("--calibration", required=True, type=click.Path(exists=True, file_okay=False))
@click.option("--out", type=click.Path(), help="Per-TDC drift as parquet.")
@click.option("--tolerance-ps", default=1.0, show_default=True,
              help="Report TDCs whose LSB drifted more than this.")
@_overwrite
def track(capture, calibration, out, tolerance_ps, overwrite) -> None:
    """Online tracking: the LSB from CAPTURE's background photons against CALIBRATION.

    Background in an ordinary range capture is a density test too; its signal peaks are
    masked. Reports each TDC's drift from the calibration's LSB at the capture's light.
    """
    from pipeline.io.caldir import load_calibration

    if out:
        check_out(out, overwrite=overwrite, fmt="parquet")
    calib = load_calibration(calibration)
    cap = Capture(capture)
    acc = HistogramAccumulator(cap.meta.n_tdc, calib.bounds, count_artifacts=True)
    for first, words in cap.iter_chunks():
        acc.update(words, first)
    st = acc.snapshot()
    light = float(st.hits.sum() / (st.n_tdc * max(st.cycles.max(), 1)))
    expected, why = calib.lsb_s(light)
    if why:
        note(why, err)
    tr = cal.track_lsb(st.hits, st.cycles, cap.meta.window_ns * 1e-9, expected,
                       artifacts=st.artifacts)
    d = tr.drift_ps
    ok = np.isfinite(d)
    err.print(f"light {tr.light:.3f} STARTs/pixel/cycle; LSB measured on {ok.sum()} of "
              f"{ok.size} TDCs; drift mean {np.nanmean(d):+.3f} ps, max |drift| "
              f"{np.nanmax(np.abs(d)):.3f} ps")
    for t in np.flatnonzero(tr.flagged):
        warn(f"TDC {t}: estimate left out: {tr.why[t]}")
    moved = np.flatnonzero(ok & (np.abs(d) > tolerance_ps))
    if moved.size:
        err.print(f"TDCs beyond {tolerance_ps} ps: {moved.tolist()} (recalibrate)")
    if out:
        import polars as pl

        from pipeline.io.atomic import atomic_path

        with atomic_path(out) as tmp:
            pl.DataFrame({"tdc": np.arange(d.size, dtype=np.uint16),
                          "lsb_ps": tr.lsb_s * 1e12, "expected_ps": tr.expected_s * 1e12,
                          "drift_ps": d, "hits": tr.hits,
                          "untrusted": list(tr.why)}).write_parquet(tmp)
        err.print(f"wrote {out}")


