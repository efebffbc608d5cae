"""Offline drivers: run the data-path stages over a whole capture file in bounded memory."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from pipeline.io.atomic import atomic_path
from pipeline.io.capture import Capture
from pipeline.io.histograms import write_histogram_table
from schemas.outputs import HISTOGRAMS
from schemas.words import DECODED_EVENTS, N_CLASSES, WORD_CLASSES
from stages.artifact import ArtifactBounds, estimate_bounds
from stages.decode import decode_batch
from stages.histogram import HistogramAccumulator, HistogramState, SelfBoundingHistogram

Progress = Callable[[int], None]  #: called with the number of words just processed


def _noop(_: int) -> None:
    pass


def estimate_capture_bounds(cap: Capture, engine: str | None = None,
                            progress: Progress = _noop) -> ArtifactBounds:
    """Pass 1 without a calibration: histogram D2nd per TDC and find the valid block."""
    acc = HistogramAccumulator(cap.meta.n_tdc, engine=engine, step_id="bounds", mode="d2nd")
    for first, words in cap.iter_chunks():
        acc.update(words, first)
        progress(words.size)
    return estimate_bounds(acc.snapshot().hits)


def histogram_capture(cap: Capture, bounds: ArtifactBounds | None = None,
                      engine: str | None = None, progress: Progress = _noop,
                      log: Callable[[str], None] | None = None
                      ) -> tuple[HistogramState, ArtifactBounds]:
    """Histogram a whole capture. Without ``bounds`` they are estimated from the capture in
    the same pass (:class:`stages.histogram.SelfBoundingHistogram`); only when the
    capture's first chunk misled the provisional bounds is a second pass made (``log``
    says so)."""
    if bounds is None:
        one = SelfBoundingHistogram(cap.meta.n_tdc, engine=engine)
        for first, words in cap.iter_chunks():
            one.update(words, first)
            progress(words.size)
        state, bounds = one.finish()
        if state is not None:
            return state, bounds
        if log:
            log("the first chunk's provisional artifact bounds did not hold: a second pass")
    acc = HistogramAccumulator(cap.meta.n_tdc, bounds, engine=engine)
    for first, words in cap.iter_chunks():
        acc.update(words, first)
        progress(words.size)
    return acc.snapshot(), bounds


def write_histograms(state: HistogramState, measurement: str, out: str | Path,
                     provenance: dict[str, str] | None = None) -> None:
    """Write a ``histograms`` parquet file atomically, with provenance in its metadata."""
    write_histogram_table(state.to_table(measurement), out, provenance)


def decode_capture(cap: Capture, out: str | Path, bounds: ArtifactBounds | None = None,
                   include_no_hit: bool = False, engine: str | None = None,
                   progress: Progress = _noop) -> tuple[np.ndarray, ArtifactBounds]:
    """Decode a capture into a ``decoded_events`` parquet file; returns the class counts."""
    if bounds is None:
        bounds = estimate_capture_bounds(cap, engine, progress)
    counts = np.zeros(N_CLASSES, np.int64)
    schema = DECODED_EVENTS.schema.with_metadata({
        **DECODED_EVENTS.schema.metadata, b"tcspc.capture": str(cap.bin_path).encode(),
        b"tcspc.bounds": bounds.source.encode()})
    with atomic_path(out) as tmp, pq.ParquetWriter(tmp, schema) as writer:
        for first, words in cap.iter_chunks():
            batch, cls = decode_batch(words, cap.meta.n_tdc, first, bounds, include_no_hit)
            writer.write_batch(batch.replace_schema_metadata(schema.metadata))
            counts += np.bincount(cls, minlength=N_CLASSES)
            progress(words.size)
    return counts, bounds


def class_summary(counts) -> dict[str, int]:
    return {name: int(counts[i]) for i, name in enumerate(WORD_CLASSES)}


__all__ = ["HISTOGRAMS", "class_summary", "decode_capture", "estimate_capture_bounds",
           "histogram_capture", "write_histograms"]
