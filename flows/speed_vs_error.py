"""``speed_vs_error``: every range estimator over the range issue's grid (M x cycles x SBR x
place in the window), throughput against RMSE over the CRLB. The numerics are
``stages.ranging_eval``; ``benchmarks/speed_vs_error.py`` runs the same grid pinned to one
core for the published table. Outputs under ``out/runs/<run>``: cells.parquet, a Pareto
figure and report.md.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import polars as pl
from prefect import flow, task
from pydantic import NonNegativeInt, PositiveInt

from flows.common import Estimator, new_run_dir, report
from pipeline.report.figures import speed_error_figure
from pipeline.report.report import markdown_table, speed_error_summary
from stages.ranging import ESTIMATORS
from stages.ranging_eval import PLACES, Setup, draw, score


@task(task_run_name="cell M={m} cycles={cycles}")
def cells(m: float, cycles: int, sbrs: list[float], pixels: int, seed: int,
          estimators: list[str]) -> list[dict]:
    """All SBRs and places of one (M, cycles) pair; seeded, so reruns draw the same."""
    rng = np.random.default_rng([seed, int(m * 1e6), cycles])
    rows = []
    for sbr in sbrs:
        for place, tof in PLACES.items():
            hist, t, crlb = draw(rng, m, cycles, sbr, tof, pixels)
            rows += [{"m": m, "cycles": cycles, "signal_counts": m * cycles, "sbr": sbr,
                      "place": place, **r}
                     for r in score(hist, t, crlb, Setup().sigma_s, estimators)]
    return rows


#: a grid that runs longer is failed by Prefect (a hang: not Running forever)
SPEED_TIMEOUT_S = 2 * 3600


@flow(name="speed_vs_error", timeout_seconds=SPEED_TIMEOUT_S)
def speed_vs_error(out: str = "data/speed_vs_error", m: list[float] | None = None,
                   cycles: list[int] | None = None, sbr: list[float] | None = None,
                   pixels: PositiveInt = 200, estimators: list[Estimator] | None = None,
                   seed: NonNegativeInt = 2024) -> dict:
    """Speed against error of the range estimators over a grid (the range issue's by
    default: M 0.01-5, cycles 1e3-1e5, SBR 0.01-100, three places in the window)."""
    run = new_run_dir(out, "speed_vs_error")
    m = [0.01, 0.1, 1.0, 5.0] if m is None else m
    cycles = [1_000, 10_000, 100_000] if cycles is None else cycles
    sbr = [0.01, 1.0, 100.0] if sbr is None else sbr
    estimators = list(ESTIMATORS) if estimators is None else estimators
    unknown = sorted(set(estimators) - set(ESTIMATORS))
    if unknown:
        raise ValueError(f"unknown estimators {unknown}; known: {list(ESTIMATORS)}")
    futures = [cells.submit(mi, ci, sbr, pixels, seed, estimators) for mi in m for ci in cycles]
    df = pl.DataFrame([r for f in futures for r in f.result()])
    df.write_parquet(run / "cells.parquet")
    png = str(speed_error_figure(df, run / "speed_vs_error.png"))
    good, summary, by_m = speed_error_summary(df)
    rep = report(str(run / "report.md"), "Range estimators: speed against error", [
        ("Grid", f"M {m}, cycles {cycles}, SBR {sbr}, places {list(PLACES)}, {pixels} "
                 "histograms per cell; throughput measured in the flow's worker (not pinned: "
                 "see benchmarks/ for the published table)."),
        (f"Summary over cells with detection > 90 % and SBR >= 1 ({good.height} rows)",
         markdown_table(summary)),
        ("Median RMSE / CRLB by M", markdown_table(by_m)),
        ("Plot", f"![speed_vs_error]({Path(png).name})"),
    ])
    result = {"run": str(run), "report": rep, "plots": [png],
              "summary": summary.to_dicts()}
    (run / "summary.json").write_text(json.dumps(result, indent=1))
    return result
