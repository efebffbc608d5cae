"""Imported by the stages' fork server (pipeline.stream.forkstart) when the graph has a
range stage: the ranging kernels load from numba's cache here, once (~0.25 CPU-s, and the
calibration's own warm-up), so the forked range stage's first measurement does not pay it.

The range stage's calibration and estimator come from ``TCSPC_FORK_WARM_RANGE`` (JSON, set
by the daemon before it starts the server). Nothing here may fail the server: a problem is
left to the range stage, which reports it in its own log. No thread is started here (the
kernels are numba's serial ones), so a fork after it is safe.
"""

from __future__ import annotations

import json
import os


def _warm() -> None:
    spec = os.environ.get("TCSPC_FORK_WARM_RANGE")
    if not spec:
        return
    try:
        from pipeline.io.caldir import load_calibration
        from pipeline.offline.ranging import RangeCore

        args = json.loads(spec)
        more = {"max_returns": args["max_returns"]} if "max_returns" in args else {}
        RangeCore(load_calibration(args["calibration"]), args.get("estimator", "ml"),
                  **more)  # (its __init__ ranges a made-up measurement: the kernels load)
    except Exception:  # noqa: BLE001 (the stage reports its own problems)
        pass


_warm()
