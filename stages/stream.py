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
                 step_id: str = "histogram", engine: str | None = None, backfill=None):
        """``backfill(start, stop)`` yields (first_word, words) of a gap in the stream (the
        pipeline reads them from the journal); None: gaps are counted, not filled."""
        self.step_id = step_id
        self.acc = HistogramAccumulator(n_tdc, bounds, engine=engine, step_id=step_id)
        self.seq = 0
        self.next_word = 0
        self.backfill = backfill
        self.duplicates = 0
        self.backfilled = 0
        self.gap_words = 0

    def _fold(self, first: int, words: np.ndarray, seq=None) -> None:
        if first < self.next_word:  # already folded in before a restart: no double count
            skip = min(self.next_word - first, words.size)
            self.duplicates += skip
            first, words = first + skip, words[skip:]
            if words.size == 0:
                return
        if first > self.next_word:
            if self.backfill is not None:
                for f, w in self.backfill(self.next_word, first):
                    self.acc.update(w, f)
                    self.backfilled += w.size
                    self.next_word = f + w.size
            if first > self.next_word:
                self.gap_words += first - self.next_word
        self.acc.update(words, first, seq=seq)
        self.next_word = first + words.size

    def catch_up(self, total_words: int) -> None:
        """Fold in what is missing up to the end of the run (from the backfill)."""
        if total_words > self.next_word and self.backfill is not None:
            for f, w in self.backfill(self.next_word, total_words):
                self._fold(f, w)
                self.backfilled += w.size

    def process(self, header: dict, batch: pa.RecordBatch) -> list:
        words = batch.column("word").to_numpy(zero_copy_only=False).astype(np.uint32,
                                                                          copy=False)
        self._fold(int(header["first_word"]), words, int(header["seq"]))
        return []

    def snapshot(self) -> dict:
        """Arrays and counters to checkpoint (the runner stores them; never pickled)."""
        st = self.acc.snapshot()
        return {"hits": st.hits, "class_counts": st.class_counts,
                "counters": np.array([st.words, st.last_seq, self.next_word, self.seq],
                                     np.int64)}

    def restore(self, state: dict) -> None:
        from stages.histogram import HistogramState

        words, last_seq, next_word, seq = (int(x) for x in state["counters"])
        self.acc.restore(HistogramState(state["hits"], state["class_counts"], words, last_seq))
        self.next_word, self.seq = next_word, seq

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
