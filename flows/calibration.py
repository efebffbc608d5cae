"""``calibration_campaign``: density tests at several light levels -> INL and the LSB
polynomial (eq. 5.1), a zero-distance delay (eq. 5.3), compared with the current
calibration and published only when it is not worse.

Layout under ``out`` (default ``data/calibration``)::

    current/                 the published calibration directory (what `tcspc range` uses)
    runs/<time>-<id>/        one per run: calibration/ (the candidate), report.md, *.png,
                             tests.parquet (one row per density test)
    cache/                   simulated captures, keyed on everything their words depend on

Publishing replaces ``current`` by a rename, so a run that fails at any step (or refuses
its candidate) leaves the old calibration in place, whole.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import polars as pl
from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE

from flows.common import new_run_dir, report, scene_dict, simulate
from pipeline.io.atomic import atomic_path
from pipeline.io.caldir import load_calibration
from pipeline.io.capture import Capture
from pipeline.offline.calibrate import add_delay, lsb_campaign, over_finite, quality
from pipeline.report.report import markdown_table
from schemas.errors import CalibrationError

#: five levels (a cubic through four would have no residual to judge it by), from below the
#: delay capture's light (~0.02 STARTs per pixel per cycle) to ~0.45 (100..3500 lux of the
#: older lux conversion, 1.3395 times brighter per lux: the same light, docs/decisions.md)
DEFAULT_LUX = [133.950, 401.849, 1071.599, 2411.097, 4688.244]


def captures_in(directory: str | Path) -> tuple[list[Path], Path]:
    """Density captures and the zero-distance capture of a directory, by sidecar ``kind``."""
    d = Path(directory)
    density, delay = [], []
    for side in sorted(d.glob("*.json")):
        cap = Capture(side.with_suffix(""))
        (density if cap.meta.kind == "density" else delay if cap.meta.kind == "delay"
         else []).append(cap.bin_path)
    if not density or len(delay) != 1:
        raise CalibrationError(f"{d}: need density captures and exactly one delay capture "
                               f"(sidecar kind); found {len(density)} density, {len(delay)} "
                               "delay")
    return density, delay[0]


def _open(c):
    """A capture path, or a daemon's journal run already opened as one."""
    return c if hasattr(c, "iter_chunks") else Capture(c)


def _label(c) -> str:
    return f"journal run {c.name}" if hasattr(c, "paths") else str(c)


@task(cache_policy=NO_CACHE)
def fit_lsb(captures: list, candidate: str, inl_rms: float) -> dict:
    """Density tests -> INL and LSB polynomial, into the candidate directory."""
    log = get_run_logger()
    best, fit, n, lsbs = lsb_campaign(captures, candidate, inl_rms, log=log.info)
    return {"n": n.tolist(), "lsb_ps": lsbs.tolist(), "coef": fit.coef.tolist(),
            "residual_ps": fit.residual_ps.tolist(),
            "inl_error_lsb": float(np.nanmedian(best.inl_error_lsb[best.ok]))}


@task(cache_policy=NO_CACHE)
def measure_delay(capture, candidate: str) -> tuple[list[float], str]:
    """Zero-distance capture -> delay per TDC (eq. 5.3), added to the candidate; and why
    there is none ("" when some TDC got one). A candidate without a delay is not failed
    here: the verdict refuses it against a current calibration that has one."""
    try:
        return (add_delay(capture, candidate).delay_s * 1e9).tolist(), ""
    except CalibrationError as exc:
        get_run_logger().warning("no delay: %s", exc)
        return [float("nan")] * load_calibration(candidate).n_tdc, str(exc)


@task(cache_policy=NO_CACHE)
def verdict(candidate: str, current: str) -> list[str]:
    """Why the candidate is worse than the current calibration (empty: publish it)."""
    if not (Path(current) / "meta.json").exists():
        return []
    return quality(candidate).worse_than(quality(current))


@task(retries=2, retry_delay_seconds=1, cache_policy=NO_CACHE)
def publish(candidate: str, current: str) -> str:
    """Copy the candidate over ``current`` in one rename (I/O only, so it may retry)."""
    with atomic_path(current) as tmp:
        shutil.copytree(candidate, tmp)
    return current


@task(cache_policy=NO_CACHE)
def plots(candidate: str, fit: dict, run: str) -> list[str]:
    from pipeline.report.figures import density_figure, lsb_figure

    calib = load_calibration(candidate)
    res = calib.density
    a = density_figure(res, Path(run) / "density.png")
    b = lsb_figure(np.asarray(fit["n"]), np.asarray(fit["lsb_ps"]), calib.lsb_fit,
                   Path(run) / "lsb.png")
    return [str(a), str(b)]


def _truth_check(captures: list, delay_capture, fit: dict,
                 delay_ns: list[float]) -> tuple[str, dict]:
    """Against the simulator's truth (when the captures carry it): LSB error per density
    test, INL error of the published table, delay error."""
    truths = [_open(c).meta.truth for c in captures]
    if not all(truths):
        return "The captures carry no truth (a real sensor): nothing to check against.", {}
    lsb_meas = np.asarray(fit["lsb_ps"])
    lsb_true = np.column_stack([t["chip"]["lsb_window_ps"] for t in truths])
    err = lsb_meas - lsb_true
    dt = _open(delay_capture).meta.truth
    d_true = dt["delay_ns"] + 2 * np.nan_to_num(np.array(dt["distance_m"], float)) / 0.299792458
    d_err_ps = (np.asarray(delay_ns) - d_true) * 1e3
    figures = {"lsb_error_rms_ps": over_finite(lambda v: np.sqrt(np.mean(v ** 2)), err),
               "lsb_error_max_ps": over_finite(lambda v: np.max(np.abs(v)), err),
               "delay_error_median_ps": over_finite(np.median, d_err_ps),
               "delay_error_rms_ps": over_finite(lambda v: np.sqrt(np.mean(v ** 2)), d_err_ps)}
    text = (f"LSB against the chip's truth over {err.shape[1]} light levels: RMS error "
            f"{figures['lsb_error_rms_ps']:.3f} ps, worst {figures['lsb_error_max_ps']:.3f} ps."
            f"\nDelay against the truth (system delay + 2 d / c): median error "
            f"{figures['delay_error_median_ps']:+.1f} ps, RMS {figures['delay_error_rms_ps']:.1f}"
            " ps over the TDCs.")
    return text, figures


@flow(name="calibration_campaign")
def calibration_campaign(out: str = "data/calibration", lux: list[float] | None = None,
                         cycles: int = 400_000, delay_cycles: int = 200_000,
                         n_pixels: int = 128, chip_seed: int = 1, seed: int = 0,
                         inl_rms: float = 0.5, captures: str | None = None,
                         journal: str | None = None, density_runs: list[str] | None = None,
                         delay_run: str | None = None, force: bool = False) -> dict:
    """Calibrate the chip: density tests at ``lux`` levels, the zero-distance delay, then
    publish to ``out/current`` unless the candidate is worse than what is there (``force``
    publishes anyway). Runs on the simulator unless ``captures`` names a directory of
    density captures and one delay capture, or ``journal`` a running daemon's journal
    (``STATE/journal``) with the runs it recorded under uniform light (``density_runs``)
    and at zero distance (``delay_run``)."""
    log = get_run_logger()
    run = new_run_dir(out, "calibration_campaign")
    cache = str(Path(out) / "cache")
    if journal:
        from pipeline.stream.journal import JournalCapture

        if not density_runs or not delay_run:
            raise CalibrationError("a campaign on a daemon's journal needs density_runs and "
                                   "delay_run")
        density_caps = [JournalCapture(journal, r) for r in density_runs]
        delay_cap = JournalCapture(journal, delay_run)
        source = f"daemon journal {journal}: runs {density_runs}, delay run {delay_run}"
    elif captures:
        density_caps, delay_cap = captures_in(captures)
        source = f"captures in {captures}"
    else:
        lux = DEFAULT_LUX if lux is None else lux
        futures = [simulate.submit(scene_dict("density", lux=lv, n_pixels=n_pixels), cycles,
                                   cache, seed + i, chip_seed) for i, lv in enumerate(lux)]
        delay_f = simulate.submit(scene_dict("delay", n_pixels=n_pixels), delay_cycles, cache,
                                  seed + len(lux), chip_seed)
        density_caps = [Path(f.result()) for f in futures]
        delay_cap = Path(delay_f.result())
        source = (f"simulator: chip seed {chip_seed}, {n_pixels} pixels, {cycles:,} cycles at "
                  f"{lux} lux, delay {delay_cycles:,} cycles")
    candidate = str(run / "calibration")
    fit = fit_lsb([c if hasattr(c, "paths") else str(c) for c in density_caps], candidate,
                  inl_rms)
    delay_ns, no_delay = measure_delay(
        delay_cap if hasattr(delay_cap, "paths") else str(delay_cap), candidate)
    delay_text = (f"delay {np.nanmin(delay_ns):.4f}..{np.nanmax(delay_ns):.4f} ns"
                  if not no_delay else f"no delay ({no_delay})")
    pngs = plots(candidate, fit, str(run))
    current = str(Path(out) / "current")
    worse = verdict(candidate, current)
    published = force or not worse
    if published:
        publish(candidate, current)
        log.info("published %s", current)
    else:
        log.warning("candidate NOT published (worse than %s): %s", current, "; ".join(worse))
    truth_text, truth = _truth_check(density_caps, delay_cap, fit, delay_ns)
    tests = pl.DataFrame({"capture": [_label(c) for c in density_caps],
                          "detections_per_pixel_per_cycle": fit["n"],
                          **{f"lsb_{name}_ps": [over_finite(fn, col) for col in
                                                np.asarray(fit["lsb_ps"], float).T]
                             for name, fn in (("mean", np.mean), ("min", np.min),
                                              ("max", np.max))}})
    tests.write_parquet(run / "tests.parquet")
    q = quality(candidate)
    summary = {"run": str(run), "candidate": candidate, "current": current,
               "published": published, "refused_because": worse, "quality": q.__dict__,
               "delay_ns": [float(np.nanmin(delay_ns)), float(np.nanmax(delay_ns))]
               if not no_delay else None, "no_delay": no_delay,
               "plots": pngs, "truth": truth,
               "captures": {"density": [_label(c) for c in density_caps],
                            "delay": _label(delay_cap)}}
    verdict_text = ("Published to `current`." if published and not worse else
                    "Published to `current` (forced) although: " + "; ".join(worse)
                    if published else "**Not published**: " + "; ".join(worse)
                    + ". The current calibration stays in place.")
    rep = report(str(run / "report.md"), "Calibration campaign", [
        ("Source", source),
        ("Verdict", verdict_text),
        ("Density tests", markdown_table(tests.drop("capture"))),
        ("Quality", f"TDCs calibrated: {q.tdcs_ok}; median INL statistical error "
                    f"{q.inl_error_lsb:.3f} LSB RMS; LSB fit residual {q.lsb_residual_ps:.3f} "
                    f"ps RMS; {delay_text}."),
        ("Against the truth", truth_text),
        ("Plots", "\n".join(f"![{Path(p).stem}]({Path(p).name})" for p in pngs)),
    ])
    summary["report"] = rep
    (run / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    return summary
