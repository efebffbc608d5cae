"""The ams TMF8820's histograms (the JSON of cpsiff/SPAD-ICCP-Summer-School's distance
captures) as a generic histograms parquet and a truth.csv, for ``tcspc calibrate distance``
and ``tcspc range``.

Each capture becomes a measurement ``capture_NNN`` (its index in the source): rows ``tdc``
0-8 are the 3 x 3 zones, row 9 the sensor's reference channel (``reference = true``), 128
bins of the nominal 91 ps (the source's own figure; the calibration fits the real width).
The sensor does not report its laser pulses: ``cycles`` is null.

Usage: ``python -m pipeline.io.tmf8820 CAPTURES.json --out H.parquet --truth truth.csv``
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from pipeline.io.atomic import atomic_path

BIN_WIDTH_PS = 91.0
ZONES = 9


def tmf8820_table(captures: list[dict]) -> tuple[pa.Table, list[tuple[str, float]]]:
    """The histograms table and the (measurement, distance_m) truth of the captures."""
    rows: dict[str, list] = {k: [] for k in ("measurement", "tdc", "counts", "cycles",
                                             "instrument", "bin_width_ps", "reference")}
    truth = []
    for i, cap in enumerate(captures):
        name = f"capture_{int(cap.get('capture_index', i)):03d}"
        hists = cap["hists"]
        if len(hists) != ZONES:
            raise ValueError(f"capture {i}: {len(hists)} zones, expected {ZONES}")
        for z, counts in enumerate([*hists, cap["reference_hist"]]):
            rows["measurement"].append(name)
            rows["tdc"].append(z)
            rows["counts"].append([int(c) for c in counts])
            rows["cycles"].append(None)
            rows["instrument"].append("generic")
            rows["bin_width_ps"].append(BIN_WIDTH_PS)
            rows["reference"].append(z == ZONES)
        truth.append((name, float(cap["dist_to_plane"])))
    schema = pa.schema([("measurement", pa.string()), ("tdc", pa.uint16()),
                        ("counts", pa.list_(pa.uint64())), ("cycles", pa.uint64()),
                        ("instrument", pa.string()), ("bin_width_ps", pa.float64()),
                        ("reference", pa.bool_())])
    return pa.table(rows, schema=schema), truth


def convert(json_path: str | Path, out: str | Path, truth_csv: str | Path) -> int:
    """Write the parquet and truth.csv (atomically); returns the number of captures."""
    captures = json.loads(Path(json_path).read_text())
    table, truth = tmf8820_table(captures)
    with atomic_path(out) as tmp:
        pq.write_table(table, tmp)
    with atomic_path(truth_csv) as tmp, open(tmp, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["measurement", "distance_m"])
        w.writerows(truth)
    return len(captures)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m pipeline.io.tmf8820", description=__doc__
                                .split("\n\n")[0])
    p.add_argument("json")
    p.add_argument("--out", required=True, help="histograms parquet to write")
    p.add_argument("--truth", required=True, help="truth.csv to write")
    a = p.parse_args(argv)
    n = convert(a.json, a.out, a.truth)
    print(f"wrote {a.out} and {a.truth}: {n} captures x {ZONES} zones + reference",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
