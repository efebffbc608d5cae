"""The run's artifact bounds: the live path classifies as the offline commands do.

With ``[histogram] calibration`` the bounds are the calibration's. Without one, a replayed
capture's bounds are estimated from the capture itself before the graph starts, by the
offline commands' own estimate (:func:`pipeline.offline.datapath.estimate_capture_bounds`,
D2nd over every word of the capture), saved once per run in ``STATE/bounds/RUN.json`` (a
restarted daemon, its workers and the end-of-run reconciliation read the same file): the
daemon's words are classified exactly as ``tcspc histogram`` classifies the capture. A
simulated or UDP stream has no words before it starts: without a calibration the topology
is refused (:mod:`pipeline.stream.topology`), unless it asks for ``[histogram] artifacts =
"count-as-hits"``; then its artifact words are counted as hits, and the daemon says so at
start and in the run's accounting (``artifact_bounds``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from pipeline.io.atomic import atomic_path
from stages.artifact import ArtifactBounds

if TYPE_CHECKING:  # (a worker loads bounds without the topology's pydantic models)
    from pipeline.stream.topology import Topology

COUNTED = 'none: artifact words counted as hits ([histogram] artifacts = "count-as-hits")'


def bounds_file(topo: Topology) -> Path | None:
    """``STATE/bounds/RUN.json`` where the run's bounds are estimated (a capture source
    without a calibration), else None."""
    if topo.histogram.get("calibration") or topo.histogram.get("artifacts") \
            or topo.source.get("kind") != "capture":
        return None
    return topo.state / "bounds" / f"{topo.run}.json"


def save_bounds(path: Path, bounds: ArtifactBounds) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps({"n_min": bounds.n_min.tolist(),
                                   "n_max": bounds.n_max.tolist(), "source": bounds.source,
                                   "uncertain": bounds.uncertain.tolist(),
                                   "reasons": list(bounds.reasons)}))


def load_bounds(path: str | Path, n_tdc: int) -> ArtifactBounds:
    """The bounds saved in ``path``, checked against the stream's TDC count."""
    try:
        d = json.loads(Path(path).read_text())
        b = ArtifactBounds(np.asarray(d["n_min"]), np.asarray(d["n_max"]), d["source"],
                           np.asarray(d["uncertain"], bool), tuple(d["reasons"]))
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"{path}: not the run's artifact bounds ({exc})") from None
    if b.n_tdc != n_tdc:
        raise ValueError(f"{path}: bounds for {b.n_tdc} TDCs; the stream has {n_tdc}")
    return b


def ensure_bounds(topo: Topology, log=print) -> str:
    """Estimate and save the run's bounds where they come from the capture (kept from a
    previous start of the run); returns what the run's words are classified with, for the
    log line at start and the accounting."""
    path = bounds_file(topo)
    if path is None:
        cal = topo.histogram.get("calibration")
        if cal:
            return f"calibration:{Path(cal).resolve()}"
        return COUNTED if topo.histogram.get("artifacts") == "count-as-hits" else "none"
    if not path.exists():
        from pipeline.io.capture import Capture
        from pipeline.offline.datapath import estimate_capture_bounds

        cap = Capture(topo.source["capture"])
        log(f"no calibration: estimating the artifact bounds from {cap.bin_path} "
            f"({cap.n_words:,} words), as `tcspc histogram` does")
        b = estimate_capture_bounds(cap)
        save_bounds(path, ArtifactBounds(b.n_min, b.n_max, f"estimated:{cap.bin_path}",
                                         b.uncertain, b.reasons))
    return load_bounds(path, topo.n_tdc).describe()


def histogram_bounds(topo: Topology) -> ArtifactBounds | None:
    """The bounds the run's words are classified with (None: none, every D2nd valid)."""
    if topo.histogram.get("calibration"):
        from pipeline.io.caldir import read_bounds

        return read_bounds(topo.histogram["calibration"], topo.n_tdc)
    path = bounds_file(topo)
    return load_bounds(path, topo.n_tdc) if path is not None and path.exists() else None
