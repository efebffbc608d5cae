"""The sink's datasets as the page reads them: which runs there are, one measurement's
histograms and ranges, and the run's accounting identity.

The sink writes measurement k of a run, one file per histogram worker, as
``OUT/<schema>/date=D/run=RUN/part-<k:06d>-t<first TDC:03d>.parquet`` (renamed into place,
so a file seen is whole). A week-long run holds hundreds of thousands of them, so the page
never lists the directory once a second: :class:`RunIndex` lists it once, then looks for
the next measurements by name.
"""

from __future__ import annotations

import json
import os
import re
import stat
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pipeline.io.limits import read_bounded
from schemas.constants import WORD_CLASSES

PART = re.compile(r"part-(\d{6,})-t(\d{3,})\.parquet$")
#: A full listing of a run's directory this often (a measurement backfilled at the end of
#: the run, by reconciliation, lands behind the newest; ``rescan()`` asks for one sooner).
RESCAN_S = 300.0
#: Measurement numbers probed past a missing one.
LOOK_AHEAD = 8


def list_runs(out: str | Path) -> list[dict]:
    """Every run under ``OUT/histograms``, newest first: ``run``, ``date``, ``mtime``."""
    runs = {}
    for d in Path(out).glob("histograms/date=*/run=*"):
        if not d.is_dir():
            continue
        run, date = d.name[4:], d.parent.name[5:]
        mtime = d.stat().st_mtime
        if run not in runs or mtime > runs[run]["mtime"]:
            runs[run] = {"run": run, "date": date, "mtime": mtime}
    return sorted(runs.values(), key=lambda r: -r["mtime"])


@dataclass
class RunIndex:
    """The measurements of one run written so far (both schemas), kept up to date cheaply."""

    out: Path
    run: str
    n_tdc: int | None = None                      #: when known: the files must cover it
    dirs: dict = field(default_factory=dict)      #: schema -> its run directory
    firsts: list = field(default_factory=list)    #: first TDC of each worker's file
    have: dict = field(default_factory=dict)      #: schema -> sorted measurement numbers
    _scanned: float = 0.0

    def __post_init__(self):
        self.out = Path(self.out)
        self.have = {"histograms": [], "ranges": []}

    def refresh(self, now: float | None = None) -> list[int]:
        """New measurements (complete in the histograms dataset) since the last call."""
        now = time.time() if now is None else now
        before = set(self.have["histograms"])
        if now - self._scanned > RESCAN_S or not self.firsts:
            self._scanned = now
            self._scan()
        else:
            for schema in self.have:
                self._probe(schema)
        return sorted(set(self.have["histograms"]) - before)

    def _scan(self) -> None:
        for schema in self.have:
            found = sorted(Path(self.out).glob(f"{schema}/date=*/run={self.run}"))
            if not found:
                continue
            self.dirs[schema] = found[-1]
            ks: dict[int, set] = {}
            for p in found[-1].iterdir():
                m = PART.match(p.name)
                if m:
                    ks.setdefault(int(m.group(1)), set()).add(int(m.group(2)))
            if schema == "histograms" and ks:
                self.firsts = sorted(set().union(*ks.values()))
                if not self._covers(max(ks)):
                    self.firsts = []  # a worker's first file not written yet: look again
                    self._scanned = 0.0
            self.have[schema] = sorted(k for k, f in ks.items()
                                       if self.firsts and f >= set(self.firsts))

    def rescan(self) -> None:
        """List the directory again at the next refresh (the run ended: backfilled files)."""
        self._scanned = 0.0

    def _covers(self, k: int) -> bool:
        """The workers' files of measurement ``k`` tile TDCs 0..n_tdc-1 with no hole."""
        import pyarrow.parquet as pq

        end = 0
        for f in self.firsts:
            p = self.path("histograms", k, f)
            if f != end or not _part_ok(p):
                return False
            end = f + pq.read_metadata(p).num_rows
        return self.n_tdc is None or end == self.n_tdc

    def _probe(self, schema: str) -> None:
        """The measurements after the newest known, by name; past a missing one (lost in
        flight with a killed stage, written again at the run's end) up to LOOK_AHEAD."""
        if self.dirs.get(schema) is None:
            return
        k = (self.have[schema][-1] + 1) if self.have[schema] else 0
        misses = 0
        while misses <= LOOK_AHEAD:
            if all(_part_ok(self.path(schema, k, f)) for f in self.firsts):
                self.have[schema].append(k)
                misses = 0
            else:
                misses += 1
            k += 1

    def path(self, schema: str, k: int, first: int) -> Path:
        return self.dirs[schema] / f"part-{k:06d}-t{first:03d}.parquet"

    def files(self, schema: str, k: int) -> list[Path]:
        if schema not in self.dirs:
            return []
        return [p for f in self.firsts if _part_ok(p := self.path(schema, k, f))]

    @property
    def latest(self) -> int | None:
        return self.have["histograms"][-1] if self.have["histograms"] else None


#: the largest dataset part the page reads (a sink's part is a measurement of one worker's
#: TDCs: KiB to a few MiB); a bigger one, or a FIFO or device, is not read
MAX_PART_BYTES = 1 << 28


def _part_ok(p: Path) -> bool:
    """A regular file (no link, no FIFO that would block the server for every viewer) of at
    most MAX_PART_BYTES."""
    import stat

    try:
        st = os.lstat(p)
    except OSError:
        return False
    return stat.S_ISREG(st.st_mode) and st.st_size <= MAX_PART_BYTES


@dataclass(frozen=True)
class Measurement:
    """One measurement's histograms, every TDC the workers wrote, ordered by TDC."""

    run: str
    k: int
    name: str
    tdc: np.ndarray       #: (n,)
    cycles: np.ndarray    #: (n,)
    counts: np.ndarray    #: (n, 512)
    classes: dict         #: word class -> (n,) counts
    groups: tuple         #: (first TDC, TDCs) of each worker's file (its calibration rows)

    @property
    def words(self) -> int:
        """Words of this measurement: one per TDC per cycle."""
        return int(self.cycles.sum())

    @property
    def classified(self) -> int:
        return int(sum(int(v.sum()) for v in self.classes.values()))


def read_measurement(index: RunIndex, k: int) -> Measurement | None:
    """Measurement ``k``'s histograms (None when its files are not all there)."""
    import pyarrow.parquet as pq

    files = index.files("histograms", k)
    if not files or len(files) < len(index.firsts):
        return None
    tables = [pq.read_table(p, use_threads=False) for p in files]
    groups = tuple((int(t["tdc"][0].as_py()), t.num_rows) for t in tables if t.num_rows)
    import pyarrow as pa

    t = pa.concat_tables(tables).sort_by("tdc")
    counts = np.asarray(t["counts"].combine_chunks().flatten().to_numpy(), np.int64)
    n = t.num_rows
    return Measurement(index.run, k, str(t["measurement"][0].as_py()) if n else "",
                       t["tdc"].to_numpy().astype(np.int64), t["cycles"].to_numpy(),
                       counts.reshape(n, -1),
                       {c: t[f"n_{c}"].to_numpy() for c in WORD_CLASSES}, groups)


def read_ranges(index: RunIndex, k: int):
    """Measurement ``k``'s ranges as a Polars frame ordered by TDC, each TDC's strongest
    return (None when not written: a run without a range stage, or not yet)."""
    import polars as pl
    import pyarrow as pa
    import pyarrow.parquet as pq

    files = index.files("ranges", k)
    if not files:
        return None
    # (pyarrow reads a small file in ~1 ms; polars' reader costs ~50 ms a call here)
    tables = [pq.read_table(p, use_threads=False) for p in files]
    df = pl.from_arrow(pa.concat_tables(tables, promote_options="permissive"))
    if "return_index" in df.columns:  # ranges 2.0: a row per return (1.0: none, all row 0)
        df = df.filter(pl.col("return_index").fill_null(0) == 0)
    return df.sort("tdc")


# ---------------------------------------------------------------- the accounting identity

@dataclass
class Tally:
    """Word classes summed over a run's measurements as they are written (each file read
    once), and the journal's word count read the same way (new index lines only)."""

    classes: dict = field(default_factory=lambda: dict.fromkeys(WORD_CLASSES, 0))
    words: int = 0              #: sum of cycles over TDCs: words in written measurements
    counted: set = field(default_factory=set)
    rows_off: int = 0           #: rows whose classes do not add up to their cycles
    journaled: int = 0
    journal_end: int | None = None
    _offset: int = 0

    def add(self, index: RunIndex, ks, budget_s: float = 0.02) -> int:
        """Count measurements ``ks`` not yet counted, for about ``budget_s`` (a fast
        replay, or a long run opened late, is caught up over the next refreshes: the page
        stays responsive and the data path keeps its CPU); returns how many are left."""
        import pyarrow.parquet as pq

        todo = [k for k in ks if k not in self.counted]
        cols = ["cycles", *(f"n_{c}" for c in WORD_CLASSES)]
        t0, done = time.perf_counter(), 0
        for k in todo:
            if time.perf_counter() - t0 > budget_s:
                break
            done += 1
            for p in index.files("histograms", k):
                t = pq.read_table(p, columns=cols, use_threads=False)
                cyc = t["cycles"].to_numpy().astype(np.int64)
                per = sum(t[f"n_{c}"].to_numpy().astype(np.int64) for c in WORD_CLASSES)
                self.rows_off += int((per != cyc).sum())
                self.words += int(cyc.sum())
                for c in WORD_CLASSES:
                    self.classes[c] += int(t[f"n_{c}"].to_numpy().sum())
            self.counted.add(k)
        return len(todo) - done

    def read_journal(self, journal: Path, run: str) -> None:
        """Words journaled so far (the new lines of ``RUN.index.jsonl`` only)."""
        path = Path(journal) / f"{run}.index.jsonl"
        try:
            # (a regular file only, read in bounded steps: a FIFO would block the server)
            fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_NOFOLLOW)
            with os.fdopen(fd, "rb") as fh:
                if not stat.S_ISREG(os.fstat(fd).st_mode):
                    return
                fh.seek(self._offset)
                data = fh.read(MAX_PART_BYTES)
        except OSError:
            return
        end = data.rfind(b"\n") + 1  # a line being written is read next time
        for line in data[:end].splitlines():
            try:
                e = json.loads(line)
            except ValueError:
                continue
            if e.get("end"):
                self.journal_end = int(e.get("words", 0))
            elif e.get("reopen"):  # an earlier stop's end: the run went on
                self.journal_end = None
            else:
                self.journaled += int(e.get("words", 0))
        self._offset += end

    @property
    def classified(self) -> int:
        return sum(self.classes.values())


def read_accounting(out: str | Path, run: str) -> dict | None:
    """``OUT/accounting/run=RUN.json``, written when the run ended (None before)."""
    try:
        # (a week-long run's lists of rebuilt parts can pass 1 MiB: 64 MiB at most)
        return json.loads(read_bounded(Path(out) / "accounting" / f"run={run}.json", 64 << 20))
    except (OSError, ValueError):
        return None


def identity(tally: Tally, accounting: dict | None, left: int = 0) -> dict:
    """journaled = hit + no_hit + artifact + invalid_phase + malformed, as the page says it.

    ``holds``: True / False, or None while the run is going (words still in flight are in
    no written measurement yet). At the end the run's accounting decides (it adds the words
    a damaged journal chunk withheld)."""
    if accounting is not None:
        classes = accounting.get("classes", {})
        return {"final": True, "journaled": int(accounting.get("words_in", 0)),
                "classes": classes, "classified": int(accounting.get("classified", 0)),
                "withheld": int(accounting.get("withheld", 0)),
                "in_flight": 0, "holds": bool(accounting.get("balanced")),
                "rows_off": tally.rows_off, "left": 0}
    in_flight = tally.journaled - tally.classified
    holds = False if tally.rows_off else None
    return {"final": False, "journaled": tally.journaled, "classes": dict(tally.classes),
            "classified": tally.classified, "withheld": 0, "in_flight": in_flight,
            "holds": holds, "rows_off": tally.rows_off, "left": left,
            "measurement_words": tally.words}
