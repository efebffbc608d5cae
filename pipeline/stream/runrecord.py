"""A run's record, ``STATE/runs/RUN.json``: what a measurement of the run is (the keys that
name its parts), the date partition its parts live in, and how the run ended. Written at
the run's first start and kept: a resume reuses its partition (parts stay in one place
whatever the date) and is refused when the topology changes what a measurement is."""

import json
import os
from pathlib import Path

from pipeline.stream.state import StateError
from pipeline.stream.topology import Topology, tdc_ranges


def identity(topo: Topology) -> dict:
    """The keys that decide what a measurement of the run is and the names of its parts."""
    return {"source.kind": topo.source.get("kind"), "n_tdc": topo.n_tdc,
            "histogram.measurement_cycles": topo.histogram.get("measurement_cycles"),
            "histogram.workers": topo.workers,
            "histogram.tdc_ranges": [list(r) for r in tdc_ranges(topo)],
            "range": topo.range is not None, "sink.out": str(topo.sink.get("out"))}


def _path(topo: Topology) -> Path:
    return topo.state / "runs" / f"{topo.run}.json"


def _write(path: Path, rec: dict) -> None:
    from pipeline.io.atomic import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(rec, indent=1, default=str))
        os.chmod(tmp, 0o600)


def take(topo: Topology) -> dict:
    """The run's record: made at its first start; on a resume, checked against ``topo``
    (StateError naming the key that changed, old -> new) and its date partition reused."""
    path, now = _path(topo), identity(topo)
    try:
        rec = json.loads(path.read_text())
    except FileNotFoundError:
        rec = {"run": topo.run, "date": topo.date, "identity": now, "state": "running"}
        _write(path, rec)
        return rec
    except (OSError, ValueError) as exc:
        raise StateError(f"run {topo.run}: its record {path} is unreadable ({exc})") from exc
    for key, old in rec.get("identity", {}).items():
        if now.get(key) != old:
            raise StateError(f"run {topo.run}: {key} changed {old} -> {now.get(key)} since "
                             f"the run started; a resume keeps what a measurement is (start "
                             f"a new --run, or restore the topology)")
    topo.date = rec["date"]  # the run's parts stay in the partition it started in
    return rec


def end(topo: Topology, result: dict) -> None:
    """Keep how the run ended (a finished run's result is not recomputed on a restart)."""
    rec = json.loads(_path(topo).read_text())
    rec.update(state=result.get("state"), result=result)
    _write(_path(topo), rec)
