"""The end of a daemon's run: the datasets reconciled with the journal (a measurement lost
in flight with a killed range or sink stage is recomputed from the journaled words: the
same code, the same numbers) and the run's accounting (words journaled = hit + no_hit +
artifact + invalid_phase + malformed, rejections by reason, corrupt and withheld words)."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline.stream.topology import Topology, spatial_geometry, tdc_ranges


def _dataset_parts(out: Path, schema: str, run: str) -> dict[tuple[int, int], Path]:
    parts = {}
    for p in out.glob(f"{schema}/date=*/run={run}/part-*.parquet"):
        _, k, t = p.stem.split("-")
        parts[(int(k), int(t[1:]))] = p
    return parts


def reconcile(topo: Topology) -> dict:
    """Recompute from the journal every (measurement, TDC range) the datasets lack; a
    measurement is words [k M N, (k + 1) M N) of the run whatever happened to the stream,
    so the recomputed one is the one an uninterrupted run would have written."""
    from pipeline.stream.bounds import histogram_bounds
    from pipeline.stream.fanout import worker_reader
    from pipeline.stream.journal import pruned_words, read_range, run_end
    from pipeline.stream.stage import ParquetSink
    from stages.stream import HistogramCore

    journal = topo.state / "journal"
    total = run_end(journal, topo.run)
    if total is None:
        return {"checked": False, "why": "the journal has no end (the source did not finish)"}
    n = topo.n_tdc
    cycles = total // n
    mc = topo.histogram.get("measurement_cycles") or max(cycles, 1)
    n_meas = max(1, -(-cycles // mc))
    by_m = topo.histogram.get("measurement_cycles") is not None  # (parts' names: stages.stream)
    out = Path(topo.sink["out"])
    have_h = _dataset_parts(out, "histograms", topo.run)
    have_r = _dataset_parts(out, "ranges", topo.run) if topo.range else None
    bounds_all = histogram_bounds(topo)  # the live workers' (calibration or estimated)
    ranger = None
    if topo.range:
        from pipeline.io.caldir import load_calibration
        from pipeline.io.geometry import load_geometry
        from pipeline.offline.ranging import RangeCore

        geom = spatial_geometry(topo)
        ranger = RangeCore(load_calibration(topo.range["calibration"]),
                           topo.range.get("estimator", "ml"),
                           max_returns=topo.range.get("max_returns", 3),
                           spatial=load_geometry(geom) if geom else None)
    sink = ParquetSink(out)
    redone, unrecoverable, corrupt_meas, rebuilt = [], [], [], []
    corrupt_chunks: dict[int, list] = {}  # first word -> [first, words, reason]
    withheld = 0
    window_ns = None
    spans = _journal_spans(journal, topo.run)
    check = topo.source.get("kind") != "file"  # (an instrument's records are not words)

    def recompute(k: int, a: int, b: int) -> list:
        """The histograms messages of measurement ``k``'s TDCs [a, b), from the journal."""
        nonlocal window_ns
        bounds = bounds_all.rows(a, b) if bounds_all else None
        core = HistogramCore(b - a, bounds, tdc_offset=a,
                             measurement_cycles=topo.histogram.get("measurement_cycles"),
                             accumulator=_instrument_accumulator(topo))
        core.measurement = k
        w = b - a
        lo = k * mc * w
        hi = min((k + 1) * mc, cycles) * w
        core.next_word = lo
        if window_ns is None:
            window_ns = _journal_window_ns(journal, topo.run)
        gate = _journal_gate_ns(journal, topo.run)
        msgs = []
        for f, words in worker_reader(lambda s, e: read_range(journal, topo.run, s, e),
                                      n, (a, b))(lo, hi):
            msgs += core.process({"run": topo.run, "first_word": f, "seq": k,
                                  "t_laser_win_ns": gate, "window_ns": window_ns,
                                  "date": topo.date, "n_tdc_total": n}, _words_batch(words))
        if hi < (k + 1) * mc * w or core.m_words is None:  # (one measurement: the run)
            msgs += core.finish({"run": topo.run})
        return msgs

    def stored(path: Path, k: int, a: int, b: int) -> list:
        """A histograms part the datasets hold (checked against the journal above) as the
        message its worker sent."""
        import pyarrow.parquet as pq

        table = pq.read_table(path)
        meta = json.loads((table.schema.metadata or {}).get(b"tcspc.measurement", b"{}"))
        head = {"kind": "data", "schema": "histograms", "run": topo.run, "seq": k,
                "step": "reconcile", "measurement": table.column("measurement")[0].as_py(),
                "measurement_index": k, "tdc_range": [a, b], "n_tdc_total": n,
                "t_laser_win_ns": _journal_gate_ns(journal, topo.run),
                "window_ns": window_ns or _journal_window_ns(journal, topo.run),
                "date": topo.date, **meta}
        return [(head, table.replace_schema_metadata(None).combine_chunks().to_batches()[0])]

    # spatial ranging ranges a measurement's frame whole: a part recomputed, or ranged
    # without another part, has the whole measurement ranged again (gathered, as live)
    spatial = ranger is not None and ranger.gather is not None
    rerange: set[int] = set()
    made: dict[tuple[int, int], list] = {}  # spatial: the parts recomputed, for the gather
    for (a, b) in tdc_ranges(topo):
        for k in range(n_meas):
            if (k, a) in have_h and (have_r is None or (k, a) in have_r):
                # every part is compared with the journal, not only the missing ones
                cyc = _words_in(spans, k * mc * n, min((k + 1) * mc, cycles) * n) // n
                why = _part_problem(have_h[(k, a)], b - a, cyc,
                                    (f"{topo.run}-m{k:06d}" if by_m else topo.run, a)
                                    ) if check else None
                if why is None and spatial and _spatial_missing(have_r[(k, a)]):
                    rerange.add(k)  # its histograms are whole: only the ranges again
                    continue
                why = why or (_unreadable(have_r[(k, a)]) if have_r is not None else None)
                if why is None:
                    continue
                rebuilt.append({"measurement": k, "tdc": a, "file": str(why[0]),
                                "why": why[1]})
            if pruned_words(journal, topo.run, k * mc * n, min((k + 1) * mc, cycles) * n):
                unrecoverable.append([k, a])  # its words were pruned (journal_keep_gb)
                continue
            bad = []
            for _ in read_range(journal, topo.run, k * mc * n, min((k + 1) * mc, cycles) * n,
                                lambda f, w, why, bad=bad: bad.append([f, w, why])):
                pass  # a measurement's words are checked whole before any is used
            if bad:
                # a corrupt chunk's words are never data: the measurement is withheld
                corrupt_meas.append([k, a])
                for c in bad:
                    corrupt_chunks[c[0]] = c
                if (k, a) not in have_h:  # (a histogram already written is classified)
                    withheld += (min((k + 1) * mc, cycles) - k * mc) * (b - a)
                continue
            msgs = recompute(k, a, b)
            for head, batch in msgs:
                sink.process(head, batch)
                if ranger is not None and not spatial:
                    for h2, b2 in ranger.process(head, batch)[1:]:
                        sink.process(h2, b2)
            if spatial:
                made[(k, a)] = msgs
                rerange.add(k)
            redone.append([k, a])
    lost = {(k, a) for k, a in unrecoverable + corrupt_meas}
    for k in sorted(rerange):  # every part of the measurement, gathered and ranged whole
        ranger.forward = False
        for (a, b) in tdc_ranges(topo):
            if (k, a) in lost or ((k, a) not in made and (k, a) not in have_h):
                continue  # (its words are gone: the frame is ranged without it, flagged)
            msgs = made.pop((k, a), None) or stored(have_h[(k, a)], k, a, b)
            for head, batch in msgs:
                for h2, b2 in ranger.process(head, batch):
                    sink.process(h2, b2)
        for h2, b2 in ranger.finish({}):  # (a frame with a part lost: what it has)
            sink.process(h2, b2)
    still = sorted({k for (k, _), p in _dataset_parts(out, "ranges", topo.run).items()
                    if _spatial_missing(p)}) if spatial else []
    return {"checked": True, "measurements": n_meas, "tdc_ranges": len(tdc_ranges(topo)),
            "recomputed": redone, "rebuilt": rebuilt, "unrecoverable": unrecoverable,
            "corrupt": corrupt_meas,
            # spatial: measurements ranged again whole, and those still without a part
            **({"spatial_reranged": sorted(rerange), "spatial_incomplete": still}
               if spatial else {}),
            "corrupt_chunks": sorted(corrupt_chunks.values()),
            "corrupt_words": sum(c[1] for c in corrupt_chunks.values()),
            "withheld_words": withheld}


def _journal_spans(journal: Path, run: str) -> list[tuple[int, int]]:
    from pipeline.stream.journal import _entries

    return sorted((e["first_word"], e["first_word"] + e["words"])
                  for e in _entries(journal / f"{run}.index.jsonl") if "first_word" in e)


def _words_in(spans: list[tuple[int, int]], lo: int, hi: int) -> int:
    """Journaled words of the run's [lo, hi) (a gap, such as lost datagrams, is none)."""
    import bisect

    i = max(0, bisect.bisect_right(spans, (lo, lo)) - 1)
    n = 0
    for a, b in spans[i:]:
        if a >= hi:
            break
        n += max(0, min(b, hi) - max(a, lo))
    return n


def _spatial_missing(path: Path) -> list | None:
    """The TDC ranges a spatial ranges part was ranged without (its metadata), None for
    none (or an unreadable file: :func:`_unreadable` says so)."""
    import pyarrow.parquet as pq

    try:
        meta = pq.read_schema(path).metadata or {}
    except Exception:  # noqa: BLE001 (pyarrow raises OSError, ArrowInvalid, ...)
        return None
    raw = meta.get(b"tcspc.spatial_missing")
    return json.loads(raw) if raw else None


def _unreadable(path: Path) -> tuple[Path, str] | None:
    import pyarrow.parquet as pq

    try:
        pq.read_metadata(path)
    except Exception as exc:  # noqa: BLE001 (pyarrow raises OSError, ArrowInvalid, ...)
        return path, f"unreadable: {type(exc).__name__}: {exc}"
    return None


def _part_problem(path: Path, n_tdc: int, cycles: int,
                  ident: tuple[str, int] | None = None) -> tuple[Path, str] | None:
    """Why a histograms part does not match the journal (None: it does): unreadable, or
    not every TDC of its range with the cycles (and so the words) the journal holds for
    its measurement (a measurement written partial by a stop, or short), or (``ident``:
    the measurement's name and first TDC) another measurement's or range's rows."""
    import numpy as np
    import pyarrow.parquet as pq

    from schemas.constants import WORD_CLASSES

    cols = [f"n_{c}" for c in WORD_CLASSES]
    try:
        t = pq.read_table(path, columns=["cycles", "measurement", "tdc", *cols])
    except Exception as exc:  # noqa: BLE001
        return path, f"unreadable: {type(exc).__name__}: {exc}"
    got = np.asarray(t.column("cycles"), np.int64)
    words = int(sum(np.asarray(t.column(c), np.int64).sum() for c in cols))
    if t.num_rows != n_tdc or (got != cycles).any() or words != cycles * n_tdc:
        span = f"{int(got.min())}..{int(got.max())}" if got.size else "no"
        return path, (f"{t.num_rows} TDCs, {span} cycles and {words:,} words; the journal "
                      f"holds {cycles:,} cycles, {cycles * n_tdc:,} words for its {n_tdc} "
                      "TDCs")
    if ident is not None:
        names = set(t.column("measurement").to_pylist())
        tdcs = np.asarray(t.column("tdc"), np.int64)
        if names != {ident[0]} or not np.array_equal(tdcs, np.arange(n_tdc) + ident[1]):
            return path, (f"rows of {sorted(names)[:2]}, TDCs {int(tdcs.min())}.."
                          f"{int(tdcs.max())}; the file's name says measurement "
                          f"{ident[0]}, TDCs {ident[1]}..{ident[1] + n_tdc - 1}")
    return None


def _instrument_accumulator(topo: Topology):
    """A file source's records are histogrammed as its instrument does (the same code as
    the live worker and the offline command); None for the thesis chip's words."""
    if topo.source.get("kind") != "file":
        return None
    from pipeline.offline.instruments import instrument_accumulator

    return instrument_accumulator(topo.source["file"], topo.source["format"],
                                  topo.source.get("firmware", "2212b"))


def _class_totals(parts: list[Path]) -> dict[str, int]:
    """An instrument's record classes (photons, markers, overflow, ...) over the parts,
    from the totals the sink keeps in each file's metadata."""
    import pyarrow.parquet as pq

    totals: dict[str, int] = {}
    for p in parts:
        meta = pq.read_schema(p).metadata or {}
        for k, v in json.loads(meta.get(b"tcspc.class_counts", b"{}")).items():
            totals[k] = totals.get(k, 0) + int(v)
    return totals


def _words_batch(words):
    import pyarrow as pa

    from schemas.words import RAW_WORDS

    return pa.record_batch([pa.array(words)], schema=RAW_WORDS.schema)


def _journal_meta(journal: Path, run: str) -> dict:
    for side in sorted(journal.glob(f"{run}-*.json")):
        return json.loads(side.read_text())
    return {}


def _journal_window_ns(journal: Path, run: str) -> float:
    return float(_journal_meta(journal, run).get("window_ns", 80.0))


def _journal_gate_ns(journal: Path, run: str) -> float:
    return float(_journal_meta(journal, run).get("t_laser_win_ns", 140.0))


def accounting(topo: Topology, metrics: dict[str, dict], reconciled: dict | None = None,
               bounds: str | None = None) -> dict:
    """Words in (journaled) = hit + no_hit + artifact + invalid_phase + malformed (from the
    histograms dataset, each measurement once) + words withheld (measurements that a
    corrupt journal chunk kept from being recomputed: ``corrupt_words`` of them in the
    corrupt chunks themselves); messages and datagrams rejected by reason (quarantined) per
    stage; datagrams lost (sequence gaps), duplicated and late; ``bounds``: what the words
    were classified with (``artifact_bounds``). Written to
    ``OUT/accounting/run=RUN.json``."""
    import polars as pl

    from pipeline.stream.journal import journaled_total, run_end
    from schemas.constants import WORD_CLASSES

    out = Path(topo.sink["out"])
    parts = sorted(_dataset_parts(out, "histograms", topo.run).values())
    cols = [f"n_{c}" for c in WORD_CLASSES]
    classes = dict.fromkeys(WORD_CLASSES, 0)
    if parts and topo.source.get("kind") == "file":  # an instrument's record classes
        classes = _class_totals(parts)
    elif parts:
        sums = pl.scan_parquet(parts).select([pl.col(c).sum() for c in cols]).collect()
        classes = {c: int(sums[f"n_{c}"][0]) for c in WORD_CLASSES}
    journaled = journaled_total(topo.state / "journal", topo.run)
    span = run_end(topo.state / "journal", topo.run)
    if span is None:  # a run without its end line (the reconciliation says so): the words
        span = max((b for _, b in _journal_spans(topo.state / "journal", topo.run)),
                   default=0)  # journaled so far, so a gap is never negative
    rejected = {name: m.get("rejected", {}) for name, m in metrics.items() if m.get("rejected")}
    rec = reconciled or {}
    withheld = int(rec.get("withheld_words", 0))
    src = metrics.get("source", {})
    result = {"run": topo.run, "words_in": journaled, "classes": classes,
              "classified": sum(classes.values()),
              "corrupt": int(rec.get("corrupt_words", 0)), "withheld": withheld,
              "corrupt_measurements": rec.get("corrupt", []),
              "balanced": sum(classes.values()) + withheld == journaled,
              "rejected_messages": rejected,
              "lost_datagrams": src.get("lost_datagrams", 0),
              "duplicate_datagrams": src.get("duplicates", 0),
              "late_datagrams": src.get("late", 0),
              # (UDP) received but never journaled: the ring was full (the journal too slow)
              "ring_dropped_datagrams": src.get("ring_dropped", 0),
              "conflicting_datagrams": src.get("conflicts", 0),
              "stream_restarts": src.get("resets", []),
              **({"sender": src.get("sender"), "peers": src.get("peers"),
                  "other_senders": src["other_senders"]} if "other_senders" in src else {}),
              "quarantine_dropped": {name: m["quarantine_dropped"] for name, m in
                                     metrics.items() if m.get("quarantine_dropped")},
              "checkpoints_discarded": {name: m["checkpoints_discarded"] for name, m in
                                        metrics.items() if m.get("checkpoints_discarded")},
              "words_in_gaps": span - journaled,
              # spatial: frames the range stage ranged without some workers' parts (its
              # last process's count; the reconciliation ranged them again whole)
              **({"spatial_incomplete_frames": int(metrics.get("range", {}).get(
                  "incomplete_frames", 0))} if spatial_geometry(topo) else {}),
              "measurements_files": len(parts)}
    if bounds is not None:
        result["artifact_bounds"] = bounds
    from pipeline.stream.state import write_under

    # (from OUT's descriptor: a link planted at OUT/accounting is refused, not followed)
    path = write_under(out, f"accounting/run={topo.run}.json",
                       json.dumps(result, indent=1).encode())
    result["path"] = str(path)
    return result
