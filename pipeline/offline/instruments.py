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

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
from scipy.constants import c as C_LIGHT

from pipeline.io.atomic import atomic_path
from pipeline.io.formats import FormatError
from schemas.outputs import HISTOGRAMS
from stages.ranging import Histograms, estimate

PICOQUANT_T3 = "picoquant-t3"
LINOSPAD2 = "linospad2"
_CLASS_COLUMNS = ("n_no_hit", "n_artifact", "n_invalid_phase", "n_malformed")


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
            out.append("warning: the file is truncated; the records before the damage were "
                       "kept")
        return out + self.notes


def instrument_table(measurement: str, counts: np.ndarray, cycles, instrument: str,
                     bin_width_ps: float | None, rows=None) -> pa.Table:
    """``histograms`` 2.0 rows of an instrument: ``counts`` (n_rows, n_codes) uint64,
    ``cycles`` per row (or one for all), ``rows`` the ``tdc`` value of each row."""
    counts = np.ascontiguousarray(counts, np.uint64)
    n, k = counts.shape
    rows = np.arange(n) if rows is None else np.asarray(rows)
    cols = {
        "measurement": pa.array([measurement] * n, pa.string()),
        "tdc": pa.array(rows.astype(np.uint16)),
        "cycles": pa.array(np.broadcast_to(np.asarray(cycles, np.uint64), (n,)).copy()),
        "counts": pa.ListArray.from_arrays(pa.array(np.arange(n + 1, dtype=np.int32) * k),
                                           pa.array(counts.ravel())),
        "n_hit": pa.array(counts.sum(axis=1, dtype=np.uint64)),
        **{c: pa.array(np.zeros(n, np.uint64)) for c in _CLASS_COLUMNS},
        "instrument": pa.array([instrument] * n, pa.string()),
        "bin_width_ps": pa.array([bin_width_ps] * n, pa.float64()),
    }
    return pa.Table.from_pydict(cols, schema=HISTOGRAMS.schema)


def histogram_ptu(path: str | Path, measurement: str | None = None,
                  chunk_records: int = 1 << 22) -> tuple[pa.Table, FileSummary]:
    """A PTU T3 file's histograms: a row per input channel, counts per dtime code (up to
    the last code any channel used: nothing is dropped), ``cycles`` the sync periods."""
    from pipeline.io.ptu import histogram_t3, read_header

    t0 = time.perf_counter()
    header = read_header(path)
    if header.format.mode != "T3":
        raise FormatError(f"{path}: {header.format.name} holds T2 records (absolute times, "
                          "no start-stop time to histogram); `tcspc decode` gives its photons")
    counts, header, tally, truncated = histogram_t3(path, chunk_records=chunk_records)
    used = int(np.flatnonzero(counts.any(axis=0))[-1]) + 1 if counts.any() else 1
    table = instrument_table(measurement or Path(path).stem, counts[:, :used],
                             tally.n_syncs, PICOQUANT_T3, header.resolution_s * 1e12)
    summary = _ptu_summary(path, tally, truncated, time.perf_counter() - t0)
    summary.notes.append(f"{header.format.name}: {counts.shape[0]} channels x {used} dtime "
                         f"codes of {header.resolution_s * 1e12:g} ps, "
                         f"{tally.n_syncs:,} sync periods")
    return table, summary


def _ptu_summary(path, tally, truncated: bool, seconds: float) -> FileSummary:
    return FileSummary(str(path), "ptu", tally.n_records, tally.n_photons,
                       {"markers": tally.n_markers, "overflow": tally.n_overflow_records,
                        "invalid": tally.n_invalid, "out_of_range": tally.n_out_of_range},
                       truncated, seconds=seconds)


def histogram_linospad2(path: str | Path, firmware: str = "2212b", by: str = "tdc",
                        measurement: str | None = None) -> tuple[pa.Table, FileSummary]:
    """A LinoSPAD2 file's fine-code histograms, a row per TDC (64) or pixel (256)."""
    from stages.instruments.linospad2 import CODE_PS

    from pipeline.io.linospad2 import histogram_file

    t0 = time.perf_counter()
    counts, tally = histogram_file(path, firmware, by)
    table = instrument_table(measurement or Path(path).stem, counts, tally.cycles,
                             LINOSPAD2, CODE_PS)
    summary = FileSummary(str(path), "linospad2", tally.words, tally.valid,
                          {"invalid": tally.invalid, "line_65": tally.line65},
                          tally.truncated, seconds=time.perf_counter() - t0)
    summary.notes.append(f"firmware {firmware}: {counts.shape[0]} {by}s x {counts.shape[1]} "
                         f"fine codes, {tally.cycles:,} cycles")
    return table, summary


def write_instrument_histograms(table: pa.Table, out: str | Path, source: str | Path,
                                summary: FileSummary) -> None:
    from pipeline.io.histograms import write_histogram_table

    write_histogram_table(table, out, {"source": source, "format": summary.format,
                                       "truncated": summary.truncated})


def decode_instrument(path: str | Path, fmt: str, out: str | Path,
                      firmware: str = "2212b") -> FileSummary:
    """Decode a PTU or LinoSPAD2 file into its events dataset, streaming, atomically."""
    t0 = time.perf_counter()
    if fmt == "ptu":
        from pipeline.io.ptu import iter_decoded_batches

        batches = iter_decoded_batches(path)
    elif fmt == "linospad2":
        from pipeline.io.linospad2 import iter_decoded_batches as lino_batches

        batches = lino_batches(path, firmware)
    else:
        raise FormatError(f"decode_instrument: {fmt!r} is not an instrument format")
    writer = None
    with atomic_path(out) as tmp:
        try:
            for batch in batches:
                if writer is None:
                    writer = pq.ParquetWriter(tmp, batch.schema)
                writer.write_batch(batch)
            summary = batches.summary() if hasattr(batches, "summary") else None
        finally:
            if writer is not None:
                writer.close()
    if summary is None:
        raise FormatError(f"{path}: the reader gave no accounting")
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
    return Histograms(counts, edges, cycles, valid)


def peak_times(table: pa.Table, sigma_s: float | None = None, estimator: str = "ml",
               p_fa: float = 1e-3, gate_ns=None):
    """The return time after the sync, per row, with the instrument response ``sigma_s``
    (default: one bin)."""
    h = _uniform(table, gate_ns)
    sigma = float(h.bin_s) if sigma_s is None else float(sigma_s)
    return estimate(h, sigma, estimator, p_fa), sigma


def measured_delay(zero: pa.Table, sigma_s: float | None = None, estimator: str = "ml",
                   p_fa: float = 1e-3, gate_ns=None) -> tuple[np.ndarray, np.ndarray]:
    """Delay per row from a zero-distance measurement (eq. 5.3 with d = 0): the return
    time there; NaN where nothing was detected. Also the peak's sigma (from its FWHM)."""
    est, _ = peak_times(zero, sigma_s, estimator, p_fa, gate_ns)
    delay = np.where(est.detected, est.t_s, np.nan)
    return delay, np.asarray(est.fwhm_s, np.float64) / (2 * np.sqrt(2 * np.log(2)))


def range_uniform(table: pa.Table, delay_s, sigma_s: float | None = None,
                  estimator: str = "ml", p_fa: float = 1e-3, gate_ns=None):
    """Distances of an instrument's T3 histograms: d = c (t - delay) / 2, per row.

    Returns (estimate, distance_m, sigma_m, note); a row without a delay (NaN) is not
    detected.
    """
    est, sigma = peak_times(table, sigma_s, estimator, p_fa, gate_ns)
    delay = np.broadcast_to(np.asarray(delay_s, np.float64), est.t_s.shape)
    est = dataclasses.replace(est, detected=np.asarray(est.detected, bool) & np.isfinite(delay))
    distance = C_LIGHT / 2 * (est.t_s - delay)
    width = float(np.nanmedian(table.column("bin_width_ps").to_numpy()))
    note = (f"uniform time axis of {width:g} ps bins (the instrument's own calibration; no "
            f"INL applied), instrument response sigma {sigma * 1e12:.1f} ps")
    return est, distance, est.sigma_s * C_LIGHT / 2, note
