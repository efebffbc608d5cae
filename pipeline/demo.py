"""``tcspc demo``: the main job on embedded defaults, outputs under ./data.

Today: a synthetic capture (stages.testpattern, with its intended class counts in the
sidecar) -> decode -> histogram, checked against the truth and queried with Polars. The
simulator, calibration, ranging and the streaming daemon join this story as they land.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
from rich.console import Console

from pipeline.capture import Capture, CaptureWriter
from pipeline.offline import decode_capture, histogram_capture, write_histograms
from schemas.words import WORD_CLASSES
from stages.testpattern import pattern_words


def run_demo(out: str | Path = "data", cycles: int = 100_000, seed: int = 0,
             console: Console | None = None) -> dict:
    """Run the demo; returns the paths written and the checks made."""
    con = console or Console(stderr=True)
    out = Path(out)
    raw = out / "raw" / "pattern"
    con.rule("1. a capture with a known class mix (128 TDCs, peak at code 300)")
    words, truth = pattern_words(cycles, 128, hit_prob=0.05, peak_code=300.0, rng=seed)
    with CaptureWriter(raw, 128, kind="pattern", note="make demo") as w:
        w.write(words)
    cap = Capture(raw)
    con.print(f"{cap.bin_path}: {cap.n_words:,} words, {cap.meta.cycles:,} cycles")

    con.rule("2. histogram (artifact bounds estimated from the capture)")
    state, bounds = histogram_capture(cap)
    hist_path = out / "histograms" / "pattern.parquet"
    write_histograms(state, "pattern", hist_path, {"capture": cap.bin_path,
                                                     "bounds": bounds.source})
    counts = state.class_counts.sum(axis=1)
    intended = truth.class_counts.sum(axis=1)
    for name, got, want in zip(WORD_CLASSES, counts, intended, strict=True):
        con.print(f"  {name:14s} {int(got):>10,}  (intended {int(want):,})")
    exact = bool(np.array_equal(state.hits, truth.hits)
                 and np.array_equal(state.class_counts, truth.class_counts))
    con.print(f"per-TDC histograms and class counts equal the intended ones: {exact}")

    con.rule("3. decode to events (hits, artifacts and bad words; no_hit counted)")
    events_path = out / "events" / "pattern.parquet"
    decode_capture(cap, events_path, bounds)

    con.rule("4. query the outputs with Polars")
    peaks = (pl.read_parquet(hist_path)
             .with_columns(peak_code=pl.col("counts").arr.arg_max())
             .select("tdc", "cycles", "n_hit", "n_artifact", "peak_code"))
    con.print(peaks.head(5))
    by_class = (pl.scan_parquet(events_path).group_by("word_class").len()
                .sort("word_class").collect())
    con.print(by_class)
    return {"capture": str(cap.bin_path), "histograms": str(hist_path),
            "events": str(events_path), "exact": exact}
