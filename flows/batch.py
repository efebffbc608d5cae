"""``batch``: one operation over a directory of captures and instrument files, one Prefect
task per file, so a month of captures or a bench of chips fans out over a Dask cluster
(``tcspc flow run batch --dask [ADDRESS]``) instead of a loop.

The files are found by content, as ``tcspc histogram`` finds them
(:func:`pipeline.io.formats.detect_format`): a chip capture (``NAME.bin`` [.zst] with its
``NAME.json``), a PicoQuant PTU file, LinoSPAD2 raw words. Each task writes one output
under ``OUT/runs/<run>/<op>/`` (atomically, named after its file) and returns a row of the
run's ``files.parquet`` (beside ``params.json``, the run's parameters and files, and
``summary.json``); the outputs do not depend on where a task ran, so a run on a
cluster gives the serial run's files (tested). A file that fails is a row with its error,
and the run fails after every other file was done, naming it.

- ``histogram``: a chip capture's first-stage histograms (its artifact bounds estimated from
  it, or the calibration's with ``calibration``); a PTU T3 file's dtime histograms, a row
  per channel; a LinoSPAD2 file's fine-code histograms, a row per TDC.
- ``calibrate``: a chip density capture's density test (a calibration directory per file:
  a bench of chips); a LinoSPAD2 file's code density (``code_density.parquet``). A PTU
  file has its maker's calibration: refused, said in its row.
- ``range``: a chip capture with ``calibration``; a PTU T3 or LinoSPAD2 file with
  ``delay_ps`` (the instrument's own uniform time axis, as ``tcspc range`` does).
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Literal

from prefect import flow, task
from prefect.cache_policies import NO_CACHE

from flows.common import check_roots, new_run_dir

OPS = ("histogram", "calibrate", "range")


def discover(directory: str | Path) -> list[tuple[str, str]]:
    """``(path, format)`` of every capture and instrument file in ``directory`` (not its
    subdirectories), by name; a chip capture once (its ``.json`` names it), other files
    whose content is none of the formats left out."""
    from pipeline.io.formats import FormatError, detect_format

    d = Path(directory)
    if not d.is_dir():
        raise ValueError(f"batch: {d} is not a directory")
    found, seen = [], set()
    for p in sorted(d.iterdir()):
        if not p.is_file():
            continue
        if p.suffix == ".json":  # a chip capture's sidecar: the capture is NAME
            p = p.with_suffix("")
        if p in seen:
            continue
        seen.add(p)
        try:
            fmt = detect_format(p)
        except FormatError:
            continue  # a capture's .bin (found by its .json), a licence, a note ...
        if fmt == "tcspc" and p.suffix in (".bin", ".zst", ".nhz"):
            continue
        found.append((str(p), fmt))
    return found


def _histogram(path: str, fmt: str, dest: Path, calibration: str | None) -> dict:
    if fmt == "tcspc":
        from pipeline.io.capture import Capture
        from pipeline.offline.datapath import histogram_capture, write_histograms

        cap = Capture(path)
        bounds = None
        if calibration:
            from pipeline.io.caldir import read_bounds

            bounds = read_bounds(calibration, cap.meta.n_tdc)
        state, bounds = histogram_capture(cap, bounds, threads=1)
        out = dest / f"{cap.name}.parquet"
        write_histograms(state, cap.name, out, {"capture": str(cap.bin_path),
                                                 "bounds": bounds.describe()})
        return {"output": str(out), "records": cap.n_words, "rows": state.n_tdc}
    from pipeline.offline import instruments as inst

    table, summary = (inst.histogram_ptu(path) if fmt == "ptu"
                      else inst.histogram_linospad2(path))
    if summary.accounted != summary.records:
        raise ValueError(f"accounting error: {summary.accounted:,} records classified, "
                         f"{summary.records:,} read")
    out = dest / f"{Path(path).name}.parquet"
    inst.write_instrument_histograms(table, out, path, summary)
    return {"output": str(out), "records": summary.records, "rows": table.num_rows,
            "note": "truncated" if summary.truncated else ""}


def _calibrate(path: str, fmt: str, dest: Path) -> dict:
    if fmt == "tcspc":
        from pipeline.io.capture import Capture
        from pipeline.offline.calibrate import density_from_capture, write_caldir

        cap = Capture(path)
        var: dict = {}
        res, second = density_from_capture(cap, inl_rms_lsb=None, variance=var)
        out = write_caldir(dest / cap.name, res, second, [cap.bin_path],
                           width_var=var.get("width_var"))
        return {"output": str(out), "records": cap.n_words, "rows": int(res.ok.sum()),
                "note": f"{int((~res.ok).sum())} TDCs flagged" if not res.ok.all() else ""}
    if fmt == "ptu":
        raise ValueError("a PicoQuant board's dtime bins are calibrated by its maker: "
                         "nothing to calibrate (histogram or range it)")
    import numpy as np
    import pyarrow as pa
    import pyarrow.parquet as pq

    from pipeline.io.atomic import atomic_path
    from pipeline.offline.linospad2_cal import calibrate

    density, tally = calibrate(path, by="tdc")
    table = pa.table({"tdc": np.arange(density.hits.size, dtype=np.uint16),
                      "hits": density.hits,
                      "width_ps": pa.array(list(density.width_ps), pa.list_(pa.float64()))})
    out = dest / f"{Path(path).name}.code_density.parquet"
    with atomic_path(out) as tmp:
        pq.write_table(table, tmp)
    return {"output": str(out), "records": int(np.sum(density.hits)),
            "rows": table.num_rows, "note": ""}


def _range(path: str, fmt: str, dest: Path, calibration: str | None,
           delay_ps: float | None) -> dict:
    import pyarrow.parquet as pq

    from pipeline.io.atomic import atomic_path

    if fmt == "tcspc":
        if not calibration:
            raise ValueError("a chip capture is ranged with a calibration (-p calibration=DIR)")
        from pipeline.io.caldir import load_calibration
        from pipeline.offline.ranging import range_capture

        out = dest / f"{Path(path).name}.parquet"
        table, note = range_capture(path, load_calibration(calibration), out)
        return {"output": str(out), "records": 0, "rows": table.num_rows, "note": note}
    if delay_ps is None:
        raise ValueError(f"a {fmt} file is ranged with its delay (-p delay_ps=...)")
    import numpy as np

    from pipeline.offline import instruments as inst
    from pipeline.offline.ranging import ranges_table

    table, summary = (inst.histogram_ptu(path) if fmt == "ptu"
                      else inst.histogram_linospad2(path))
    cut = inst.truncation(path, table, summary)
    if cut:  # as `tcspc range`: ranges from part of a measurement are not written
        raise ValueError(f"{cut}: not ranged (its ranges would come from part of a "
                         "measurement)")
    est, d, s, note = inst.range_uniform(table, np.full(table.num_rows, delay_ps * 1e-12))
    ranges = ranges_table(Path(path).stem, est, d, s)
    ranges = ranges.replace_schema_metadata({**ranges.schema.metadata,
                                             b"tcspc.source": str(path).encode(),
                                             b"tcspc.time_axis": note.encode()})
    out = dest / f"{Path(path).name}.parquet"
    with atomic_path(out) as tmp:
        pq.write_table(ranges, tmp)
    return {"output": str(out), "records": summary.records, "rows": ranges.num_rows,
            "note": ""}


@task(cache_policy=NO_CACHE, task_run_name="{op} {path}")
def process(path: str, fmt: str, op: str, dest: str, calibration: str | None = None,
            delay_ps: float | None = None) -> dict:
    """One file's operation; its row of ``files.parquet`` (``error`` set, and no output,
    when the file could not be done: bad input is that file's, never the run's crash)."""
    from schemas.errors import TcspcError

    t0 = time.perf_counter()
    row = {"file": path, "format": fmt, "op": op, "output": "", "records": 0, "rows": 0,
           "note": "", "error": ""}
    try:
        if op == "histogram":
            row.update(_histogram(path, fmt, Path(dest), calibration))
        elif op == "calibrate":
            row.update(_calibrate(path, fmt, Path(dest)))
        else:
            row.update(_range(path, fmt, Path(dest), calibration, delay_ps))
    except (TcspcError, ValueError, OSError) as exc:
        row["error"] = f"{type(exc).__name__}: {exc}"
    row["seconds"] = time.perf_counter() - t0
    return row


#: a batch that runs longer is failed by Prefect (all Dask workers dead: not Running forever)
BATCH_TIMEOUT_S = 6 * 3600


@flow(name="batch", timeout_seconds=BATCH_TIMEOUT_S)
def batch(inputs: str = "data/captures",
          op: Literal["histogram", "calibrate", "range"] = "histogram", out: str = "data/batch",
          calibration: str | None = None, delay_ps: float | None = None) -> dict:
    """Histogram, calibrate or range (``op``) every capture and instrument file in a directory.

    One task per file of ``inputs``, on a Dask cluster with ``--dask``; ``calibration``
    (a chip capture's bounds, or its ranging) and ``delay_ps`` (an instrument's ranging)
    as ``tcspc histogram`` and ``tcspc range`` take them."""
    if op not in OPS:
        raise ValueError(f"batch: op must be one of {', '.join(OPS)}, found {op!r}")
    check_roots(out=out, inputs=inputs, calibration=calibration)  # (a served run: roots)
    files = discover(inputs)
    if not files:
        raise ValueError(f"batch: no capture or instrument file in {inputs}")
    run = new_run_dir(out, "batch")
    params = {"inputs": str(inputs), "op": op, "out": str(out), "calibration": calibration,
              "delay_ps": delay_ps, "files": [p for p, _ in files]}
    (run / "params.json").write_text(json.dumps(params, indent=1))
    dest = run / op
    dest.mkdir()
    t0 = time.perf_counter()
    futures = [process.submit(p, fmt, op, str(dest), calibration, delay_ps)
               for p, fmt in files]
    rows = [f.result() for f in futures]
    wall = time.perf_counter() - t0
    import polars as pl

    pl.DataFrame(rows).write_parquet(run / "files.parquet")
    failed = [f"{Path(r['file']).name}: {r['error']}" for r in rows if r["error"]]
    result = {"run": str(run), "op": op, "files": len(rows), "failed": len(failed),
              "wall_s": wall, "files_per_s": len(rows) / wall if wall > 0 else float("nan"),
              "task_s": sum(r["seconds"] for r in rows)}
    (run / "summary.json").write_text(json.dumps({**result, "failed_files": failed},
                                                 indent=1))
    if failed:
        raise RuntimeError(f"batch: {len(failed)} of {len(rows)} files failed (the rest are "
                           f"in {run}): " + "; ".join(failed))
    return result
