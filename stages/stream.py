"""Stage cores for the stream: plain objects the generic ZeroMQ runner drives.

A core has a ``step_id``, ``process(header, batch) -> [(header, batch), ...]`` for each
data message and ``finish(header) -> [...]`` at the end of the stream. No sockets here.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from schemas.outputs import HISTOGRAMS
from schemas.words import RAW_WORDS, WORD_CLASSES
from stages.artifact import ArtifactBounds
from stages.histogram import HistogramAccumulator


class HistogramCore:
    """Folds raw-word batches into per-TDC histograms; emits them at the end."""

    in_spec = RAW_WORDS
    out_spec = HISTOGRAMS

    def __init__(self, n_tdc: int, bounds: ArtifactBounds | None = None,
                 step_id: str = "histogram", engine: str | None = None):
        self.step_id = step_id
        self.acc = HistogramAccumulator(n_tdc, bounds, engine=engine, step_id=step_id)
        self.seq = 0

    def process(self, header: dict, batch: pa.RecordBatch) -> list:
        words = batch.column("word").to_numpy(zero_copy_only=False).astype(np.uint32,
                                                                          copy=False)
        self.acc.update(words, int(header["first_word"]), seq=int(header["seq"]))
        return []

    def finish(self, header: dict) -> list:
        state = self.acc.snapshot()
        table = state.to_table(str(header.get("run", "run")))
        out = {"kind": "data", "schema": HISTOGRAMS.name, "version": HISTOGRAMS.version,
               "run": header.get("run", "run"), "seq": self.seq, "step": self.step_id,
               "words": state.words,
               "class_counts": dict(zip(WORD_CLASSES, state.class_counts.sum(1).tolist(),
                                        strict=True))}
        self.seq += 1
        return [(out, batch) for batch in table.to_batches()]
