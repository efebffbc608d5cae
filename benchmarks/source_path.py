"""Where the stream source's cycles go, and the daemon's words/s, side by side with another
source tree in the same run.

1. The source's work per batch of a capture replay, each step timed apart (CPU seconds of
   this process, so other processes' load weighs less), the way main's source does it
   (read and swap in place, a big-endian copy for the journal, each worker's TDC range cut
   into a new array, the Arrow IPC copy; zstd level 1 of the journal's frame) and the way
   it does now (read as stored, journal from that buffer, one swap-and-cut copy into the
   message: pipeline.stream.rawwire). The zstd step is the journal writer's thread.
2. ``tcspc daemon`` (capture source, journal on with zstd, ``--workers`` histogram
   workers by TDC range, measurements of 20,000 cycles, the sink; a range stage with
   ``--calibration``) from each ``--tree``, interleaved, words/s from the source's first
   batch to the last measurement written; the accounting must balance.

    python benchmarks/source_path.py --tree /path/to/main --tree . [--cycles 500000]
        [--hit-prob 0.05] [--workers 2] [--repeat 2] [--calibration DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def source_steps(capture: Path, ranges, rounds: int = 2) -> dict[str, dict[str, float]]:
    import pyarrow as pa
    import zstandard

    from pipeline.io.capture import Capture
    from pipeline.stream import wire
    from pipeline.stream.fanout import TdcSplitter
    from pipeline.stream.rawwire import RawWordsEncoder
    from schemas.words import RAW_WORDS

    cap = Capture(capture)
    n = cap.meta.n_tdc
    chunk = max(1, (1 << 18) // n) * n
    sp = TdcSplitter(n, ranges)
    codec = zstandard.ZstdCompressor(level=1, write_checksum=True, write_content_size=True)
    enc = RawWordsEncoder()
    head = {"kind": "data", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
            "run": "r", "seq": 0, "step": "source", "first_word": 0, "n_tdc": 1,
            "t_laser_win_ns": 140.0}
    out = {"before": {}, "now": {}}

    def tick(d, k, t0):
        t = time.process_time()
        d[k] = d.get(k, 0.0) + t - t0
        return t

    for _ in range(rounds):  # interleaved: the machine's load weighs on both alike
        d = out["before"]
        t = time.process_time()
        for first, w in cap.iter_chunks(chunk):
            t = tick(d, "read + swap in place", t)
            be = w.astype(">u4")
            t = tick(d, "big-endian copy (journal)", t)
            codec.compress(memoryview(be).cast("B"))
            t = tick(d, "zstd (journal thread)", t)
            for f, part in sp.split(first, w):
                wire.encode({**head, "first_word": f},
                            pa.record_batch([pa.array(part)], schema=RAW_WORDS.schema))
            t = tick(d, "cut by TDC range + IPC copy", t)
        d = out["now"]
        t = time.process_time()
        for first, w in cap.iter_chunks(chunk, native=False):
            t = tick(d, "read as stored", t)
            codec.compress(memoryview(w).cast("B"))
            t = tick(d, "zstd (journal thread)", t)
            for f, view in sp.views(first, w):
                enc.frames({**head, "first_word": f}, view)
            t = tick(d, "swap + cut + IPC, one copy", t)
    words = cap.n_words * rounds
    return {k: {s: words / v / 1e6 for s, v in d.items()} | {
        "total (one thread)": words / sum(d.values()) / 1e6} for k, d in out.items()}


def daemon_run(tree: Path, tmp: Path, capture: Path, workers: int, tag: str,
               calibration: str | None) -> tuple[float, dict]:
    state, outd = tmp / f"state-{tag}", tmp / f"out-{tag}"
    topo = tmp / f"topo-{tag}.toml"
    topo.write_text(f"""
[daemon]
state = "{state}"
[source]
kind = "capture"
capture = "{capture}"
[histogram]
workers = {workers}
measurement_cycles = 20000
{f'calibration = "{calibration}"' if calibration else ''}
{f'[range]{chr(10)}calibration = "{calibration}"' if calibration else ''}
[sink]
out = "{outd}"
""")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = str(tree)
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                          str(topo), "--run", "bench"], capture_output=True, text=True,
                         env=env, cwd=tree, timeout=3600)
    if res.returncode != 0:
        raise SystemExit(f"daemon from {tree} failed:\n{res.stderr[-3000:]}")
    log = (state / "logs" / "source.log").read_text()
    first = float(re.findall(r"first batch sent at ([0-9.]+)", log)[-1])
    # the last measurement written (the daemon's reconciliation and exit after it are a
    # fixed cost of the run, not of its words)
    end = max(p.stat().st_mtime for p in outd.glob("*/date=*/run=bench/*.parquet"))
    acc = json.loads(res.stdout)["accounting"]
    return end - first, acc


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tree", action="append", type=Path, default=[])
    ap.add_argument("--cycles", type=int, default=500_000)
    ap.add_argument("--n-tdc", type=int, default=128)
    ap.add_argument("--hit-prob", type=float, default=0.05)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--calibration", default=None)
    args = ap.parse_args()
    print("$ python benchmarks/source_path.py " + " ".join(sys.argv[1:]))
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, load average {os.getloadavg()[0]:.1f} at start "
          "(shared with other work)")
    from pipeline.io.capture import CaptureWriter
    from pipeline.stream.fanout import equal_ranges
    from stages.testpattern import pattern_words

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        words, _ = pattern_words(args.cycles, args.n_tdc, hit_prob=args.hit_prob, rng=0)
        with CaptureWriter(tmp / "cap", args.n_tdc, kind="pattern") as w:
            w.write(words)
        n_words = words.size
        del words
        print(f"capture: {n_words / 1e6:.1f} M words, {args.n_tdc} TDCs, "
              f"{args.hit_prob:.0%} hits (stages.testpattern)\n")
        steps = source_steps(tmp / "cap.bin", equal_ranges(args.n_tdc, args.workers))
        print(f"source steps, M words per CPU-second ({args.workers} TDC ranges):")
        for way, d in steps.items():
            print(f"  {way}: " + "; ".join(f"{k} {v:.0f}" for k, v in d.items()))
        if not args.tree:
            return
        walls: dict[Path, list[float]] = {t: [] for t in args.tree}
        for k in range(args.repeat):
            for i, tree in enumerate(args.tree):
                wall, acc = daemon_run(tree, tmp, tmp / "cap.bin", args.workers,
                                       f"{i}-{k}", args.calibration)
                if not acc.get("balanced") or acc["words_in"] != n_words:
                    raise SystemExit(f"{tree}: the run did not balance: {acc}")
                walls[tree].append(wall)
        print(f"\ndaemon, journal zstd, {args.workers} histogram workers"
              f"{', range' if args.calibration else ''}, sink; M words/s from the first "
              f"batch to the last measurement written (best, median of {args.repeat}):")
        for tree, ws in walls.items():
            print(f"  {tree}: {n_words / min(ws) / 1e6:.1f} "
                  f"(median {n_words / float(np.median(ws)) / 1e6:.1f}); balanced")
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
