"""The whole `tcspc histogram` command and `tcspc --help`, as a user runs them (wall time of
the subprocess, file read from the page cache included).

The capture is the street scene simulated for ``--cycles`` cycles and tiled ``--tile``
times (as issue 15 did: 50 000 cycles x 16 = 102 M words), written under a temporary
directory (never committed). The command runs with the bounds estimated from the capture
(one pass) and with a calibration's bounds, each the best of ``--repeat`` runs.

    python benchmarks/cli.py [--cycles 50000] [--tile 16] [--repeat 3] [--out results.md]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.datapath import emit, machine  # noqa: E402

TCSPC = [sys.executable, "-m", "pipeline.cli"]


def timed(cmd: list[str], repeat: int) -> tuple[float, str]:
    best, err = float("inf"), ""
    for _ in range(repeat):
        t0 = time.perf_counter()
        res = subprocess.run(cmd, capture_output=True, text=True)
        dt = time.perf_counter() - t0
        if res.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)} failed:\n{res.stderr}")
        best, err = min(best, dt), res.stderr
    return best, err


def make_capture(tmp: Path, cycles: int, tile: int) -> Path:
    from pipeline.io.capture import Capture, CaptureWriter

    one = tmp / "street"
    subprocess.run([*TCSPC, "simulate", str(ROOT / "scenes" / "street.toml"), "--cycles",
                    str(cycles), "--out", str(one) + ".bin", "-q"], check=True)
    cap = Capture(str(one) + ".bin")
    words = np.concatenate([w.copy() for _, w in cap.iter_chunks()])
    with CaptureWriter(tmp / "tiled", cap.meta.n_tdc, cap.meta.window_ns,
                       cap.meta.t_laser_win_ns, kind="range",
                       note=f"street x {tile}") as w:
        for _ in range(tile):
            w.write(words)
    return tmp / "tiled.bin"


def calibration_bounds(tmp: Path) -> Path:
    """A calibration directory whose tdc.parquet holds the chip's true bounds (the LSB
    columns NaN: `tcspc histogram` reads only Nmin/Nmax from it)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from schemas.outputs import CALIBRATION_TDC

    chip = json.loads((tmp / "street.json").read_text())["truth"]["chip"]
    n = len(chip["n_min"])
    nan = np.full(n, np.nan)
    caldir = tmp / "cal"
    caldir.mkdir()
    pq.write_table(pa.table({
        "tdc": pa.array(np.arange(n), pa.uint16()), "lsb_ps": pa.array(nan),
        "lsb_poly": pa.FixedSizeListArray.from_arrays(pa.array(np.zeros(4 * n)), 4),
        "n_min": pa.array(chip["n_min"], pa.uint16()),
        "n_max": pa.array(chip["n_max"], pa.uint16()),
        "n_th": pa.array(chip["n_th"], pa.uint16()), "pdm": pa.array(chip["pdm"], pa.uint16()),
        "delay_ps": pa.array(nan), "ok": pa.array(np.ones(n, bool))},
        schema=CALIBRATION_TDC.schema), caldir / "tdc.parquet")
    (caldir / "meta.json").write_text(json.dumps({"schema_version": CALIBRATION_TDC.version}))
    return caldir


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cycles", type=int, default=50_000)
    ap.add_argument("--tile", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    lines = ["### `tcspc` as a user runs it", "",
             f"command: `python benchmarks/cli.py --cycles {args.cycles} --tile {args.tile} "
             f"--repeat {args.repeat}`", f"machine: {machine()}", ""]
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        capture = make_capture(tmp, args.cycles, args.tile)
        from pipeline.io.capture import Capture

        n_words = Capture(capture).n_words
        cal = calibration_bounds(tmp)
        help_s, _ = timed([str(Path(sys.executable).parent / "tcspc"), "--help"],
                          max(args.repeat, 5))
        rows = [("`tcspc --help`", help_s, None)]
        for label, extra in (("`tcspc histogram` (bounds from the capture, one pass)", []),
                             ("`tcspc histogram --calibration` (bounds given)",
                              ["--calibration", str(cal)])):
            dt, err = timed([*TCSPC, "histogram", str(capture), "--out",
                             str(tmp / "h.parquet"), "-q", *extra], args.repeat)
            rows.append((label, dt, n_words / dt))
        lines += [f"capture: {n_words / 1e6:.1f} M words ({n_words * 4 / 1e9:.2f} GB, street "
                  f"scene {args.cycles:,} cycles x {args.tile}, from the page cache)", "",
                  "| command | wall s (best of runs) | M words/s |", "|---|---:|---:|"]
        lines += [f"| {label} | {dt:.3f} | {'' if r is None else f'{r / 1e6:.0f}'} |"
                  for label, dt, r in rows]
    emit(lines, args.out)


if __name__ == "__main__":
    main()
