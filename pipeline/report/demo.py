"""The data-path part of ``tcspc demo`` (flows/demo.py runs it first), outputs under ./data.

1. a synthetic capture with a known class mix -> histogram and decode, checked exactly;
2. the street scene through the simulator (the chip's words, truth in the sidecar) ->
   histogram -> each target's peak code against the code its distance predicts (eq. 5.4);
3. Polars queries of the outputs.
The calibration campaign, the streaming daemon and the ranges follow in flows/demo.py.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import polars as pl
from rich.console import Console

from pipeline.io.capture import Capture, CaptureWriter
from pipeline.offline.datapath import decode_capture, histogram_capture, write_histograms
from schemas.constants import WORD_CLASSES
from stages.testpattern import pattern_words


def run_demo(out: str | Path = "data", cycles: int = 100_000, seed: int = 0,
             console: Console | None = None) -> dict:
    """Run the demo; returns the paths written and the checks made."""
    con = console or Console(stderr=True, markup=False)  # paths are printed as they are
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

    con.rule("4. the street scene through the simulated chip (fast engine)")
    street = _street(out, con)

    con.rule("5. query the outputs with Polars")
    peaks = (pl.read_parquet(hist_path)
             .with_columns(peak_code=pl.col("counts").list.arg_max())
             .select("tdc", "cycles", "n_hit", "n_artifact", "peak_code"))
    con.print(peaks.head(5))
    by_class = (pl.scan_parquet(events_path).group_by("word_class").len()
                .sort("word_class").collect())
    con.print(by_class)
    return {"capture": str(cap.bin_path), "histograms": str(hist_path),
            "events": str(events_path), "exact": exact, **street}


def _street(out: Path, con: Console, cycles: int = 20_000) -> dict:
    """Simulate the street scene, histogram it, and compare each target's peak code with
    the code its distance predicts: tau = T_LW - delay - 2 d / c over the chip's LSB."""
    from scipy.constants import c

    from pipeline.offline.simulate import simulate_capture

    scene = Path(__file__).resolve().parents[2] / "scenes" / "street.toml"
    raw = out / "raw" / "street"
    meta, sim = simulate_capture(scene, cycles, raw, seed=1)
    cap = Capture(raw)
    truth = cap.meta.truth
    state, bounds = histogram_capture(cap)
    write_histograms(state, "street", out / "histograms" / "street.parquet",
                     {"capture": cap.bin_path, "bounds": bounds.source})
    lsb = np.array(truth["chip"]["lsb_window_ps"]) * 1e-12
    rows = []
    for t in sim.sm.scene.targets:
        px = np.arange(t.pixels[0], t.pixels[1] + 1)
        tau = (truth["t_laser_win_ns"] - truth["delay_ns"]) * 1e-9 - 2 * t.distance_m / c
        expected = float(np.mean(tau / lsb[px]))
        # below the window's start (x_T): the reset peak sits at x_T
        top = np.floor(np.array(truth["chip"]["x_t"])[px] - 6).astype(int)
        masked = np.where(np.arange(state.hits.shape[1])[None, :] < top[:, None],
                          state.hits[px], 0)
        peak = masked[:, 2:].argmax(axis=1) + 2
        rows.append((t.distance_m, expected, float(np.median(peak))))
        con.print(f"  target at {t.distance_m:5.1f} m (pixels {t.pixels[0]}-{t.pixels[1]}): "
                  f"peak code {np.median(peak):.0f}, expected ~{expected:.1f} "
                  f"(INL shifts it by up to ~2 codes)")
    ok = all(abs(got - want) <= 4 for _, want, got in rows)
    con.print(f"every target's peak within 4 codes of its distance: {ok}")
    return {"street_capture": str(cap.bin_path), "street_ok": ok}
