"""``distance_sweep``: the thesis's range sweeps (section 5.3-5.4) on the simulator or on
captures: 0.2-3 m in 5 cm steps at a fixed gate, then 3.5-60 m with the gate moved along
(T_laser-win set so the return falls 40 ns before the window closes). Per distance and TDC:
range against truth, FWHM, detection; per distance: the spread across TDCs (uniformity).
Outputs under ``out/runs/<run>``: points.parquet (distance x TDC), summary.parquet,
figures like the thesis's 5.4-5.7 and report.md.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Annotated

import numpy as np
import polars as pl
from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from pydantic import Field

from flows.common import (
    Estimator,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    clean_leftovers,
    new_run_dir,
    prune_cache,
    report,
    run_namer,
    scene_dict,
    simulate,
    simulated,
    touch,
)
from pipeline.io.caldir import load_calibration
from pipeline.io.capture import Capture
from pipeline.offline.ranging import range_capture
from pipeline.report.report import markdown_table

C_M_PER_NS = 0.299792458
WINDOW_BEFORE_CLOSE_NS = 40.0


def default_distances() -> list[float]:
    short = np.round(np.arange(0.20, 3.0001, 0.05), 3)
    long = [3.5, 5.0, 7.5, 10.0, 15.0, 20.0, 25.0, 30.0, 40.0, 50.0, 60.0]
    return [float(d) for d in short] + long


def gate_ns(distance_m: float, delay_ns: float = 100.0, short_gate_ns: float = 140.0) -> float:
    """T_laser-win for a distance: the short-range gate up to 3 m, else the return placed
    ``WINDOW_BEFORE_CLOSE_NS`` before the window closes, on a 10 ns grid."""
    if distance_m <= 3.0:
        return short_gate_ns
    arrival = delay_ns + 2 * distance_m / C_M_PER_NS
    return float(10 * math.ceil((arrival + WINDOW_BEFORE_CLOSE_NS) / 10))


@task(cache_policy=NO_CACHE, task_run_name="range at {distance_m} m")
def range_point(capture: str, calibration: str, out: str, estimator: str,
                distance_m: float) -> list[dict]:
    """Range one capture; a row per TDC with the error against ``distance_m``."""
    t, note = range_capture(capture, load_calibration(calibration), out, estimator)
    if note:
        get_run_logger().warning("%s: %s", capture, note)
    d = t.column("distance_m").to_numpy()
    rows = pl.from_arrow(t).with_columns(
        true_m=pl.lit(distance_m), error_m=pl.lit(d) - distance_m,
        gate_ns=pl.lit(Capture(capture).meta.t_laser_win_ns))
    return rows.drop("measurement").to_dicts()


def summarise(points: pl.DataFrame) -> pl.DataFrame:
    """Per distance: median range and error over detected TDCs, mean FWHM, the spread of
    the per-TDC ranges (worst-case mismatch, like the thesis's uniformity figures), and the
    share of TDCs detecting."""
    det = points.filter(pl.col("detected"))
    s = (det.group_by("true_m").agg(
        pl.col("distance_m").median().alias("median_m"),
        pl.col("error_m").median().alias("median_error_m"),
        pl.col("error_m").abs().max().alias("worst_error_m"),
        (pl.col("distance_m").max() - pl.col("distance_m").min()).alias("mismatch_m"),
        pl.col("distance_m").std().alias("tdc_spread_m"),
        pl.col("fwhm_m").mean().alias("fwhm_mean_m"),
        pl.col("sigma_m").median().alias("sigma_median_m")))
    rate = points.group_by("true_m", "gate_ns").agg(
        pl.col("detected").mean().alias("detected"))
    return rate.join(s, on="true_m", how="left").sort("true_m")


@task(cache_policy=NO_CACHE)
def figures(points: pl.DataFrame, summary: pl.DataFrame, run: str) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from pipeline.report.figures import _save

    run = Path(run)
    paths = []
    for name, lo, hi in (("short", 0.0, 3.01), ("long", 3.01, 1e9)):
        s = summary.filter((pl.col("true_m") > lo) & (pl.col("true_m") < hi))
        p = points.filter((pl.col("true_m") > lo) & (pl.col("true_m") < hi)
                          & pl.col("detected"))
        if s.is_empty():
            continue
        fig, ax = plt.subplots(1, 3, figsize=(15, 4.2))
        first = p.filter(pl.col("tdc") == p["tdc"].min())
        ax[0].plot(s["true_m"], s["true_m"], "k--", lw=0.8, label="ideal")
        ax[0].plot(first["true_m"], first["distance_m"], ".", label=f"TDC {p['tdc'].min()}")
        ax[0].set_xlabel("actual distance (m)")
        ax[0].set_ylabel("measured (m)")
        ax[0].set_title(f"range of the first detector ({name}; Fig. 5.4/5.6)")
        ax[0].legend()
        ax[1].plot(s["true_m"], s["median_error_m"] * 100, "o-", ms=3, label="median over TDCs")
        ax[1].fill_between(s["true_m"], (s["median_error_m"] - s["mismatch_m"] / 2) * 100,
                           (s["median_error_m"] + s["mismatch_m"] / 2) * 100, alpha=0.3,
                           label="spread across TDCs")
        ax[1].plot(s["true_m"], s["fwhm_mean_m"] * 100, "s-", ms=3, label="FWHM (mean)")
        ax[1].set_xlabel("actual distance (m)")
        ax[1].set_ylabel("cm")
        ax[1].set_title("error and FWHM (Fig. 5.5)")
        ax[1].legend(fontsize=8)
        ax[1].grid(alpha=0.3)
        piv = (p.pivot(on="tdc", index="true_m", values="error_m",
                       aggregate_function="median").sort("true_m"))
        img = piv.drop("true_m").to_numpy().T * 100
        im = ax[2].imshow(img, aspect="auto", cmap="coolwarm", origin="lower",
                          extent=[0, piv.height, -0.5, img.shape[0] - 0.5],
                          vmin=-np.nanmax(np.abs(img)), vmax=np.nanmax(np.abs(img)))
        ax[2].set_xlabel("distance step")
        ax[2].set_ylabel("TDC")
        ax[2].set_title("error per TDC, cm (uniformity; Fig. 5.7)")
        fig.colorbar(im, ax=ax[2])
        paths.append(str(_save(fig, run / f"sweep_{name}.png")))
    return paths


#: a sweep that runs longer than this is failed by Prefect (the default sweep: ~70 points)
SWEEP_TIMEOUT_S = 12 * 3600


@flow(name="distance_sweep", timeout_seconds=SWEEP_TIMEOUT_S,
      flow_run_name=run_namer("sweep", {"stream": "on stream", "captures": "on captures"}))
def distance_sweep(out: str = "data/sweeps", calibration: str | None = None,
                   distances: Annotated[list[PositiveFloat], Field(min_length=1)] | None = None,
                   cycles: PositiveInt = 20_000, estimator: Estimator = "ml",
                   n_pixels: PositiveInt = 128, chip_seed: NonNegativeInt = 1,
                   seed: NonNegativeInt = 100, captures: str | None = None,
                   stream: str | None = None, runs: dict[str, float] | None = None,
                   cache_max_gb: PositiveFloat = 20.0,
                   cache_max_age_days: PositiveFloat = 30.0) -> dict:
    """Range against truth over distance, on the simulator (a calibration campaign first
    when no ``calibration`` is given), on ``captures`` (a directory of range captures
    whose sidecar truth holds the distance), or on a running daemon's datasets: ``stream``
    (its sink's ``out``) with ``runs`` mapping each run id to the distance it measured.
    The capture cache is bounded as the campaign's (``cache_max_gb``, ``_age_days``)."""
    log = get_run_logger()
    run = new_run_dir(out, "distance_sweep", calibration=calibration, captures=captures,
                      stream=stream)
    if stream is not None:
        return _from_stream(run, stream, runs or {}, log)
    if calibration is None:
        from flows.calibration import calibration_campaign

        cal = calibration_campaign(out=str(Path(out) / "calibration"), n_pixels=n_pixels,
                                   chip_seed=chip_seed)
        calibration = cal["current"]
    cache = str(Path(out) / "cache")
    clean_leftovers(cache, log=log)
    jobs = []  # (capture, true distance)
    if captures:
        for side in sorted(Path(captures).glob("*.json")):
            cap = Capture(side.with_suffix(""))
            truth = cap.meta.truth or {}
            d = [x for x in truth.get("distance_m", []) if x is not None]
            if cap.meta.kind == "range" and d:
                jobs.append((str(cap.bin_path), float(np.median(d))))
        if not jobs:
            raise ValueError(f"{captures}: no range captures with a true distance")
    else:
        distances = default_distances() if distances is None else distances
        args = []
        for i, d in enumerate(distances):
            base = "short_range" if d <= 3.0 else "long_range"
            sc = scene_dict(base, distance_m=d, t_laser_win_ns=gate_ns(d), n_pixels=n_pixels)
            args.append((sc, cycles, cache, seed + i, chip_seed))
        caps = simulated([simulate.submit(*a) for a in args], args)
        jobs = list(zip(caps, distances, strict=True))
        used = {Path(c).parent.name for c in caps}
        for name in used:
            touch(Path(cache) / name)
        prune_cache(cache, cache_max_gb, cache_max_age_days, keep=used, log=log)
    ranged = [range_point.submit(c, calibration, str(run / "ranges" / f"{i:03d}.parquet"),
                                 estimator, d) for i, (c, d) in enumerate(jobs)]
    points = pl.DataFrame([r for f in ranged for r in f.result()])
    points.write_parquet(run / "points.parquet")
    summary = summarise(points)
    summary.write_parquet(run / "summary.parquet")
    pngs = figures(points, summary, str(run))
    return _report(run, points, summary, pngs, log, len(jobs), setup=(
        f"calibration `{calibration}`; estimator {estimator}; " + (
            f"captures in {captures}" if captures else
            f"simulator, {cycles:,} cycles per point, chip seed {chip_seed}")))


@task(cache_policy=NO_CACHE)
def read_stream(stream: str, runs: dict[str, float]) -> pl.DataFrame:
    """The ranges a daemon wrote for ``runs`` (every measurement), with the truth."""
    frames = []
    for name, d in runs.items():
        files = sorted(Path(stream).glob(f"ranges/date=*/run={name}/*.parquet"))
        if not files:
            raise ValueError(f"{stream}: no ranges of run {name!r} (is it a daemon's sink "
                             "directory, and did the run have a [range] stage?)")
        r = pl.read_parquet(files)
        frames.append(r.with_columns(true_m=pl.lit(float(d)),
                                     error_m=pl.col("distance_m") - float(d),
                                     gate_ns=pl.lit(None, pl.Float64)).drop("measurement"))
    return pl.concat(frames)


def _from_stream(run: Path, stream: str, runs: dict[str, float], log) -> dict:
    if not runs:
        raise ValueError("a sweep on a daemon's datasets needs runs: {run id: distance}")
    points = read_stream(stream, runs)
    points.write_parquet(run / "points.parquet")
    summary = summarise(points)
    summary.write_parquet(run / "summary.parquet")
    pngs = figures(points, summary, str(run))
    return _report(run, points, summary, pngs, log, len(runs),
                   setup=f"the daemon's datasets in {stream}, runs {runs}")


def _report(run: Path, points: pl.DataFrame, summary: pl.DataFrame, pngs: list[str], log,
            n_points: int, setup: str) -> dict:
    det = points.filter(pl.col("detected"))
    short = summary.filter(pl.col("true_m") <= 3.0)
    long = summary.filter(pl.col("true_m") > 3.0)
    facts = {
        "points": n_points, "tdcs": int(points["tdc"].n_unique()),
        "detected": float(points["detected"].mean()),
        "median_abs_error_cm": float(det["error_m"].abs().median() * 100),
        "short_fwhm_cm": [float(short["fwhm_mean_m"].min() * 100),
                          float(short["fwhm_mean_m"].mean() * 100),
                          float(short["fwhm_mean_m"].max() * 100)] if short.height else None,
        "long_fwhm_cm": [float(long["fwhm_mean_m"].min() * 100),
                         float(long["fwhm_mean_m"].mean() * 100),
                         float(long["fwhm_mean_m"].max() * 100)] if long.height else None,
        "worst_mismatch_cm": float(summary["mismatch_m"].max() * 100),
    }
    log.info("sweep: %s", facts)
    table = summary.select(
        "true_m", "gate_ns", "detected",
        (pl.col("median_error_m") * 100).alias("median error cm"),
        (pl.col("mismatch_m") * 100).alias("TDC mismatch cm"),
        (pl.col("fwhm_mean_m") * 100).alias("FWHM cm"))
    rep = report(str(run / "report.md"), "Distance sweep", [
        ("Setup", f"{setup}; {n_points} distances x {facts['tdcs']} TDCs."),
        ("Summary", "\n".join(f"- {k}: {v}" for k, v in facts.items())),
        ("Per distance", markdown_table(table)),
        ("Plots", "\n".join(f"![{Path(p).stem}]({Path(p).name})" for p in pngs)),
    ])
    result = {"run": str(run), "report": rep, "plots": pngs, **facts}
    (run / "summary.json").write_text(json.dumps(result, indent=1))
    return result
