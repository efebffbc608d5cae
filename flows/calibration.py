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
place, whole. The run ends Completed (type and name: Prefect's own automations key on
``prefect.flow-run.Completed``) whether it publishes or refuses; the verdict is in its
result (``outcome``, ``rule``, ``why``, ``refused_because``), a tag on the run
(``tcspc:published`` / ``tcspc:refused``) and the event ``tcspc.calibration.published`` or
``tcspc.calibration.refused`` for automations (:mod:`flows.automations` creates a lab's).
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
    show_waiting,
    simulate,
    simulated,
    tag_run,
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


#: The reset period assumed when a scene's light is predicted for the plan (the simulated
#: chip's; it only orders and scales the levels the plan weighs).
PLAN_RESET_S = 20e-9


def scene_light(scene: dict) -> float:
    """A density scene's light, detections per pixel per cycle (eq. 5.1's n), as its model
    predicts it: ``1 - exp(-rate (reset + T))``, ``rate`` the median pixel's ambient and
    dark detections a second."""
    from stages.models.scene import evaluate, scene_from_dict

    model = evaluate(scene_from_dict(scene, scene.get("name", "scene")), cycles=1)
    rate = float(np.median(model.bg_rate_hz))
    return float(-np.expm1(-rate * (PLAN_RESET_S + model.window_s)))


@task(cache_policy=NO_CACHE, timeout_seconds=STEP_TIMEOUT_S,
      task_run_name="plan the density tests from the zero capture")
def plan_density(zero, budget: int, lux: list[float], n_pixels: int) -> dict:
    """The density tests' cycles at the ``lux`` levels, planned from the zero-distance
    capture ``zero`` within ``budget`` cycles (:func:`stages.calibration.plan_tests`, as
    `tcspc calibrate plan`; its levels the lights the scenes' model predicts at ``lux``).
    A test the plan adds at the zero's own light goes to the level nearest it in light."""
    from pipeline.offline.calibrate import density_histograms
    from stages import calibration as cal

    cap = _open(zero)
    state, _ = density_histograms(cap)
    lights = [scene_light(scene_dict("density", lux=lv, n_pixels=n_pixels)) for lv in lux]
    p = cal.plan_tests(state.hits, state.cycles, budget, cap.meta.window_ns * 1e-9,
                       levels=lights)
    cycles = np.zeros(len(lux))
    for n, c in zip(p.lights, p.cycles, strict=True):
        cycles[int(np.argmin(np.abs(np.log(lights) - np.log(max(n, 1e-9)))))] += c
    e = p.delay_error_ps
    why = ""
    if not np.isfinite(e).any():  # no return on uniform light: nothing to plan for
        why = ("no return found above uniform light in the zero capture (give it ambient "
               "light: delay_lux): the budget split evenly")
        get_run_logger().warning("plan: %s", why)
        cycles = np.full(len(lux), budget // len(lux))
    return {"budget": int(budget), "lux": list(lux), "lights": [round(v, 6) for v in lights],
            "cycles": [max(int(c), 1) for c in cycles], "zero_light": round(p.zero_light, 6),
            "expected_delay_error_ps": (round(float(np.nanmedian(e)), 1)
                                        if np.isfinite(e).any() else None),
            "not_planned": why}


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


#: the current calibration is replaced by a worse candidate past this age (hours) ...
MAX_AGE_H = 7 * 24.0
#: ... or when the chip's LSB has drifted this far from it (median TDC, ps) ...
MAX_LSB_DRIFT_PS = 0.5
#: ... or its delay this far (median TDC, ps: ~1.5 cm of range)
MAX_DELAY_DRIFT_PS = 100.0
#: a worse candidate that replaces an old or drifted one must calibrate this share of the
#: TDCs the current one does (and reach the campaign's inl_rms, and have a delay where the
#: current one has)
MIN_TDC_SHARE = 0.9


def calibration_age_h(caldir: str | Path, now: dt.datetime | None = None) -> float | None:
    """Hours since a calibration was made: meta.json's ``created`` (when its fit was
    computed, from captures no younger), else its version's stamp; None when it records
    no time."""
    real = Path(caldir).resolve()
    try:
        made = dt.datetime.fromisoformat(json.loads((real / "meta.json").read_text())["created"])
        made = made if made.tzinfo else made.replace(tzinfo=dt.UTC)
    except (OSError, ValueError, KeyError, TypeError):
        stamp = version_time(real)
        if not stamp:
            return None
        made = dt.datetime.strptime(stamp, "%Y%m%dT%H%M%SZ").replace(tzinfo=dt.UTC)
    return ((now or dt.datetime.now(dt.UTC)) - made).total_seconds() / 3600


def drift_ps(candidate: str | Path, current: str | Path) -> dict:
    """How far the chip moved from the current calibration, by this campaign's own
    measurements: the LSB the density tests measured at their light levels against what
    the current calibration gives at those levels, and the delay measured now against
    its delay; each the size of the median over the TDCs both calibrate of the per-TDC
    difference (ps; NaN where either lacks it): a shift of the chip, which temperature
    and supply move as a whole, not one TDC's scatter (a delay is measured per TDC to a
    fraction of an LSB: two fits of one capture differ by ~150 ps per TDC)."""
    new, cur = load_calibration(candidate), load_calibration(current)
    both = new.ok & cur.ok
    lsb = float("nan")
    if new.lsb_fit is not None and cur.lsb_fit is not None and new.lsb_fit.levels is not None \
            and both.any():
        now = new.lsb_fit.points_ps()  # (TDC, level)
        then = np.column_stack([cur.lsb_fit.lsb_ps(float(n)) for n in new.lsb_fit.levels])
        lsb = abs(over_finite(np.median, np.nanmedian(now - then, axis=1)[both]))
    delay = abs(over_finite(np.median, (new.delay_s - cur.delay_s)[both] * 1e12))
    return {"lsb": lsb, "delay": delay}


#: The stream's LSB tracking counts as drift only when beyond the limit by this many of its
#: standard errors (a median over ~100 TDCs of estimates each good to <= 10 ps).
STREAM_DRIFT_SIGMAS = 3.0
#: ... read from the newest this many ranges files ranged with the current calibration.
STREAM_DRIFT_FILES = 20


def stream_drift_ps(current: str | Path, stream_out: str | Path | None,
                    last: int = STREAM_DRIFT_FILES) -> dict | None:
    """The LSB drift the daemon's range stage measured against the current calibration
    (its online tracking, ``tcspc.lsb_drift`` in each ranges file's metadata, issue 39.3):
    the inverse-variance mean of the newest ``last`` files ranged with this calibration
    (``tcspc.calibration_id``), its standard error and how many files; None where the
    stream has none (no ``stream_out``, no ranges with this calibration, or a measurement
    too dim to track)."""
    import pyarrow.parquet as pq

    if stream_out is None or not (Path(stream_out) / "ranges").is_dir():
        return None
    try:
        cal_id = load_calibration(current).meta.get("calibration_id")
    except (CalibrationError, OSError, ValueError):
        return None
    if not cal_id:
        return None
    files = sorted((Path(stream_out) / "ranges").rglob("*.parquet"),
                   key=lambda p: p.stat().st_mtime, reverse=True)
    vals = []
    for f in files:
        try:
            meta = pq.read_schema(f).metadata or {}
        except (OSError, ValueError):
            continue
        if meta.get(b"tcspc.calibration_id", b"").decode() != cal_id \
                or b"tcspc.lsb_drift" not in meta:
            continue
        rec = json.loads(meta[b"tcspc.lsb_drift"])
        if np.isfinite(rec.get("se_ps", np.inf)) and rec["se_ps"] > 0:
            vals.append((rec["median_ps"], rec["se_ps"]))
        if len(vals) >= last:
            break
    if not vals:
        return None
    m, se = np.array(vals).T
    w = 1 / se ** 2
    return {"lsb": float(np.sum(w * m) / np.sum(w)), "se": float(1 / np.sqrt(np.sum(w))),
            "files": len(vals)}


def within_limits(candidate: str | Path, current: str | Path, inl_rms: float) -> list[str]:
    """Why the candidate is not good enough to replace anything on its own (empty: it
    is): fewer than MIN_TDC_SHARE of the current calibration's TDCs, an INL error over
    ``inl_rms``, no delay where the current one has one."""
    mine, theirs = quality(candidate), quality(current)
    why = []
    if mine.tdcs_ok < MIN_TDC_SHARE * theirs.tdcs_ok:
        why.append(f"calibrates {mine.tdcs_ok} TDCs, under {MIN_TDC_SHARE:.0%} of the "
                   f"current one's {theirs.tdcs_ok}")
    if not mine.inl_error_lsb <= inl_rms:
        why.append(f"INL error {mine.inl_error_lsb:.3f} LSB RMS over the limit {inl_rms}")
    if theirs.has_delay and not mine.has_delay:
        why.append("has no delay measurement, the current one has")
    return why


@task(cache_policy=NO_CACHE)
def verdict(candidate: str, current: str, inl_rms: float = 0.5, max_age_h: float = MAX_AGE_H,
            max_lsb_drift_ps: float = MAX_LSB_DRIFT_PS,
            max_delay_drift_ps: float = MAX_DELAY_DRIFT_PS,
            now: dt.datetime | None = None, stream_out: str | None = None) -> dict:
    """Publish the candidate or not, and by which rule (``rule``; ``why`` in words):

    - ``first``: there is no current calibration;
    - ``unreadable``: the current one cannot be read (no meta.json, a dangling link):
      refused, for a person to look at;
    - ``quality``: the candidate is not worse than the current one: published;
    - ``age`` / ``drift``: it is worse, but the current one is older than ``max_age_h``
      or the chip drifted from it (LSB past ``max_lsb_drift_ps``, delay past
      ``max_delay_drift_ps``, as this campaign measured them; or the LSB past its limit
      by ``STREAM_DRIFT_SIGMAS`` standard errors as the daemon's range stage tracked it,
      :func:`stream_drift_ps` of ``stream_out``), and the candidate is within the
      absolute limits (:func:`within_limits`): published;
    - ``quality`` again: worse, and the current one still young and in place: refused.

    ``worse`` lists how the candidate is worse (what a refusal gives as its reasons)."""
    cur = Path(current)
    out = {"publish": True, "rule": "first", "worse": [], "age_h": None,
           "drift_ps": {"lsb": None, "delay": None}, "stream_drift_ps": None,
           "why": "no current calibration: the first is published"}
    if not cur.exists() and not cur.is_symlink():
        return out
    try:
        if not (cur / "meta.json").is_file():
            raise CalibrationError(f"{cur}: no meta.json")
        theirs = quality(cur)
    except (CalibrationError, OSError, ValueError) as exc:  # (pyarrow's: ValueError)
        why = (f"the current calibration cannot be read ({exc}); not replaced "
               "automatically (force=true publishes after a look)")
        return {**out, "publish": False, "rule": "unreadable", "worse": [why], "why": why}
    worse = quality(candidate).worse_than(theirs)
    age = calibration_age_h(cur, now)
    drift = drift_ps(candidate, cur)
    out.update(worse=worse, age_h=age, drift_ps={k: _num(v) for k, v in drift.items()})
    aged = f"{age:.1f} h old" if age is not None else "of unknown age"
    stream = stream_drift_ps(cur, stream_out)
    out["stream_drift_ps"] = stream
    moved = (f"LSB drift {drift['lsb']:.3f} ps (limit {max_lsb_drift_ps:g}), delay drift "
             f"{drift['delay']:.1f} ps (limit {max_delay_drift_ps:g})")
    if stream is not None:
        moved += (f"; the stream's LSB tracking {stream['lsb']:+.3f} +- {stream['se']:.3f} ps"
                  f" over its last {stream['files']} measurements")
    elif stream_out is not None:
        moved += "; no LSB tracking in the stream's ranges with this calibration"
    stream_moved = stream is not None and abs(stream["lsb"]) > max(
        max_lsb_drift_ps, STREAM_DRIFT_SIGMAS * stream["se"])
    if not worse:
        return {**out, "rule": "quality", "why": f"not worse than the current calibration "
                f"({aged}; {moved})"}
    old = age is not None and age > max_age_h
    drifted = (drift["lsb"] > max_lsb_drift_ps or drift["delay"] > max_delay_drift_ps
               or stream_moved)  # NaN: no
    if old or drifted:
        short = within_limits(candidate, cur, inl_rms)
        rule = "drift" if drifted else "age"
        reason = (f"the chip drifted from the current calibration ({moved})" if drifted else
                  f"the current calibration is {aged} (limit {max_age_h:g} h)")
        if not short:
            return {**out, "rule": rule, "why": f"{reason}: replaced although the candidate "
                    f"is worse ({'; '.join(worse)}), being within the absolute limits"}
        return {**out, "publish": False, "rule": rule,
                "worse": worse + [w for w in short if w not in worse],
                "why": f"{reason}, but the candidate is not within the absolute limits "
                       f"({'; '.join(short)})"}
    return {**out, "publish": False, "rule": "quality",
            "why": f"worse than the current calibration ({'; '.join(worse)}), which is "
                   f"{aged} (limit {max_age_h:g} h) and in place ({moved})"}


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

    emit_event(event=f"tcspc.calibration.{outcome}",
               resource={"prefect.resource.id": f"tcspc.calibration.{_slug(out)}",
                         "prefect.resource.name": str(Path(out).resolve())},
               related=[{"prefect.resource.id": f"prefect.tag.tcspc:{outcome}",
                         "prefect.resource.role": "tag"}],
               payload={"outcome": outcome, "rule": summary["rule"], "why": summary["why"],
                        "refused_because": summary["refused_because"],
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
                         wait_s: NonNegativeFloat = 3600.0,
                         max_age_h: PositiveFloat = MAX_AGE_H,
                         max_lsb_drift_ps: PositiveFloat = MAX_LSB_DRIFT_PS,
                         max_delay_drift_ps: PositiveFloat = MAX_DELAY_DRIFT_PS,
                         stream_out: str | None = None,
                         plan_budget: PositiveInt | None = None,
                         delay_lux: NonNegativeFloat = 400.0) -> dict:
    """Calibrate the chip: density tests at ``lux`` levels, the zero-distance delay, then
    publish to ``out/current`` unless the candidate is worse than what is there (``force``
    publishes anyway). Runs on the simulator unless ``captures`` names a directory of
    density captures and one delay capture, or ``journal`` a running daemon's journal
    (``STATE/journal``) with the runs it recorded under uniform light (``density_runs``)
    and at zero distance (``delay_run``). One campaign at a time per ``out``: another waits
    up to ``wait_s`` (its state named AwaitingLock meanwhile). A worse candidate replaces
    a current calibration older than ``max_age_h`` or one the chip drifted from (LSB past
    ``max_lsb_drift_ps``, delay past ``max_delay_drift_ps``; by this campaign's
    measurements, or the LSB by the online tracking of the daemon whose output is
    ``stream_out``) when it is within the absolute limits (:func:`verdict`). The run ends
    Completed either way; the verdict is
    in its result (``outcome``, ``rule``, ``refused_because``), its tag
    (``tcspc:published`` / ``tcspc:refused``) and the ``tcspc.calibration.*`` event. The
    cache keeps ``cache_max_gb`` at most, entries unused for ``cache_max_age_days``
    dropped. With ``plan_budget`` (the simulator's campaign) the zero-distance capture is
    taken first and the density tests' cycles at the ``lux`` levels are planned from it
    within that budget (:func:`plan_density`, as `tcspc calibrate plan`; ``cycles`` is then
    not used); the plan is in the result and the report. The zero capture then has
    ``delay_lux`` of ambient light (the plan reads its window's end and its return against
    uniform light; `calibrate delay` counts that light as a fifth density test)."""
    log = get_run_logger()
    check_roots(out=out, captures=captures, journal=journal)  # (a served run: its roots)
    cache = Path(out) / "cache"
    with exclusive(out, wait_s, log, on_wait=show_waiting) as dead:
        for rec in dead:
            how = "waiting for" if rec.get("waiting") else "holding"
            if mark_crashed(rec["id"], f"its process (pid {rec.get('pid')} on "
                            f"{rec.get('host')}) died {how} {out}"):
                log.warning("run %s died without ending; marked Crashed", rec.get("name"))
        clean_leftovers(out, cache, Path(out) / "versions", log=log)
        summary, used = _campaign(out, str(cache), lux, cycles, delay_cycles, n_pixels,
                                  chip_seed, seed, inl_rms, captures, journal, density_runs,
                                  delay_run, force, log, plan_budget, delay_lux,
                                  limits=dict(inl_rms=inl_rms, max_age_h=max_age_h,
                                              max_lsb_drift_ps=max_lsb_drift_ps,
                                              max_delay_drift_ps=max_delay_drift_ps,
                                              stream_out=stream_out))
        prune_cache(cache, cache_max_gb, cache_max_age_days, keep=used, log=log)
    # Completed by type and name (Prefect's own automations key on prefect.flow-run.Completed);
    # the verdict in the result, a tag and the event
    tag_run(f"tcspc:{summary['outcome']}")
    _announce(summary["outcome"], out, summary)
    return Completed(message=summary["verdict"], data=summary)


def _campaign(out, cache, lux, cycles, delay_cycles, n_pixels, chip_seed, seed, inl_rms,
              captures, journal, density_runs, delay_run, force, log, plan_budget,
              delay_lux, limits: dict) -> tuple[dict, set]:
    run = new_run_dir(out, "calibration_campaign")
    plan = None
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
        zero_scene = scene_dict("delay", n_pixels=n_pixels)
        if plan_budget and delay_lux > 0:
            zero_scene = {**zero_scene, "ambient": [{"kind": "lux", "lux": float(delay_lux)}]}
        zero_job = (zero_scene, delay_cycles, cache, seed + len(lux), chip_seed)
        level_cycles = [cycles] * len(lux)
        if plan_budget:  # the zero capture first, the density tests planned from it
            delay_cap = Path(simulated([simulate.submit(*zero_job)], [zero_job])[0])
            plan = plan_density(str(delay_cap), plan_budget, list(lux), n_pixels)
            level_cycles = plan["cycles"]
            log.info("density tests planned from the zero capture: %s cycles at %s lux "
                     "(expected delay error %s ps)", level_cycles, list(lux),
                     plan["expected_delay_error_ps"])
        jobs = [(scene_dict("density", lux=lv, n_pixels=n_pixels), c, cache, seed + i,
                 chip_seed) for i, (lv, c) in enumerate(zip(lux, level_cycles, strict=True))]
        if plan_budget:
            density_caps = list(map(Path, simulated([simulate.submit(*a) for a in jobs],
                                                    jobs)))
        else:
            jobs.append(zero_job)
            *density_caps, delay_cap = map(Path, simulated(
                [simulate.submit(*a) for a in jobs], jobs))
        source = (f"simulator: chip seed {chip_seed}, {n_pixels} pixels, "
                  + (f"{cycles:,} cycles" if plan is None else
                     f"{level_cycles} cycles planned from the zero capture within "
                     f"{plan_budget:,}") + f" at {lux} lux, delay {delay_cycles:,} cycles"
                  + (f" at {delay_lux:g} lux" if plan is not None and delay_lux > 0 else ""))
    if plan is not None:
        (run / "plan.json").write_text(json.dumps(plan, indent=1))
    used = {Path(c).parent.name for c in (*density_caps, delay_cap)
            if not hasattr(c, "paths") and Path(c).parent.parent == Path(cache)}
    current = str(Path(out) / "current")
    fit_args = ([c if hasattr(c, "paths") else str(c) for c in density_caps], inl_rms, cache)
    try:
        fit = fit_lsb(*fit_args)
    except CalibrationError as exc:  # the captures cannot give the quality asked: a refusal
        log.warning("candidate NOT published: %s", exc)
        for name in used:
            touch(Path(cache) / name)
        return _unfit(out, run, source, current, density_caps, delay_cap, str(exc)), used
    fit = remade_if_gone(fit, fit["dir"], fit_lsb, *fit_args)
    delay_args = (delay_cap if hasattr(delay_cap, "paths") else str(delay_cap), fit["dir"],
                  cache)
    delay = measure_delay(*delay_args)
    delay = remade_if_gone(delay, delay["dir"], measure_delay, *delay_args)
    used |= {Path(fit["dir"]).name, Path(delay["dir"]).name}
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
    compare = comparison(candidate, current)
    v = verdict(candidate, current, **limits)
    worse = v["worse"]
    published = force or v["publish"]
    if published:
        publish(candidate, out, run.name)
        log.info("published %s (%s: %s)", current, "forced" if not v["publish"] else
                 v["rule"], v["why"])
    else:
        log.warning("candidate NOT published (%s): %s", v["rule"], v["why"])
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
    forced = published and not v["publish"]
    verdict_text = ("Published to `current` (forced) although: " + "; ".join(worse)
                    if forced else f"Published to `current` (rule {v['rule']}): {v['why']}."
                    if published else f"**Not published** (rule {v['rule']}): {v['why']}. "
                    "The current calibration stays in place.")
    summary = {"run": str(run), "flow_run": info, "candidate": candidate, "current": current,
               "published": published, "outcome": "published" if published else "refused",
               "rule": "forced" if forced else v["rule"], "why": v["why"],
               "age_h": v["age_h"], "drift_ps": v["drift_ps"],
               "stream_drift_ps": v["stream_drift_ps"], "forced": bool(forced),
               "refused_because": [] if published else worse, "overruled": worse if published
               else [], "verdict": verdict_text.replace("*", ""), "quality": q.__dict__,
               "figures": {r["figure"]: r["candidate"] for r in compare},
               "flagged_tdcs": flagged,
               "delay_ns": [float(np.nanmin(delay_ns)), float(np.nanmax(delay_ns))]
               if not no_delay else None, "no_delay": no_delay,
               "plots": pngs, "truth": truth,
               "captures": {"density": [_label(c) for c in density_caps],
                            "delay": _label(delay_cap)}, "plan": plan}
    sections = [
        ("Source", source),
        ("Verdict", verdict_text),
        ("Against the current calibration", _compare_md(compare)),
        ("Flagged TDCs", markdown_table(pl.DataFrame(flagged)) if flagged else "None."),
        ("Density tests", markdown_table(tests.drop("capture"))),
        ("Quality", f"TDCs calibrated: {q.tdcs_ok}; median INL statistical error "
                    f"{q.inl_error_lsb:.3f} LSB RMS; LSB fit residual {q.lsb_residual_ps:.3f} "
                    f"ps RMS; {delay_text}."),
        ("Against the truth", truth_text),
        ("Plots", "\n".join(f"![{Path(p).stem}]({Path(p).name})" for p in pngs)),
        ("Flow run", f"{info['name']} ({info['id']})"),
    ]
    _finish(out, run, summary, sections, compare, flagged)
    return summary, used


def _compare_md(compare: list[dict]) -> str:
    return markdown_table(pl.DataFrame(compare, schema={
        "figure": pl.String, "candidate": pl.Float64, "current": pl.Float64}))


def _finish(out: str, run: Path, summary: dict, sections: list, compare: list[dict],
            flagged: list[dict]) -> None:
    """The run's report.md and summary.json, and the same where the Prefect UI shows them."""
    rep = report(str(run / "report.md"), "Calibration campaign", sections)
    summary["report"] = rep
    (run / "summary.json").write_text(json.dumps(summary, indent=1, default=str))
    publish_artifacts(out, summary["outcome"].capitalize(), summary["verdict"],
                      report_markdown(Path(rep).read_text(), run), compare, flagged)


def _unfit(out: str, run: Path, source: str, current: str, density_caps: list, delay_cap,
           why: str) -> dict:
    """The summary of a campaign whose captures could not give a candidate of the quality
    asked (the INL check): a refusal with its reason, the current calibration's figures,
    the report and artifacts as any refusal has."""
    try:
        theirs = figures_of(current)
    except (CalibrationError, OSError, ValueError):
        theirs = {}
    compare = [{"figure": k, "candidate": None, "current": _num(v)} for k, v in theirs.items()]
    text = (f"**Not published** (rule quality): the captures give no candidate: {why}. The "
            "current calibration stays in place.")
    summary = {"run": str(run), "flow_run": flow_run_info(), "candidate": None,
               "current": current, "published": False, "outcome": "refused",
               "rule": "quality", "why": why, "age_h": None,
               "drift_ps": {"lsb": None, "delay": None}, "stream_drift_ps": None,
               "forced": False,
               "refused_because": [why], "overruled": [], "verdict": text.replace("*", ""),
               "quality": None, "figures": {}, "flagged_tdcs": [], "delay_ns": None,
               "no_delay": "", "plots": [], "truth": {},
               "captures": {"density": [_label(c) for c in density_caps],
                            "delay": _label(delay_cap)}}
    sections = [("Source", source), ("Verdict", text),
                ("The current calibration", _compare_md(compare) if compare else "None."),
                ("Flow run", f"{summary['flow_run']['name']} ({summary['flow_run']['id']})")]
    _finish(out, run, summary, sections, compare, [])
    return summary


def report_markdown(text: str, run: Path) -> str:
    """The report for the Prefect UI: its figures (``![x](x.png)``, files beside report.md
    that the UI cannot reach) embedded as data: URIs, so the artifact shows them."""
    import base64

    def embed(m: re.Match) -> str:
        png = run / m.group(2)
        if not png.is_file() or "/" in m.group(2):
            return m.group(0)
        data = base64.b64encode(png.read_bytes()).decode()
        return f"![{m.group(1)}](data:image/png;base64,{data})"

    return re.sub(r"!\[([^\]]*)\]\(([^)\s]+\.png)\)", embed, text)
