"""Files per second of the ``batch`` flow (one task per file) against Dask workers.

    PYTHONPATH=. .venv/bin/python -m benchmarks.batch [--files 8] [--cycles 200000]

Writes ``--files`` simulated chip captures of scenes/small16.toml (16 TDCs, ``--cycles``
cycles each) to a temporary directory, then histograms them with ``tcspc flow run batch``'s
flow: on Prefect's default task runner (threads in this process), and on a local Dask
cluster of 1 and 2 worker processes (one thread each). Prints the command, the machine, its
load, and per run the wall time, files/s and the mean time a task spent on its file (the
per-file cost, without the scheduling around it). The outputs of every run are compared
with the first's.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
ROOT = Path(__file__).resolve().parents[1]


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--files", type=int, default=8)
    ap.add_argument("--cycles", type=int, default=200_000)
    ap.add_argument("--workers", default="1,2", help="Dask worker processes, comma-separated")
    args = ap.parse_args(argv)

    import polars as pl
    import pyarrow.parquet as pq
    from distributed import LocalCluster
    from prefect.testing.utilities import prefect_test_harness
    from prefect_dask import DaskTaskRunner

    from benchmarks.datapath import machine
    from flows.batch import batch
    from pipeline.offline.simulate import simulate_capture

    print("command:", "PYTHONPATH=. python -m benchmarks.batch", shlex.join(sys.argv[1:]))
    print("machine:", machine())
    print(f"load average before: {os.getloadavg()[0]:.1f} (the machine is shared: other "
          "sessions' work runs beside this one)")
    with tempfile.TemporaryDirectory() as tmp, prefect_test_harness(server_startup_timeout=180):
        src = Path(tmp) / "in"
        src.mkdir()
        for i in range(args.files):
            simulate_capture(ROOT / "scenes" / "small16.toml", args.cycles, src / f"chip{i}",
                             seed=i, chip_seed=1 + i)
        words = args.files * args.cycles * 16
        print(f"{args.files} chip captures of {args.cycles:,} cycles x 16 TDCs "
              f"({words / 1e6:.1f} M words in all)")
        runs = [("Prefect threads (default)", None, None)]
        runs += [(f"Dask, {n} worker process{'es' if n > 1 else ''}", n, None)
                 for n in (int(x) for x in args.workers.split(","))]
        rows, first = [], None
        for label, n, _ in runs:
            out = Path(tmp) / f"out{len(rows)}"
            if n is None:
                t0 = time.perf_counter()
                r = batch(str(src), out=str(out))
                wall = time.perf_counter() - t0
            else:
                with LocalCluster(n_workers=n, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
                    fl = batch.with_options(task_runner=DaskTaskRunner(
                        address=cluster.scheduler_address))
                    fl(str(src), out=str(Path(tmp) / "warm"))  # workers' imports paid
                    t0 = time.perf_counter()
                    r = fl(str(src), out=str(out))
                    wall = time.perf_counter() - t0
            files = pl.read_parquet(Path(r["run"]) / "files.parquet")
            got = {p.name: pq.read_table(p).replace_schema_metadata(None)
                   for p in (Path(r["run"]) / "histogram").glob("*.parquet")}
            first = first or got
            same = got.keys() == first.keys() and all(got[k].equals(first[k]) for k in got)
            rows.append((label, wall, r["files"] / wall, float(files["seconds"].mean()), same))
        print()
        print("| runner | wall (s) | files/s | per-file task (s) | outputs = first run's |")
        print("|---|---|---|---|---|")
        for label, wall, fps, per, same in rows:
            print(f"| {label} | {wall:.2f} | {fps:.2f} | {per:.3f} | {'yes' if same else 'NO'} |")
    print(f"\nload average after: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
