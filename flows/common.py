"""What every flow shares: scenes with overrides, simulated captures cached on their inputs,
run directories, and the report task (the only task that retries: it does I/O only)."""

from __future__ import annotations

import copy
import datetime as dt
import hashlib
import json
import secrets
import tomllib
from functools import cache
from pathlib import Path

from prefect import get_run_logger, task
from prefect.cache_policies import NO_CACHE

from pipeline.io.atomic import atomic_path
from pipeline.io.caldir import software_version
from pipeline.io.capture import Capture
from pipeline.offline.simulate import simulate_capture
from pipeline.report.report import write_report
from stages.models.scene import scene_from_dict

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"


def scene_dict(name_or_path: str, **overrides) -> dict:
    """A scene file (a name under ``scenes/`` or a path) as a dict, with ``overrides``:
    ``n_pixels``, ``lux`` (every ambient source), ``distance_m`` and ``t_laser_win_ns``."""
    path = Path(name_or_path)
    if not path.suffix:
        path = SCENES / f"{name_or_path}.toml"
    raw = tomllib.loads(path.read_text())
    raw.setdefault("name", path.stem)
    raw = copy.deepcopy(raw)
    if overrides.get("n_pixels") is not None:
        n = int(overrides["n_pixels"])
        raw.setdefault("sensor", {})["n_pixels"] = n  # hot pixels beyond n drop out
        for t in raw.get("targets", []):
            t["pixels"] = [min(t["pixels"][0], n - 1), min(t["pixels"][1], n - 1)]
    if overrides.get("lux") is not None:
        for a in raw.get("ambient", []):
            a["lux"] = float(overrides["lux"])
    if overrides.get("distance_m") is not None:
        for t in raw.get("targets", []):
            t["distance_m"] = float(overrides["distance_m"])
    if overrides.get("t_laser_win_ns") is not None:
        raw.setdefault("gate", {})["t_laser_win_ns"] = float(overrides["t_laser_win_ns"])
    scene_from_dict(raw, str(path))  # validate now, naming the file
    return raw


@cache
def _model_source_hash() -> str:
    h = hashlib.sha256()
    for p in sorted((ROOT / "stages").rglob("*.py")):
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def capture_key(scene: dict, cycles: int, seed: int, chip_seed: int) -> str:
    """The cache key of a simulated capture: everything its words depend on, including
    the simulator's source, so a changed model never reuses a stale capture."""
    blob = json.dumps({"scene": scene, "cycles": cycles, "seed": seed, "chip_seed": chip_seed,
                       "software": software_version(), "source": _model_source_hash()},
                      sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:20]


@task(cache_policy=NO_CACHE, task_run_name="simulate {scene[name]} ({cycles} cycles)")
def simulate(scene: dict, cycles: int, cache_dir: str, seed: int = 0,
             chip_seed: int = 1) -> str:
    """A simulated capture of ``scene``; reused when one with the same inputs exists (the
    words depend only on them). Written atomically: a failure leaves no capture behind."""
    key = capture_key(scene, cycles, seed, chip_seed)
    where = Path(cache_dir) / key
    path = where / scene["name"]
    if (where / f"{scene['name']}.json").exists():
        Capture(path, strict=True)
        get_run_logger().info("reusing %s", path)
        return str(path)
    with atomic_path(where) as tmp:
        tmp.mkdir(parents=True)
        simulate_capture(scene_from_dict(scene, scene["name"]), cycles, tmp / scene["name"],
                         seed=seed, chip_seed=chip_seed)
    return str(path)


def new_run_dir(out: str | Path, flow: str) -> Path:
    """``OUT/runs/<UTC time>-<random>``: one directory per run, never reused."""
    stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
    run = Path(out) / "runs" / f"{stamp}-{secrets.token_hex(3)}"
    run.mkdir(parents=True)
    (run / "flow.txt").write_text(f"{flow}\n")
    return run


@task(retries=2, retry_delay_seconds=1, cache_policy=NO_CACHE)
def report(path: str, title: str, sections: list[tuple[str, str]]) -> str:
    """Write a run's Markdown report atomically (I/O only, so it may retry)."""
    return str(write_report(path, title, sections))
