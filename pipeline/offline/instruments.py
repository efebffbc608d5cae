"""Real instruments' files through the offline commands: histogram, decode and range of a
PicoQuant PTU file or a LinoSPAD2 raw capture (the readers are ``pipeline.io.ptu`` and
``pipeline.io.linospad2``; the decoders ``stages.instruments``).

An instrument's histograms are ``histograms`` 2.0 rows with its own code count and bin
width (``instrument``, ``bin_width_ps``). A PicoQuant board is calibrated by its maker: its
dtime bins are uniform, so ranging needs no INL, only the delay (given, or measured on a
zero-distance file), which :func:`range_uniform` says in its note.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.io.atomic import atomic_path
from pipeline.io.formats import FormatError
from pipeline.offline.threads import default_threads
from stages.instruments.accumulate import (
    LINOSPAD2,
    PICOQUANT_T3,
    Linospad2Accumulator,
    PtuT3Accumulator,
    column,
    instrument_table,
)

if TYPE_CHECKING:  # (ranging imports scipy.special: 0.3-1 s a histogram or decode never needs)
    from stages.ranging import Histograms

#: m/s, exact (SI); scipy.constants' import costs 0.1-0.5 s on a command's start
C_LIGHT = 299_792_458.0

__all__ = ["LINOSPAD2", "PICOQUANT_T3", "FileSummary", "decode_instrument",
           "histogram_linospad2", "histogram_ptu", "instrument_accumulator",
           "instrument_table", "measured_delay", "range_uniform", "truncation",
           "zero_response"]


@dataclass
class FileSummary:
    """What a pass over an instrument's file found: every record accounted for."""

    path: str
    format: str
    records: int = 0                   #: records (PTU) or words (LinoSPAD2) read
    events: int = 0                    #: photons (PTU) or valid pixel words (LinoSPAD2)
    counted: dict[str, int] = field(default_factory=dict)  #: the other classes, by name
    truncated: bool = False            #: the file ended early (what was read is kept)
    notes: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def accounted(self) -> int:
        return self.events + sum(self.counted.values())

    def lines(self) -> list[str]:
        rate = self.records / max(self.seconds, 1e-9) / 1e6
        parts = [f"{self.events:,} events"] + [f"{v:,} {k}" for k, v in self.counted.items()]
        out = [f"{self.path} ({self.format}): {self.records:,} records in {self.seconds:.2f} s "
               f"({rate:.1f} M records/s): " + ", ".join(parts)]
        if self.truncated:
            out.append("warning: the records before the damage were kept (the output is "
                       "flagged tcspc.truncated=True in its metadata)")
        return out + self.notes


def instrument_accumulator(path: str | Path, fmt: str, firmware: str = "2212b",
                           by: str = "tdc", header=None):
    """The accumulator an instrument's file is histogrammed with, live and offline: a PTU
    T3 file's record format, resolution and input channels from its header (``header``,
    read here unless given)."""
    if fmt == "ptu":
        from pipeline.io.ptu import read_header

        header = header if header is not None else read_header(path)
        if header.format.mode != "T3":
            raise FormatError(f"{path}: {header.format.name} holds T2 records (absolute "
                              "times, no start-stop time to histogram); `tcspc decode` "
                              "gives its photons")
        return PtuT3Accumulator(header.format, header.resolution_s, header.n_input_channels)
    if fmt == "linospad2":
        if by not in ("tdc", "pixel"):
            raise FormatError(f"--by must be tdc or pixel, found {by!r}")
        return Linospad2Accumulator(firmware, by)
    raise FormatError(f"{path}: {fmt!r} is not an instrument format")


def _fold_file(path, fmt: str, acc, measurement: str | None, chunk_words: int,
               threads: int = 1, header=None):
    from pipeline.io.formats import instrument_truncation, instrument_words

    t0 = time.perf_counter()
    if fmt == "ptu":
        fold_ptu(path, acc, chunk_words, threads, header)
    else:
        for first, words in instrument_words(path, fmt, chunk_words):
            acc.update(words, first)
    state = acc.snapshot(copy=False)  # (acc ends here: its counts need no copy)
    table = state.to_table(measurement or Path(path).stem)
    classes = state.totals()
    events = classes.pop("photons" if fmt == "ptu" else "valid")
    damage = header.truncation if header is not None else instrument_truncation(path, fmt)
    summary = FileSummary(str(path), fmt, state.words, events, classes, bool(damage),
                          seconds=time.perf_counter() - t0)
    if damage:
        summary.notes.append(f"warning: {damage}")
    return table, state, summary


def fold_ptu(path: str | Path, acc: PtuT3Accumulator, chunk_records: int,
             threads: int, header=None) -> None:
    """Fold a PTU T3 file's records into ``acc`` on ``threads`` threads: each reads a chunk
    into its own buffer and histograms it into its own counts (the compiled loop runs
    without the GIL, and one thread's read overlaps the others' loops); the chunks' parts
    are folded into ``acc`` in file order, so the overflow count and the sync total are
    what one pass gives, and the counts (order-free) are summed at the end. A file of
    one chunk, or one thread, is read and folded in one pass. ``header``: the file's, read
    here unless given."""
    from pipeline.io.ptu import iter_chunks, read_header

    header = header if header is not None else read_header(path)
    n = header.n_readable
    if threads < 2 or n <= chunk_records:
        for first, words in iter_chunks(path, chunk_records, header):
            acc.update(words, first)
        return
    import queue
    from concurrent.futures import ThreadPoolExecutor
    from contextlib import ExitStack

    from pipeline.io.buffers import aligned_empty
    from pipeline.io.ptu import read_records

    threads = min(threads, -(-n // chunk_records))
    size = min(chunk_records, n)
    lanes: queue.SimpleQueue = queue.SimpleQueue()
    with ExitStack() as stack:
        own = []  # the counts of every lane but the first, which adds into acc's own
        for i in range(threads):
            counts = acc.counts if i == 0 else np.zeros_like(acc.counts)
            own += [counts] if i else []
            lanes.put((stack.enter_context(open(path, "rb", buffering=0)),
                       aligned_empty(size, "<u4"), counts))

        def part(first: int):
            fh, buf, counts = lanes.get()  # one never waits: at most `threads` run at once
            try:
                words = read_records(fh, header, first, buf[:min(chunk_records, n - first)])
                return acc.part(words, counts)
            finally:
                lanes.put((fh, buf, counts))

        pool = stack.enter_context(ThreadPoolExecutor(threads, "ptu-histogram"))
        last = -1  # the largest dtime of any photon: no count lies past it
        try:
            for p in pool.map(part, range(0, n, chunk_records)):  # (in file order)
                acc.fold(p)
                last = max(last, p.tally.max_dtime)
        except BaseException:
            pool.shutdown(cancel_futures=True)
            raise
    for counts in own:  # (the used codes only: a format has up to 32768, mostly unused)
        acc.counts[:, :last + 1] += counts[:, :last + 1]


def histogram_ptu(path: str | Path, measurement: str | None = None,
                  chunk_records: int = 1 << 20,
                  threads: int | None = None) -> tuple[pa.Table, FileSummary]:
    """A PTU T3 file's histograms: a row per input channel, counts per dtime code (up to
    the last code any channel used: nothing is dropped), ``cycles`` the sync periods.
    ``threads`` (default: ``pipeline.offline.threads.default_threads`` with the compiled
    loops, 1 with the numpy engine, which holds the GIL) share the chunks; the result is
    the same for any number."""
    from pipeline.io.ptu import read_header

    header = read_header(path)  # (once: its tags are parsed in Python)
    acc = instrument_accumulator(path, "ptu", header=header)
    if threads is None:
        from stages.instruments.ptu import default_engine

        threads = default_threads() if (acc.engine or default_engine()) == "numba" else 1
    table, state, summary = _fold_file(path, "ptu", acc, measurement, chunk_records,
                                       threads, header)
    summary.notes.append(f"{acc.fmt.name}: {table.num_rows} channels x "
                         f"{len(table.column('counts')[0]) if table.num_rows else 0} dtime "
                         f"codes of {acc.bin_width_ps:g} ps, {state.n_cycles:,} sync periods")
    return table, summary


def histogram_linospad2(path: str | Path, firmware: str = "2212b", by: str = "tdc",
                        measurement: str | None = None) -> tuple[pa.Table, FileSummary]:
    """A LinoSPAD2 file's fine-code histograms, a row per TDC (64) or pixel (256)."""
    acc = instrument_accumulator(path, "linospad2", firmware, by)
    table, state, summary = _fold_file(path, "linospad2", acc, measurement, 1 << 20)
    summary.notes.append(f"firmware {firmware}: {table.num_rows} {by}s x 140 fine codes, "
                         f"{state.n_cycles:,} cycles")
    return table, summary


def write_instrument_histograms(table: pa.Table, out: str | Path, source: str | Path,
                                summary: FileSummary) -> None:
    from pipeline.io.histograms import write_histogram_table

    write_histogram_table(table, out, {"source": source, "format": summary.format,
                                       "truncated": summary.truncated})


def decode_instrument(path: str | Path, fmt: str, out: str | Path,
                      firmware: str = "2212b") -> FileSummary:
    """Decode a PTU or LinoSPAD2 file into its events dataset (``ptu_t2_events``,
    ``ptu_t3_events`` or ``linospad2_events``), streaming in bounded memory, atomically;
    every record accounted for in the returned summary."""
    from pipeline.io.formats import instrument_truncation, instrument_words
    from schemas.instruments import LINOSPAD2_EVENTS, PTU_T2_EVENTS, PTU_T3_EVENTS

    t0 = time.perf_counter()
    if fmt == "ptu":
        from pipeline.io.ptu import DecodeReport, iter_decoded_batches, read_header

        report, header = DecodeReport(), read_header(path)
        damage = header.truncation
        spec = PTU_T3_EVENTS if header.format.is_t3 else PTU_T2_EVENTS
        batches = iter_decoded_batches(path, report=report, header=header)
    elif fmt == "linospad2":
        damage = instrument_truncation(path, fmt)
        from stages.instruments.linospad2 import LINES, WORDS_PER_LINE, decode_words

        spec, tally = LINOSPAD2_EVENTS, {"valid": 0, "invalid": 0, "line_65": 0, "words": 0}
        per_cycle = LINES * WORDS_PER_LINE

        def lino():
            for first, words in instrument_words(path, fmt, 1 << 20):
                whole = words.size - words.size % per_cycle
                tally["words"] += words.size
                tally["partial_cycle"] = words.size - whole
                d = decode_words(words[:whole], firmware, first_cycle=first // per_cycle)
                for k, v in (("valid", d.tally.valid), ("invalid", d.tally.invalid),
                             ("line_65", d.tally.line65)):
                    tally[k] += v
                cols = d.columns()
                yield pa.RecordBatch.from_arrays(
                    [column(cols[f.name], f.type) for f in spec.schema], schema=spec.schema)
        batches = lino()
    else:
        raise FormatError(f"decode_instrument: {fmt!r} is not an instrument format")
    schema = spec.schema
    if damage:  # flagged as the histograms are (tcspc.truncated), with the account
        schema = schema.with_metadata({**(schema.metadata or {}), b"tcspc.truncated": b"True",
                                       b"tcspc.truncation": damage.encode()})
    # dictionary pages for the narrow columns only (kind, channel, dtime; tdc, pixel, fine):
    # a wide one (a time, a code) has too many values, and the writer tries a dictionary
    # and drops it page after page. The write takes half (PTU) to a third (LinoSPAD2) of
    # the time, and the file is 10-25 % smaller; the data read back are the same.
    narrow = [f.name for f in schema if f.type.bit_width < 32]
    with atomic_path(out) as tmp, pq.ParquetWriter(tmp, schema,
                                                   use_dictionary=narrow) as writer:
        for batch in batches:
            writer.write_batch(batch.replace_schema_metadata(schema.metadata))
    if fmt == "ptu":
        summary = FileSummary(str(path), fmt, report.n_records_read,
                              report.n_photons + report.n_sync,
                              {"markers": report.n_markers,
                               "overflow": report.n_overflow_records,
                               "invalid": report.n_invalid}, bool(damage))
        if report.n_sync:
            summary.notes.append(f"{report.n_sync:,} of the events are sync events (T2: "
                                 "kept as photons of the sync channel)")
    else:
        summary = FileSummary(str(path), fmt, tally.pop("words"), tally.pop("valid"), tally,
                              bool(damage))
    if damage:
        summary.notes.append(f"warning: {damage}")
    summary.seconds = time.perf_counter() - t0
    return summary


def _uniform(table: pa.Table, gate_ns: tuple[float, float] | None) -> Histograms:
    """Histograms on the instrument's own uniform time axis (no INL: its maker calibrated
    it), bins outside ``gate_ns`` masked."""
    inst = set(table.column("instrument").to_pylist())
    if inst != {PICOQUANT_T3}:
        raise FormatError(f"range takes PicoQuant T3 histograms (dtime after each sync), "
                          f"found {sorted(inst)}: a LinoSPAD2 fine-code histogram is not a "
                          "time-of-flight histogram")
    counts = np.stack(table.column("counts").to_numpy(zero_copy_only=False)).astype(np.float64)
    width_s = np.asarray(table.column("bin_width_ps").to_numpy(), np.float64) * 1e-12
    k = np.arange(counts.shape[1] + 1)
    edges = width_s[:, None] * k[None, :]
    valid = np.ones(counts.shape, bool)
    if gate_ns is not None:
        mid = 0.5 * (edges[:, 1:] + edges[:, :-1])
        valid &= (mid >= gate_ns[0] * 1e-9) & (mid <= gate_ns[1] * 1e-9)
    cycles = np.asarray(table.column("cycles").to_numpy(), np.float64)
    from stages.ranging import Histograms

    return Histograms(counts, edges, cycles, valid)


def truncation(path, table: pa.Table, summary: FileSummary | None) -> str | None:
    """What a file cut short holds, in a line (None: whole): a PTU file's ``summary``, or
    a histograms ``table`` flagged ``tcspc.truncated`` by the command that wrote it. Its
    ranges would come from part of a measurement: `range` and the batch flow refuse it
    unless told."""
    if summary is not None:
        return (f"{path} is truncated: its {summary.records:,} whole records before the "
                "damage") if summary.truncated else None
    if (table.schema.metadata or {}).get(b"tcspc.truncated") == b"True":
        return f"{path} is flagged truncated (histograms of a file cut short)"
    return None


def peak_times(table: pa.Table, sigma_s: float | None = None, estimator: str = "ml",
               p_fa: float = 1e-3, gate_ns=None, max_returns: int = 1, response=None):
    """The return times after the sync, per row (up to ``max_returns`` each), with the
    instrument response ``sigma_s`` (default: measured on the returns,
    :func:`stages.ranging.width.response_from_data`). A measured ``response``
    (:func:`zero_response`) is the model of each return found when searching for the
    next (its tail included); without one further returns are searched with Gaussian
    tails, which a real response's long tail is not."""
    from stages.ranging import estimate_returns, response_from_data

    h = _uniform(table, gate_ns)
    sigma = response_from_data(h)[0] if sigma_s is None else float(sigma_s)
    return estimate_returns(h, sigma, estimator, p_fa, max_returns,
                            response=response if max_returns > 1 else None), sigma


def zero_response(zero: pa.Table, delay_s, source: str, gate_ns=None):
    """The instrument's response measured on a zero-distance (or any single-target) file:
    its channels' returns at ``delay_s`` (NaN: not detected, left out), pile-up corrected,
    aligned and averaged, tail included (:func:`stages.ranging.irf.response_from_returns`).
    None when no channel has a return."""
    from stages.ranging.irf import response_from_returns

    t = np.asarray(delay_s, np.float64)
    if not np.isfinite(t).any():
        return None
    n = int(np.isfinite(t).sum())
    return response_from_returns(_uniform(zero, gate_ns), t,
                                 f"{source}'s {n} return(s), aligned and averaged")


def measured_delay(zero: pa.Table, sigma_s: float | None = None, estimator: str = "ml",
                   p_fa: float = 1e-3, gate_ns=None) -> tuple[np.ndarray, np.ndarray]:
    """Delay per row from a zero-distance measurement (eq. 5.3 with d = 0): the return
    time there; NaN where nothing was detected. Also, per row, the instrument sigma the
    delay was estimated with (``sigma_s``, else measured on the zero's returns), which the
    ranges must use too: an estimator's time of an asymmetric return moves with the model's
    width (the HydraHarp sample ranged against itself with its returns' FWHM in place of
    the delay's sigma came out 2.07 m away, not at 0)."""
    est, sigma = peak_times(zero, sigma_s, estimator, p_fa, gate_ns)
    delay = np.where(est.detected, est.t_s, np.nan)
    return delay, np.full(delay.shape, float(sigma))


def range_uniform(table: pa.Table, delay_s, sigma_s: float | None = None,
                  estimator: str = "ml", p_fa: float = 1e-3, gate_ns=None,
                  max_returns: int = 1, response=None):
    """Distances of an instrument's T3 histograms: d = c (t - delay) / 2, per row and
    return (``est.pixel``, ``est.return_index``).

    Returns (estimate, distance_m, sigma_m, note); a row without a delay (NaN) is not
    detected, a return before the zero is flagged and not detected.
    """
    from pipeline.offline.ranging import behind_zero
    from stages.ranging.validation import check_delay

    est, sigma = peak_times(table, sigma_s, estimator, p_fa, gate_ns, max_returns, response)
    delay = np.broadcast_to(check_delay(delay_s, "the delay"), (table.num_rows,))[est.pixel]
    est = dataclasses.replace(est, detected=np.asarray(est.detected, bool) & np.isfinite(delay))
    est, distance = behind_zero(est, C_LIGHT / 2 * (est.t_s - delay))
    width = float(np.nanmedian(table.column("bin_width_ps").to_numpy()))
    note = (f"uniform time axis of {width:g} ps bins (the instrument's own calibration; no "
            f"INL applied), instrument response sigma {sigma * 1e12:.1f} ps"
            + (" (measured on the returns)" if sigma_s is None else ""))
    return est, distance, est.sigma_s * C_LIGHT / 2, note
