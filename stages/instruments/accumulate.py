"""Accumulators of instruments' records for the stream: the same duck type as the thesis
chip's :class:`stages.histogram.HistogramAccumulator` (``update``, ``snapshot``, ``reset``)
plus ``checkpoint`` / ``restore_checkpoint``, so :class:`stages.stream.HistogramCore` folds a
replayed PTU T3 or LinoSPAD2 file as it folds chip words, and the offline command uses the
very same object (live and offline histograms are equal by construction, and a test checks
that the stream's transport, journal and restarts keep them so).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa

from schemas.outputs import HISTOGRAMS

if TYPE_CHECKING:  # (the decoders are imported where a record is decoded)
    from stages.instruments.ptu import Tally

PICOQUANT_T3 = "picoquant-t3"
LINOSPAD2 = "linospad2"
_CLASS_COLUMNS = ("n_no_hit", "n_artifact", "n_invalid_phase", "n_malformed")


def column(values, type_: pa.DataType) -> pa.Array:
    """A column without nulls over a numpy array's memory (converted to ``type_``'s dtype
    where it differs, else no copy), without ``pa.array``'s check for a masked array,
    which imports numpy.ma (30-90 ms of a command's start)."""
    values = np.ascontiguousarray(values, type_.to_pandas_dtype())
    return pa.Array.from_buffers(type_, values.size, [None, pa.py_buffer(values)])


def instrument_table(measurement: str, counts: np.ndarray, cycles, instrument: str,
                     bin_width_ps: float | None, rows=None) -> pa.Table:
    """``histograms`` 2.0 rows of an instrument: ``counts`` (n_rows, n_codes) uint64,
    ``cycles`` per row (or one for all), ``rows`` the ``tdc`` value of each row. The class
    columns are the thesis chip's: ``n_hit`` is the row's counts, the others 0 (an
    instrument's record classes are in the file's ``tcspc.class_counts``)."""
    counts = np.ascontiguousarray(counts, np.uint64)
    n, k = counts.shape
    rows = np.arange(n) if rows is None else np.asarray(rows)
    cols = {
        "measurement": pa.array([measurement] * n, pa.string()),
        "tdc": column(rows, pa.uint16()),
        "cycles": column(np.broadcast_to(np.asarray(cycles, np.uint64), (n,)), pa.uint64()),
        "counts": pa.ListArray.from_arrays(column(np.arange(n + 1) * k, pa.int32()),
                                           column(counts.ravel(), pa.uint64())),
        "n_hit": column(counts.sum(axis=1, dtype=np.uint64), pa.uint64()),
        **{c: column(np.zeros(n), pa.uint64()) for c in _CLASS_COLUMNS},
        "instrument": pa.array([instrument] * n, pa.string()),
        "bin_width_ps": pa.array([bin_width_ps] * n, pa.float64()),
    }
    return pa.Table.from_pydict(cols, schema=HISTOGRAMS.schema)


@dataclass(frozen=True)
class InstrumentState:
    """A snapshot of an instrument accumulator: what ``HistogramCore`` emits."""

    counts: np.ndarray       #: (n_rows, n_codes) uint64
    n_cycles: int            #: sync periods (PTU T3) or acquisition cycles (LinoSPAD2)
    words: int               #: records folded in
    classes: dict            #: records by class; they add up to ``words``
    instrument: str
    bin_width_ps: float

    @property
    def cycles(self) -> np.ndarray:
        return np.full(self.counts.shape[0], self.n_cycles, np.uint64)

    def totals(self) -> dict[str, int]:
        return dict(self.classes)

    def to_table(self, measurement: str) -> pa.Table:
        """Rows per channel (TDC, pixel); a PTU's codes up to the last one any channel used
        (its 2^15 dtime codes mostly lie beyond the sync period: nothing is dropped)."""
        c = self.counts
        if self.instrument == PICOQUANT_T3:
            used = int(np.flatnonzero(c.any(axis=0))[-1]) + 1 if c.any() else 1
            c = c[:, :used]
        return instrument_table(measurement, c, self.n_cycles, self.instrument,
                                self.bin_width_ps)


@dataclass(frozen=True)
class T3Part:
    """What a run of PTU T3 records adds to an accumulator, apart from its photons'
    counts: ``tally`` counted from 0 wraps (its ``wraps`` are the wraps the run adds),
    ``tail`` the syncs its last event reaches past them (0 when none does), ``words``
    its records."""

    tally: Tally
    tail: int
    words: int


class PtuT3Accumulator:
    """PicoQuant T3 records, in file order, into counts[channel, dtime].

    The overflow count carries from one batch to the next (a record's sync number depends
    on every overflow before it), so batches must come in order: the stream's
    ``HistogramCore`` guarantees it (it skips what it has and backfills gaps from the
    journal before folding on).
    """

    def __init__(self, fmt, resolution_s: float, n_channels: int | None = None,
                 engine: str | None = None):
        if not fmt.is_t3:
            raise ValueError(f"{fmt.name} is a T2 format: there is no dtime to histogram")
        from stages.instruments.ptu import resolution_ps_fraction

        self.fmt, self.engine = fmt, engine
        # headers store 64 ps as the float32 rounding 6.3999999744e-11 s: the exact value
        self.bin_width_ps = float(resolution_ps_fraction(resolution_s))
        self.n_channels = int(n_channels or fmt.n_channels)
        self.reset(keep_position=False)

    def reset(self, keep_position: bool = True) -> None:
        """Zero the counts (a new measurement); the position in the record stream (the
        overflow count) is kept unless ``keep_position`` is False."""
        self.counts = np.zeros((self.n_channels, self.fmt.n_dtime_codes), np.uint64)
        self.classes = dict.fromkeys(("photons", "markers", "overflow", "invalid",
                                      "out_of_range"), 0)
        self.words = 0
        if not keep_position:
            self.wraps = 0
            self.n_syncs = 0

    def update(self, words: np.ndarray, first: int = 0, seq=None) -> None:
        words = np.asarray(words, np.uint32)
        if words.size:
            self.fold(self.part(words))

    def part(self, words: np.ndarray, counts: np.ndarray | None = None) -> T3Part:
        """What ``words`` (a non-empty run of records) add, wherever they sit in the file:
        their photons added into ``counts`` (this accumulator's by default; a thread's own
        array when chunks are histogrammed in parallel), the rest as a :class:`T3Part`.
        Nothing of the accumulator changes but ``counts``: the parts of a file's chunks
        can be made in any order, on any thread, and then :meth:`fold`-ed in file order
        (a histogram's counts are order-free; the overflow count and the sync total are
        not, and the fold carries them)."""
        from stages.instruments.ptu import decode_records, histogram_records

        t = histogram_records(words, self.fmt, self.counts if counts is None else counts,
                              0, self.engine)
        # the chunk's last event (photon or marker; mostly its last record), decoded from
        # as few records at its end as it takes: the syncs it reaches past the chunk's
        # wraps (none when overflow records follow it, or the chunk holds no event)
        k, tail = 1, 0
        while True:
            end = decode_records(words[-k:], self.fmt, 0, self.engine)
            if len(end):
                tail = max(0, int(end.time[-1]) + 1 - end.wraps * self.fmt.wrap)
                break
            if k >= words.size:
                break
            k *= 64
        return T3Part(t, tail, words.size)

    def fold(self, part: T3Part) -> None:
        """Add the :meth:`part` of the next chunk of the file (in file order)."""
        t = part.tally
        # the sync periods: past the last event, or the last overflow record's wraps if
        # later (the same however the file is cut into chunks)
        self.wraps += t.wraps
        self.n_syncs = max(self.n_syncs, self.wraps * self.fmt.wrap + part.tail)
        self.words += part.words
        c = self.classes
        c["photons"] += t.n_photons - t.n_out_of_range
        c["out_of_range"] += t.n_out_of_range
        c["markers"] += t.n_markers
        c["overflow"] += t.n_overflow_records
        c["invalid"] += t.n_invalid

    def snapshot(self, copy: bool = True) -> InstrumentState:
        """The state now; ``copy=False`` shares the counts (for an accumulator that is
        done: a later update would change the state)."""
        return InstrumentState(self.counts.copy() if copy else self.counts, self.n_syncs,
                               self.words, dict(self.classes), PICOQUANT_T3,
                               self.bin_width_ps)

    def checkpoint(self) -> dict[str, np.ndarray]:
        return {"inst_counts": self.counts.copy(),
                "inst_position": np.array([self.wraps, self.n_syncs, self.words], np.int64),
                "inst_classes": np.array(list(self.classes.values()), np.int64)}

    def restore_checkpoint(self, state: dict) -> None:
        counts = np.asarray(state["inst_counts"], np.uint64)
        if counts.shape != self.counts.shape:
            raise ValueError(f"checkpoint counts {counts.shape} do not fit this file's "
                             f"{self.counts.shape}")
        self.counts = counts.copy()
        self.wraps, self.n_syncs, self.words = (int(x) for x in state["inst_position"])
        self.classes = dict(zip(self.classes, (int(x) for x in state["inst_classes"]),
                                strict=True))


class Linospad2Accumulator:
    """LinoSPAD2 raw words into fine-code counts per TDC or pixel.

    Any split of the stream is taken: the words of an incomplete cycle wait for the rest
    (``carry``); a run that ends inside a cycle counts them as ``partial_cycle``.
    """

    def __init__(self, firmware: str = "2212b", by: str = "tdc"):
        from stages.instruments.linospad2 import (
            CODE_PS,
            LINES,
            N_FINE,
            N_PIXEL,
            N_TDC,
            WORDS_PER_LINE,
            check_firmware,
        )

        self.firmware, self.by = check_firmware(firmware), by
        self.per_cycle = LINES * WORDS_PER_LINE
        self.shape = (N_TDC if by == "tdc" else N_PIXEL, N_FINE)
        self.bin_width_ps = float(CODE_PS)
        self.reset()

    def reset(self, keep_position: bool = True) -> None:
        self.counts = np.zeros(self.shape, np.uint64)
        self.classes = dict.fromkeys(("valid", "invalid", "line_65"), 0)
        self.cycles = 0
        self.words = 0
        self.carry = np.zeros(0, np.uint32)

    def update(self, words: np.ndarray, first: int = 0, seq=None) -> None:
        from stages.instruments.linospad2 import fine_histograms

        words = np.asarray(words, np.uint32)
        self.words += words.size
        if self.carry.size:
            words = np.concatenate([self.carry, words])
        whole = words.size - words.size % self.per_cycle
        self.carry = words[whole:].copy()
        if whole:
            counts, t = fine_histograms(words[:whole], self.firmware, self.by)
            self.counts += counts
            self.cycles += t.cycles
            c = self.classes
            c["valid"] += t.valid
            c["invalid"] += t.invalid
            c["line_65"] += t.line65

    def snapshot(self, copy: bool = True) -> InstrumentState:
        """The state now; ``copy=False`` as :meth:`PtuT3Accumulator.snapshot`."""
        classes = dict(self.classes)
        if self.carry.size:
            classes["partial_cycle"] = int(self.carry.size)
        return InstrumentState(self.counts.copy() if copy else self.counts, self.cycles,
                               self.words, classes, LINOSPAD2, self.bin_width_ps)

    def checkpoint(self) -> dict[str, np.ndarray]:
        return {"inst_counts": self.counts.copy(), "inst_carry": self.carry.copy(),
                "inst_position": np.array([self.cycles, self.words], np.int64),
                "inst_classes": np.array(list(self.classes.values()), np.int64)}

    def restore_checkpoint(self, state: dict) -> None:
        counts = np.asarray(state["inst_counts"], np.uint64)
        if counts.shape != self.shape:
            raise ValueError(f"checkpoint counts {counts.shape} are not {self.shape}")
        self.counts = counts.copy()
        self.carry = np.asarray(state["inst_carry"], np.uint32).copy()
        self.cycles, self.words = (int(x) for x in state["inst_position"])
        self.classes = dict(zip(self.classes, (int(x) for x in state["inst_classes"]),
                                strict=True))
