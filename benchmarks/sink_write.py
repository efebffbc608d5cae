"""ParquetSink.process, parts written per second (a 128-TDC histograms table each): the
safe writes of issue 36 against main. `PYTHONPATH=TREE python benchmarks/sink_write.py NAME`."""
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pyarrow as pa

from pipeline.stream.stage import ParquetSink
from schemas.outputs import HISTOGRAMS

n = 128
t = pa.table({"measurement": ["r-m000000"] * n, "tdc": pa.array(np.arange(n), pa.uint16()),
              "counts": [list(range(300))] * n})
batch = t.to_batches()[0]
for _ in range(2):
    with tempfile.TemporaryDirectory() as d:
        sink = ParquetSink(Path(d) / "out")
        t0 = time.perf_counter()
        for k in range(400):
            sink.process({"kind": "data", "schema": HISTOGRAMS.name, "run": "r", "seq": k,
                          "date": "2026-01-01", "tdc_range": [0, n]}, batch)
        dt = time.perf_counter() - t0
    print(f"{sys.argv[1]}: 400 parts in {dt:.2f} s ({dt / 400 * 1e3:.2f} ms a part)")
