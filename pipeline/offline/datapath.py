"""Offline drivers: run the data-path stages over a whole capture file in bounded memory."""

from __future__ import annotations

import queue
from collections import deque
from collections.abc import Callable, Iterable
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from pipeline.io.atomic import atomic_path
from pipeline.io.capture import Capture
from pipeline.offline.threads import default_threads
from schemas.constants import N_CLASSES, WORD_CLASSES
from stages.artifact import ArtifactBounds, estimate_bounds
from stages.datapath import default_engine
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


def _fan_out(chunks: Iterable[tuple[int, np.ndarray]], lanes: list, progress: Progress,
             stable: int = 1) -> None:
    """Feed the chunks to ``lanes`` (accumulators with ``update(words, first_word)``), one
    thread each; each chunk goes to whichever lane is free. ``stable``: for how many
    chunks a yielded view stays valid (a capture's ``chunk_ring``); the chunks of a
    source that reuses its buffer sooner are copied before they are handed on."""
    if len(lanes) == 1:
        for first, words in chunks:
            lanes[0].update(words, first)
            progress(words.size)
        return
    free: queue.SimpleQueue = queue.SimpleQueue()
    for lane in lanes:
        free.put(lane)

    def run(words, first):
        lane = free.get()  # one never waits: at most len(lanes) tasks run at once
        try:
            lane.update(words, first)
        finally:
            free.put(lane)
        return words.size

    # chunks in flight when the next is read: a view must not be overwritten before its
    # lane is done with it
    copy = stable - 1 < len(lanes)
    limit = len(lanes) + 1 if copy else stable - 1
    pending: deque = deque()
    with ThreadPoolExecutor(len(lanes), thread_name_prefix="histogram") as pool:
        for first, words in chunks:
            if copy:  # a source that reuses its buffer too soon: hand on a copy
                words = words.copy()
            pending.append(pool.submit(run, words, first))
            while len(pending) > limit:
                progress(pending.popleft().result())
        while pending:
            progress(pending.popleft().result())


def histogram_capture(cap: Capture, bounds: ArtifactBounds | None = None,
                      engine: str | None = None, progress: Progress = _noop,
                      log: Callable[[str], None] | None = None,
                      threads: int | None = None) -> tuple[HistogramState, ArtifactBounds]:
    """Histogram a whole capture. Without ``bounds`` they are estimated from the capture in
    the same pass (:class:`stages.histogram.SelfBoundingHistogram`); only when the
    capture's first chunk misled the provisional bounds is a second pass made (``log``
    says so). ``threads`` (default :func:`default_threads`) share the words, each
    summing its own counts: the result is the same for any number."""
    if threads is None:  # the numpy engine holds the GIL too often to gain from threads
        threads = default_threads() if (engine or default_engine()) == "numba" else 1
    # a capture's chunks can go to the threads as they are read, from a ring of buffers
    # (Capture.iter_chunks) long enough for the chunks in flight; other sources' are copied
    ring = getattr(cap, "chunk_ring", None)
    if ring is not None and threads > 1:
        cap.chunk_ring = max(ring, threads + 2)
    try:
        return _histogram_capture(cap, bounds, engine, progress, log, threads,
                                  getattr(cap, "chunk_ring", 1))
    finally:
        if ring is not None:
            cap.chunk_ring = ring


def _histogram_capture(cap, bounds, engine, progress, log, threads, stable):
    if bounds is None:
        one = SelfBoundingHistogram(cap.meta.n_tdc, engine=engine)
        chunks = iter(cap.iter_chunks())
        head = next(chunks, None)
        if head is not None:  # the first chunk sets the provisional cores the forks share
            one.update(head[1], head[0])
            progress(head[1].size)
            forks = [one.fork() for _ in range(threads - 1)]
            _fan_out(chunks, [one, *forks], progress, stable)
            for f in forks:
                one.merge(f)
        state, bounds = one.finish()
        if state is not None:
            return state, bounds
        if log:
            log("the first chunk's provisional artifact bounds did not hold: a second pass")
    accs = [HistogramAccumulator(cap.meta.n_tdc, bounds, engine=engine)
            for _ in range(threads)]
    _fan_out(cap.iter_chunks(), accs, progress, stable)
    state = accs[0].snapshot()
    for acc in accs[1:]:
        state = state + acc.snapshot()
    return state, bounds


def write_histograms(state: HistogramState, measurement: str, out: str | Path,
                     provenance: dict[str, str] | None = None) -> None:
    """Write a ``histograms`` parquet file atomically, with provenance in its metadata."""
    from pipeline.io.histograms import write_histogram_table

    write_histogram_table(state.to_table(measurement), out, provenance)


def decode_capture(cap: Capture, out: str | Path, bounds: ArtifactBounds | None = None,
                   include_no_hit: bool = False, engine: str | None = None,
                   progress: Progress = _noop) -> tuple[np.ndarray, ArtifactBounds]:
    """Decode a capture into a ``decoded_events`` parquet file; returns the class counts."""
    import pyarrow.parquet as pq

    from schemas.words import DECODED_EVENTS
    from stages.decode import decode_batch

    if bounds is None:
        bounds = estimate_capture_bounds(cap, engine, progress)
    counts = np.zeros(N_CLASSES, np.int64)
    schema = DECODED_EVENTS.schema.with_metadata({
        **DECODED_EVENTS.schema.metadata, b"tcspc.capture": str(cap.bin_path).encode(),
        b"tcspc.bounds": bounds.source.encode(),
        **({b"tcspc.truncated": b"True"} if getattr(cap, "truncated", None) else {})})
    with atomic_path(out) as tmp, pq.ParquetWriter(tmp, schema) as writer:
        for first, words in cap.iter_chunks():
            batch, cls = decode_batch(words, cap.meta.n_tdc, first, bounds, include_no_hit)
            writer.write_batch(batch.replace_schema_metadata(schema.metadata))
            counts += np.bincount(cls, minlength=N_CLASSES)
            progress(words.size)
    return counts, bounds


def class_summary(counts) -> dict[str, int]:
    return {name: int(counts[i]) for i, name in enumerate(WORD_CLASSES)}


__all__ = ["class_summary", "decode_capture", "default_threads", "estimate_capture_bounds",
           "histogram_capture", "write_histograms"]
