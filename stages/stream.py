"""Stage cores for the stream: plain objects the generic ZeroMQ runner drives.

A core has a ``step_id``, ``process(header, batch) -> [(header, batch), ...]`` for each
data message and ``finish(header) -> [...]`` at the end of the stream. No sockets here.

Measurements. With ``measurement_cycles`` M, the histogram core emits one histogram per M
cycles: measurement k holds the cycles [k M, (k + 1) M) of the run, fixed by the words'
stream index, not by how they were batched or when a stage restarted. So the same run gives
the same measurements, and one sent twice after a restart is the same message twice (the
sink writes it to the same file). Without M the run is one measurement, emitted at its end.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from schemas.constants import N_CLASSES, WORD_CLASSES
from schemas.errors import Rejected
from schemas.outputs import HISTOGRAMS
from schemas.words import RAW_SPARSE, RAW_WORDS
from stages.artifact import ArtifactBounds
from stages.datapath import SparseWords
from stages.histogram import HistogramAccumulator


class HistogramCore:
    """Folds raw-word batches into per-TDC histograms, one per measurement.

    ``tdc_offset``: this worker takes TDCs ``tdc_offset .. tdc_offset + n_tdc - 1`` of each
    cycle (a fan-out by TDC range); its stream index counts its own words.
    """

    #: raw words whole, or in sparse form (what a chip's source sends)
    in_spec = {RAW_WORDS.name: RAW_WORDS, RAW_SPARSE.name: RAW_SPARSE}
    out_spec = HISTOGRAMS

    def __init__(self, n_tdc: int, bounds: ArtifactBounds | None = None,
                 step_id: str = "histogram", engine: str | None = None, backfill=None,
                 tdc_offset: int = 0, measurement_cycles: int | None = None,
                 context: dict | None = None, accumulator=None):
        """``backfill(start, stop)`` yields (first_word, words) of a gap in the stream (the
        pipeline reads them from the journal); None: gaps are counted, not filled.
        ``context``: the run's run id, gate, window and date known before any message (a
        worker restarted after its source ended hears none, yet must label its output).
        ``accumulator``: another instrument's accumulator in place of the thesis chip's
        (:mod:`stages.instruments.accumulate`: a PTU T3 or LinoSPAD2 file replayed through
        the graph); it has the same ``update``/``snapshot``/``reset`` and its own
        ``checkpoint``/``restore_checkpoint``."""
        if measurement_cycles is not None and measurement_cycles < 1:
            raise ValueError(f"measurement_cycles must be >= 1, found {measurement_cycles}")
        self.step_id = step_id
        self.n_tdc = n_tdc
        self.instrument = accumulator is not None
        self.acc = accumulator if accumulator is not None else HistogramAccumulator(
            n_tdc, bounds, engine=engine, step_id=step_id, tdc_offset=tdc_offset)
        self.tdc_offset = tdc_offset
        self.m_words = None if measurement_cycles is None else measurement_cycles * n_tdc
        self.measurement = 0      #: index of the measurement being filled
        self.emitted = 0          #: measurements sent (this process)
        self.next_word = 0
        self.backfill = backfill
        self.duplicates = 0
        self.backfilled = 0
        self.gap_words = 0
        self.words_total = 0      #: words folded in over the run (restored from checkpoints)
        #: words by class of the measurements emitted whole by this process
        self._classes_done = np.zeros(N_CLASSES, np.uint64)
        self.context: dict = dict(context or {})  #: gate and the like, from the headers
        self._out: list = []

    # ------------------------------------------------------------------ folding
    def _accumulate(self, first: int, words: np.ndarray, seq=None) -> None:
        self.words_total += words.size
        if self.m_words is None:
            self.acc.update(words, first, seq=seq)
            return
        while words.size:
            k = first // self.m_words
            if k != self.measurement:  # a gap reached past the measurement being filled
                if self.acc.snapshot().words:
                    self._emit(partial=True)
                self.measurement = k
            end = (k + 1) * self.m_words
            take = min(words.size, end - first)
            self.acc.update(words[:take], first, seq=seq)
            first, words = first + take, words[take:]
            if first == end:
                self._emit(partial=False)

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
                    self._accumulate(f, w)
                    self.backfilled += w.size
                    self.next_word = f + w.size
            if first > self.next_word:
                self.gap_words += first - self.next_word
        self._accumulate(first, words, seq)
        self.next_word = first + words.size

    def catch_up(self, total_words: int) -> None:
        """Fold in what is missing up to the end of the run (from the backfill)."""
        if total_words > self.next_word and self.backfill is not None:
            for f, w in self.backfill(self.next_word, total_words):
                self._fold(f, w)
                self.backfilled += w.size

    # ------------------------------------------------------------------ output
    def _emit(self, partial: bool, keep: bool = False) -> None:
        """Send the measurement being filled; ``keep``: and go on filling it (the stream's
        end or a stop: the checkpoint keeps it, so a run resumed later completes it and its
        complete histogram replaces the partial one, the same file)."""
        state = self.acc.snapshot()
        run = str(self.context.get("run", "run"))
        k = self.measurement
        name = run if self.m_words is None else f"{run}-m{k:06d}"
        table = state.to_table(name)
        cycles0 = 0 if self.m_words is None else k * (self.m_words // self.n_tdc)
        head = {"kind": "data", "schema": HISTOGRAMS.name, "version": HISTOGRAMS.version,
                "run": run, "seq": k, "step": self.step_id, "measurement": name,
                "measurement_index": k, "partial": partial,
                "cycles": [cycles0, cycles0 + int(state.cycles.max(initial=0))],
                "tdc_range": [self.tdc_offset, self.tdc_offset + self.n_tdc],
                "words": state.words,
                "class_counts": state.totals(),
                **{k2: v for k2, v in self.context.items() if k2 != "run"}}
        self._out += [(head, batch) for batch in table.to_batches()]
        self.emitted += 1
        if keep:
            return
        self._classes_done += state.class_counts.sum(axis=1).astype(np.uint64)
        self.acc.reset()
        self.measurement += 1

    def words_by_class(self) -> dict[str, int] | None:
        """Words folded in by this process by class (the measurements it emitted whole and
        the one being filled, from its checkpoint on): the live metrics' words by class,
        a counter that starts again with the process (the run's truth is the
        accounting's). None for an accumulator that does not count classes."""
        live = getattr(self.acc, "class_totals", None)
        if live is None:
            return None
        tot = self._classes_done + live()
        return {name: int(tot[i]) for i, name in enumerate(WORD_CLASSES)}

    def _take(self) -> list:
        out, self._out = self._out, []
        return out

    def process(self, header: dict, batch: pa.RecordBatch) -> list:
        self.context = {**self.context, "run": header.get("run", "run"),
                        **{k: header[k] for k in ("t_laser_win_ns", "window_ns",
                                                  "n_tdc_total", "date") if k in header}}
        words = batch.column("word").to_numpy(zero_copy_only=False).astype(np.uint32,
                                                                          copy=False)
        if header.get("schema") == RAW_SPARSE.name:
            if self.instrument:
                raise Rejected("schema_mismatch", f"{self.step_id}: sparse raw words are the "
                               "thesis chip's; this worker folds an instrument's records")
            index = batch.column("index").to_numpy(zero_copy_only=False).astype(np.uint32,
                                                                               copy=False)
            words = SparseWords(int(header["n_words"]), index, words)
            problem = words.problem()
            if problem:
                raise Rejected("bad_payload", f"message {header['seq']}: {problem}")
        self._fold(int(header["first_word"]), words, int(header["seq"]))
        return self._take()

    def finish(self, header: dict) -> list:
        self.context.setdefault("run", header.get("run", "run"))
        if self.acc.snapshot().words or self.m_words is None:
            self._emit(partial=self.m_words is not None, keep=True)
        return self._take()

    # ------------------------------------------------------------------ checkpoints
    def snapshot(self) -> dict:
        """Arrays and counters to checkpoint (the runner stores them; never pickled)."""
        if self.instrument:
            return {**self.acc.checkpoint(),
                    "counters": np.array([0, -1, self.next_word, self.measurement,
                                          self.words_total], np.int64)}
        st = self.acc.snapshot()
        return {"hits": st.hits, "class_counts": st.class_counts,
                "counters": np.array([st.words, st.last_seq, self.next_word,
                                      self.measurement, self.words_total], np.int64)}

    def restore(self, state: dict) -> None:
        from stages.histogram import HistogramState

        words, last_seq, next_word, measurement, total = (int(x) for x in state["counters"])
        self.words_total = total
        self.next_word, self.measurement = next_word, measurement
        if self.instrument:
            self.acc.restore_checkpoint(state)
            return
        self.acc.restore(HistogramState(state["hits"], state["class_counts"], words, last_seq,
                                        self.tdc_offset))
