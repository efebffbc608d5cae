"""``calibration_campaign``: density tests at several light levels -> INL and the LSB
polynomial (eq. 5.1), a zero-distance delay (eq. 5.3), compared with the current
calibration and published only when it is not worse.

Layout under ``out`` (default ``data/calibration``)::

    current -> versions/<run>  the published calibration (what `tcspc range` uses): a link,
                               replaced in one rename, so it is never missing
    versions/<run>/            the last KEEP_VERSIONS published calibrations
    runs/<time>-<id>/          one per run: calibration/ (the candidate), report.md, *.png,
                               tests.parquet (one row per density test), summary.json
    cache/                     simulated captures, fits and delays, keyed on their inputs
                               and the code version (bounded: cache_max_gb, _age_days)
    .lock                      held by the campaign running (one at a time)
    .lock.wait-PID             a campaign waiting for it

A run that fails at any step (or refuses its candidate) leaves the old calibration in
place, whole. The run ends in a state named for its outcome, ``Published`` or ``Refused``
(both Completed), and emits the event ``tcspc.calibration.published`` or
``tcspc.calibration.refused`` for automations.
"""

from __future__ import annotations

import datetime as dt
import json
import re
import shutil
from pathlib import Path
from typing import Annotated

import numpy as np
import polars as pl
from prefect import flow, get_run_logger, task
from prefect.cache_policies import NO_CACHE
from prefect.states import Completed
from pydantic import Field

from flows.common import (
    NonNegativeFloat,
    NonNegativeInt,
    PositiveFloat,
    PositiveInt,
    Stored,
    check_roots,
    clean_leftovers,
    content_key,
    exclusive,
    file_identity,
    flow_run_info,
    mark_crashed,
    new_run_dir,
    prune_cache,
    remade_if_gone,
    report,
    run_namer,
    scene_dict,
    simulate,
    simulated,
    touch,
)
from pipeline.io.atomic import atomic_path, point_link
from pipeline.io.caldir import load_calibration
from pipeline.io.capture import Capture
from pipeline.offline.calibrate import add_delay, lsb_campaign, over_finite, quality
from pipeline.report.report import markdown_table
from schemas.errors import CalibrationError

#: five levels (a cubic through four would have no residual to judge it by), from below the
#: delay capture's light (~0.02 STARTs per pixel per cycle) to ~0.45 (100..3500 lux of the
#: older lux conversion, 1.3395 times brighter per lux: the same light, docs/decisions.md)
DEFAULT_LUX = [133.950, 401.849, 1071.599, 2411.097, 4688.244]
#: the LSB-against-light fit needs density tests at this many levels at least
MIN_LEVELS = 4
#: published calibrations kept under versions/ (the current one always)
KEEP_VERSIONS = 5
#: a campaign that runs longer than this is failed by Prefect (a hung capture, a stuck disk)
CAMPAIGN_TIMEOUT_S = 6 * 3600
#: the numeric tasks' limit (one density fit, one delay)
STEP_TIMEOUT_S = 3600

LuxLevels = Annotated[list[PositiveFloat], Field(min_length=MIN_LEVELS)]


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


def _fit_dir(inputs: dict) -> tuple[str, Path]:
    key = content_key(step="fit", captures=[file_identity(c) for c in inputs["captures"]],
                      inl_rms=inputs["inl_rms"])
    return key, Path(inputs["cache_dir"]) / f"fit-{key}"


def _delay_dir(inputs: dict) -> tuple[str, Path]:
    key = content_key(step="delay", capture=file_identity(inputs["capture"]),
                      fit=Path(inputs["fit_dir"]).name)
    return key, Path(inputs["cache_dir"]) / f"delay-{key}"


@task(cache_policy=Stored(where=_fit_dir), persist_result=True, timeout_seconds=STEP_TIMEOUT_S,
      task_run_name="fit INL and LSB over {inl_rms} LSB")
def fit_lsb(captures: list, inl_rms: float, cache_dir: str) -> dict:
    """Density tests -> INL and LSB polynomial, into a cache entry keyed on the captures
    (path, size, time), ``inl_rms`` and the code version: a rerun resumes from it."""
    log = get_run_logger()
    _, where = _fit_dir({"captures": captures, "inl_rms": inl_rms, "cache_dir": cache_dir})
    with atomic_path(where) as tmp:
        best, fit, n, lsbs = lsb_campaign(captures, tmp / "calibration", inl_rms,
                                          log=log.info)
        (tmp / "fit.json").write_text(json.dumps({
            "n": n.tolist(), "lsb_ps": lsbs.tolist(), "coef": fit.coef.tolist(),
            "residual_ps": fit.residual_ps.tolist(),
            "inl_error_lsb": float(np.nanmedian(best.inl_error_lsb[best.ok]))}))
    return {"dir": str(where), **json.loads((where / "fit.json").read_text())}


@task(cache_policy=Stored(where=_delay_dir), persist_result=True,
      timeout_seconds=STEP_TIMEOUT_S, task_run_name="measure the delay at zero distance")
def measure_delay(capture, fit_dir: str, cache_dir: str) -> dict:
    """Zero-distance capture -> delay per TDC (eq. 5.3), added to a copy of the fit (a
    cache entry, like the fit's); and why there is none ("" when some TDC got one). A
    candidate without a delay is not failed here: the verdict refuses it against a current
    calibration that has one."""
    _, where = _delay_dir({"capture": capture, "fit_dir": fit_dir, "cache_dir": cache_dir})
    with atomic_path(where) as tmp:
        shutil.copytree(Path(fit_dir) / "calibration", tmp / "calibration")
        try:
            delay_ns, why = (add_delay(capture, tmp / "calibration").delay_s * 1e9).tolist(), ""
        except CalibrationError as exc:
            get_run_logger().warning("no delay: %s", exc)
            n = load_calibration(tmp / "calibration").n_tdc
            delay_ns, why = [float("nan")] * n, str(exc)
        (tmp / "delay.json").write_text(json.dumps({"delay_ns": delay_ns, "no_delay": why}))
    return {"dir": str(where), **json.loads((where / "delay.json").read_text())}


@task(cache_policy=NO_CACHE)
def verdict(candidate: str, current: str) -> list[str]:
    """Why the candidate is worse than the current calibration (empty: publish it). There
    being none is the only case for publishing unexamined; a ``current`` that cannot be
    read (no meta.json, a dangling link) is a reason to refuse, for a person to look at."""
    cur = Path(current)
    if not cur.exists() and not cur.is_symlink():
        return []
    try:
        if not (cur / "meta.json").is_file():
            raise CalibrationError(f"{cur}: no meta.json")
        theirs = quality(cur)
    except (CalibrationError, OSError, ValueError) as exc:  # (pyarrow's: ValueError)
        return [f"the current calibration cannot be read ({exc}); not replaced "
                "automatically (force=true publishes after a look)"]
    return quality(candidate).worse_than(theirs)


def version_time(p: Path) -> str:
    """When a version was made, by its own record, as a sortable UTC stamp: the run's stamp in
    its name (``20261204T205400Z-…``, ``before-…`` too), else meta.json's ``created``. Not
    the mtime: ``copytree`` copies that from the cache, so a new version can look old."""
    if m := re.search(r"(\d{8}T\d{6}Z)", p.name):
        return m.group(1)
    try:
        created = json.loads((p / "meta.json").read_text())["created"]
        return dt.datetime.fromisoformat(created).astimezone(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    except (OSError, ValueError, KeyError, TypeError):
        return ""  # no time of its own: the oldest


@task(retries=2, retry_delay_seconds=1, cache_policy=NO_CACHE)
def publish(candidate: str, out: str, version: str) -> str:
    """Copy the candidate to ``versions/<version>`` and point ``current`` at it in one
    rename (I/O only, so it may retry); keep the last KEEP_VERSIONS versions."""
    versions = Path(out) / "versions"
    target = versions / version
    with atomic_path(target) as tmp:
        shutil.copytree(candidate, tmp)
    current = Path(out) / "current"
    old = point_link(current, target)
    if old is not None:  # an older layout's directory: kept as a version
        old.rename(versions / f"before-{version}")
    live = current.resolve()
    for p in sorted(versions.iterdir(), key=version_time)[:-KEEP_VERSIONS]:
        if p.resolve() != live and not p.name.startswith("."):
            shutil.rmtree(p, ignore_errors=True)
    return str(current)


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


def figures_of(caldir: str | Path) -> dict:
    """A calibration's quality figures, for the verdict's table: TDCs calibrated, INL and
    DNL RMS over the codes (median and worst TDC), the INL's statistical error, the LSB
    fit's residual, the delay and its spread across TDCs."""
    calib = load_calibration(caldir)
    q = quality(caldir)
    ok = calib.ok

    def rms(grid):
        g = np.asarray(grid, np.float64)[ok]
        return np.sqrt(np.nanmean(g ** 2, axis=1)) if g.size else np.empty(0)

    inl, dnl = rms(calib.density.inl_lsb), rms(calib.density.dnl_lsb)
    d_ns = calib.delay_s * 1e9
    return {"TDCs calibrated": q.tdcs_ok, "TDCs flagged": int(calib.n_tdc - ok.sum()),
            "INL RMS, median TDC (LSB)": over_finite(np.median, inl),
            "INL RMS, worst TDC (LSB)": over_finite(np.max, inl),
            "DNL RMS, median TDC (LSB)": over_finite(np.median, dnl),
            "DNL RMS, worst TDC (LSB)": over_finite(np.max, dnl),
            "INL statistical error (LSB RMS)": q.inl_error_lsb,
            "LSB fit residual (ps RMS)": q.lsb_residual_ps,
            "TDCs with a delay": int(np.isfinite(d_ns).sum()),
            "delay median (ns)": over_finite(np.median, d_ns),
            "delay spread max-min (ns)": over_finite(np.ptp, d_ns),
            "delay spread std (ns)": over_finite(np.std, d_ns)}


def flagged_tdcs(caldir: str | Path) -> list[dict]:
    """The TDCs the candidate flags, each with why (density test, delay)."""
    calib = load_calibration(caldir)
    dens = calib.reasons or ("",) * calib.n_tdc
    rows = []
    for i in range(calib.n_tdc):
        why_d = dens[i] or ("" if calib.ok[i] else "flagged by the density test")
        why_t = calib.delay_reasons[i] if not np.isfinite(calib.delay_s[i]) else ""
        if why_d or why_t:
            rows.append({"tdc": i, "density test": why_d or "ok", "delay": why_t or "ok"})
    return rows


def _num(v):
    return None if isinstance(v, float) and not np.isfinite(v) else v


def comparison(candidate: str, current: str) -> list[dict]:
    """The candidate's figures beside the calibration it would replace (None where there
    is none, or it cannot be read)."""
    mine = figures_of(candidate)
    try:
        theirs = figures_of(current)
    except (CalibrationError, OSError, ValueError):  # none, or unreadable: the verdict says
        theirs = {}
    return [{"figure": k, "candidate": _num(v), "current": _num(theirs.get(k))}
            for k, v in mine.items()]


def publish_artifacts(out: str, outcome: str, verdict_text: str, report_md: str,
                      compare: list[dict], flagged: list[dict]) -> None:
    """The verdict, the figures against the current calibration and the flagged TDCs, where
    the Prefect UI shows them (artifacts keyed on the calibration, so each night's is a new
    version of the same three)."""
    from prefect.artifacts import create_markdown_artifact, create_table_artifact

    key = _slug(out)
    create_markdown_artifact(report_md, key=f"{key}-report",
                             description=f"{outcome}: {verdict_text}"[:500])
    create_table_artifact(compare, key=f"{key}-figures",
                          description=f"{outcome}: candidate against the current calibration")
    create_table_artifact(flagged or [{"tdc": None, "density test": "none flagged",
                                       "delay": ""}],
                          key=f"{key}-flagged", description="TDCs flagged, with why")


def _slug(out: str) -> str:
    """An artifact key and event resource id for a calibration directory (lowercase
    letters, digits, dashes): its last three path parts to read, and 8 hex digits of the
    whole resolved path, so ``benchA/data/calibration`` and ``benchB/data/calibration``
    (or two long paths alike at their end) never share one."""
    import hashlib

    where = str(Path(out).resolve())
    name = re.sub(r"[^a-z0-9]+", "-", "-".join(Path(where).parts[-3:]).lower()).strip("-")
    return f"calibration-{name[:38].strip('-')}-{hashlib.sha256(where.encode()).hexdigest()[:8]}"


def _announce(outcome: str, out: str, summary: dict) -> None:
    """``tcspc.calibration.published`` / ``.refused``: what automations trigger on."""
    from prefect.events import emit_event

    emit_event(event=f"tcspc.calibration.{outcome.lower()}",
               resource={"prefect.resource.id": f"tcspc.calibration.{_slug(out)}",
                         "prefect.resource.name": str(Path(out).resolve())},
               payload={"refused_because": summary["refused_because"],
                        "forced": summary["forced"], "run": summary["run"],
                        "quality": summary["quality"]})


@flow(name="calibration_campaign", timeout_seconds=CAMPAIGN_TIMEOUT_S,
      flow_run_name=run_namer("campaign", {"journal": "on journal",
                                           "captures": "on captures"}))
def calibration_campaign(out: str = "data/calibration", lux: LuxLevels | None = None,
                         cycles: PositiveInt = 400_000, delay_cycles: PositiveInt = 200_000,
                         n_pixels: PositiveInt = 128, chip_seed: NonNegativeInt = 1,
                         seed: NonNegativeInt = 0, inl_rms: PositiveFloat = 0.5,
                         captures: str | None = None, journal: str | None = None,
                         density_runs: list[str] | None = None, delay_run: str | None = None,
                         force: bool = False, cache_max_gb: PositiveFloat = 20.0,
                         cache_max_age_days: PositiveFloat = 30.0,
                         wait_s: NonNegativeFloat = 3600.0) -> dict:
    """Calibrate the chip: density tests at ``lux`` levels, the zero-distance delay, then
    publish to ``out/current`` unless the candidate is worse than what is there (``force``
    publishes anyway). Runs on the simulator unless ``captures`` names a directory of
    density captures and one delay capture, or ``journal`` a running daemon's journal
    (``STATE/journal``) with the runs it recorded under uniform light (``density_runs``)
    and at zero distance (``delay_run``). One campaign at a time per ``out``: another waits
    up to ``wait_s``. The cache keeps ``cache_max_gb`` at most, entries unused for
    ``cache_max_age_days`` dropped."""
    log = get_run_logger()
    check_roots(out=out, captures=captures, journal=journal)  # (a served run: its roots)
    cache = Path(out) / "cache"
    with exclusive(out, wait_s, log) as dead:
        for rec in dead:
            how = "waiting for" if rec.get("waiting") else "holding"
            if mark_crashed(rec["id"], f"its process (pid {rec.get('pid')} on "
                            f"{rec.get('host')}) died {how} {out}"):
                log.warning("run %s died without ending; marked Crashed", rec.get("name"))
        clean_leftovers(out, cache, Path(out) / "versions", log=log)
        summary, used = _campaign(out, str(cache), lux, cycles, delay_cycles, n_pixels,
                                  chip_seed, seed, inl_rms, captures, journal, density_runs,
                                  delay_run, force, log)
        prune_cache(cache, cache_max_gb, cache_max_age_days, keep=used, log=log)
    outcome = "Published" if summary["published"] else "Refused"
    _announce(outcome, out, summary)
    return Completed(name=outcome, message=summary["verdict"], data=summary)


def _campaign(out, cache, lux, cycles, delay_cycles, n_pixels, chip_seed, seed, inl_rms,
              captures, journal, density_runs, delay_run, force, log) -> tuple[dict, set]:
    run = new_run_dir(out, "calibration_campaign")
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
        jobs = [(scene_dict("density", lux=lv, n_pixels=n_pixels), cycles, cache, seed + i,
                 chip_seed) for i, lv in enumerate(lux)]
        jobs.append((scene_dict("delay", n_pixels=n_pixels), delay_cycles, cache,
                     seed + len(lux), chip_seed))
        *density_caps, delay_cap = map(Path, simulated([simulate.submit(*a) for a in jobs],
                                                        jobs))
        source = (f"simulator: chip seed {chip_seed}, {n_pixels} pixels, {cycles:,} cycles at "
                  f"{lux} lux, delay {delay_cycles:,} cycles")
    fit_args = ([c if hasattr(c, "paths") else str(c) for c in density_caps], inl_rms, cache)
    fit = fit_lsb(*fit_args)
    fit = remade_if_gone(fit, fit["dir"], fit_lsb, *fit_args)
    delay_args = (delay_cap if hasattr(delay_cap, "paths") else str(delay_cap), fit["dir"],
                  cache)
    delay = measure_delay(*delay_args)
    delay = remade_if_gone(delay, delay["dir"], measure_delay, *delay_args)
    used = {Path(fit["dir"]).name, Path(delay["dir"]).name} | {
        Path(c).parent.name for c in (*density_caps, delay_cap) if not hasattr(c, "paths")
        and Path(c).parent.parent == Path(cache)}
    for name in used:
        touch(Path(cache) / name)
    delay_ns, no_delay = delay["delay_ns"], delay["no_delay"]
    candidate = str(run / "calibration")
    shutil.copytree(Path(delay["dir"]) / "calibration", candidate)
    info = flow_run_info()
    meta_path = Path(candidate) / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta["flow_run"] = info  # which run made it (the Prefect UI's link)
    meta_path.write_text(json.dumps(meta, indent=1))
    delay_text = (f"delay {np.nanmin(delay_ns):.4f}..{np.nanmax(delay_ns):.4f} ns"
                  if not no_delay else f"no delay ({no_delay})")
    pngs = plots(candidate, fit, str(run))
    current = str(Path(out) / "current")
    compare = comparison(candidate, current)
    worse = verdict(candidate, current)
    published = force or not worse
    if published:
        publish(candidate, out, run.name)
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
    flagged = flagged_tdcs(candidate)
    verdict_text = ("Published to `current`." if published and not worse else
                    "Published to `current` (forced) although: " + "; ".join(worse)
                    if published else "**Not published**: " + "; ".join(worse)
                    + ". The current calibration stays in place.")
    summary = {"run": str(run), "flow_run": info, "candidate": candidate, "current": current,
               "published": published, "forced": bool(published and worse),
               "refused_because": [] if published else worse, "overruled": worse if published
               else [], "verdict": verdict_text.replace("*", ""), "quality": q.__dict__,
               "figures": {r["figure"]: r["candidate"] for r in compare},
               "flagged_tdcs": flagged,
               "delay_ns": [float(np.nanmin(delay_ns)), float(np.nanmax(delay_ns))]
               if not no_delay else None, "no_delay": no_delay,
               "plots": pngs, "truth": truth,
               "captures": {"density": [_label(c) for c in density_caps],
                            "delay": _label(delay_cap)}}
    sections = [
        ("Source", source),
        ("Verdict", verdict_text),
        ("Against the current calibration", markdown_table(pl.DataFrame(
            compare, schema={"figure": pl.String, "candidate": pl.Float64,
                             "current": pl.Float64}))),
        ("Flagged TDCs", markdown_table(pl.DataFrame(flagged)) if flagged else "None."),
        ("Density tests", markdown_table(tests.drop("capture"))),
        ("Quality", f"TDCs calibrated: {q.tdcs_ok}; median INL statistical error "
                    f"{q.inl_error_lsb:.3f} LSB RMS; LSB fit residual {q.lsb_residual_ps:.3f} "
                    f"ps RMS; {delay_text}."),
        ("Against the truth", truth_text),
        ("Plots", "\n".join(f"![{Path(p).stem}]({Path(p).name})" for p in pngs)),
        ("Flow run", f"{info['name']} ({info['id']})"),
    ]
    rep = report(str(run / "report.md"), "Calibration campaign", sections)
    summary["report"] = rep
    (run / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    publish_artifacts(out, "Published" if published else "Refused", summary["verdict"],
                      Path(rep).read_text(), compare, flagged)
    return summary, used
