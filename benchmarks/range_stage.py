"""The range stage's cost per measurement: `RangeCore.process` (what the daemon's range
stage runs on each histograms message) on the histograms and calibration of a demo's
output (``--data``, the directory `tcspc demo --out` wrote: its calibration/current and
stream/histograms), per source tree given (``--tree``, e.g. the main branch's and this
one's), in the same run.

Cases: the demo's street measurements and the test pattern's (``stages.testpattern``, what
``benchmarks/source_path.py`` streams through the daemon: 5 % hits, half of them in a peak
3 codes wide, 20 000 cycles, 3 measurements, histogrammed with the calibration's bounds as
the daemon's worker does); 64 TDCs (one histogram worker's message) and 128 (the two
workers' messages of a measurement joined), ``max_returns`` 1 and 3, the ``ml`` and
``fast`` estimators (``--only street`` or ``--only pattern`` for one of the data), and
with ``--spatial`` the range stage's ``[range] spatial = true`` on 128 TDCs (the
``thesis128`` geometry's line; K 1 and 3; ``--spatial-only``: those cases alone). Each
case runs in a fresh process per tree, the trees alternating, after one untimed pass
(numba kernels, caches): best of ``--repeat`` passes over the measurements, in CPU ms per
measurement (the process's CPU time: on a shared machine a pass's wall time counts the
time its process waited for a core; the daemon's table counts CPU-seconds too). The
trees' ranges are compared (every column, NaN equal to NaN): "identical" means bit for
bit; else, where the rows, detections and flags are the same, how far the distances are
in their own sigmas and the column that moved most (relative), with how many of its
values moved beyond 1e-3 (``same``).

The implied throughput is the words a measurement holds over its cost, on one core:
cycles x TDCs x words a TDC a cycle (the chip reads every TDC out every cycle, hit or
not: 1 word, checked on the messages' class counts), at 20 k and 100 k cycles a
measurement; the range stage's cost does not grow with the cycles (it reads histograms).

    python benchmarks/range_stage.py --data DEMO/data --tree /path/to/main --tree .
                                     [--repeat 5] [--only street|pattern] [--parts]

``--parts``: below each case, the CPU ms a measurement spent inside the range path's main
steps (``PARTS_SHOWN``; a step inside another counts in both), each tree's own.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

#: one process: one case on one tree; times, and the ranges saved for the comparison
WORKER = r"""
import glob, json, sys, time
import numpy as np, pyarrow as pa, pyarrow.parquet as pq
from pipeline.io.caldir import load_calibration
from pipeline.offline.ranging import RangeCore

data, source, n_tdc, k, estimator, repeat, out, PARTS = sys.argv[1:9]
n_tdc, k, repeat = int(n_tdc), int(k), int(repeat)
cal = load_calibration(f"{data}/calibration/current")
parts = {}
if source == "pattern":  # the daemon's benchmark words, histogrammed as its worker does
    from stages.histogram import HistogramAccumulator
    from stages.testpattern import pattern_words
    for seed in range(3):
        words, _ = pattern_words(20_000, cal.n_tdc, hit_prob=0.05, rng=seed)
        acc = HistogramAccumulator(cal.n_tdc, cal.bounds)
        acc.update(words, 0)
        t = acc.snapshot().to_table(f"pattern{seed}")
        parts[f"pattern{seed}"] = [t.slice(a, 64) for a in range(0, t.num_rows, 64)]
else:
    files = sorted(glob.glob(f"{data}/stream/histograms/**/*.parquet", recursive=True))
    for f in files:
        t = pq.read_table(f)
        parts.setdefault(t["measurement"][0].as_py(), []).append(t)
batches, words = [], 0.0
for name, ts in sorted(parts.items()):
    ts = sorted(ts, key=lambda t: t["tdc"][0].as_py())
    t = pa.concat_tables(ts) if n_tdc > 64 else ts[0]
    if t.num_rows != n_tdc:
        continue
    batches.append((name, t.combine_chunks().to_batches()[0]))
    cls = sum(np.asarray(t[c], np.float64) for c in ("n_hit", "n_no_hit", "n_artifact",
                                                     "n_invalid_phase", "n_malformed"))
    words = float(np.mean(cls / np.asarray(t["cycles"], np.float64)))
if not batches:
    sys.exit(f"{data}: no histograms message of {n_tdc} TDCs ({source})")
if estimator == "spatial":  # the daemon's [range] spatial = true, the thesis's line
    from pipeline.io.geometry import load_geometry
    core = RangeCore(cal, "ml", max_returns=k, forward_histograms=False,
                     spatial=load_geometry("thesis128"))
else:
    core = RangeCore(cal, estimator, max_returns=k, forward_histograms=False)

def one(name, b):
    return core.process({"run": "bench", "measurement": name, "t_laser_win_ns": 20.0,
                         "window_ns": 80.0}, b)

res = [one(n, b) for n, b in batches]  # untimed: kernels, caches
parts = {}
if PARTS:  # CPU ms a measurement inside each named function (nested ones counted in both)
    import importlib
    for path in PARTS.split(","):
        mod_name, fn_name = path.rsplit(".", 1)
        mod = importlib.import_module(mod_name)
        fn = getattr(mod, fn_name, None)
        if fn is None:
            continue
        def timed(*a, _fn=fn, _name=fn_name, **kw):
            t0 = time.process_time()
            try:
                return _fn(*a, **kw)
            finally:
                parts[_name] = parts.get(_name, 0.0) + time.process_time() - t0
        setattr(mod, fn_name, timed)
best = float("inf")
for _ in range(repeat):
    t0 = time.process_time()
    for n, b in batches:
        one(n, b)
    best = min(best, time.process_time() - t0)
table = pa.Table.from_batches([b for r in res for _, b in r])
np.savez(out, **{c: np.asarray(table[c].to_numpy(zero_copy_only=False))
                 for c in table.column_names})
print(json.dumps({"ms": best / len(batches) * 1e3, "measurements": len(batches),
                  "words_per_tdc_cycle": words,
                  "parts": {k: v / (repeat * len(batches)) * 1e3 for k, v in parts.items()}}))
"""


#: the steps ``--parts`` times (a function a tree lacks is left out of its column)
PARTS_SHOWN = (
    "pipeline.offline.ranging.estimate_returns", "stages.ranging.multi.estimate",
    "stages.ranging.ml._ml_numba", "stages.ranging.ml._ml_setup", "stages.ranging.ml._detect",
    "stages.ranging.multi.return_fwhm", "stages.ranging.multi._masked",
    "stages.ranging.multi._rows", "pipeline.offline.ranging.time_axis",
    "pipeline.offline.ranging._unresolved", "pipeline.offline.ranging.ranges_table")
PARTS = ",".join(PARTS_SHOWN)


def same(a: Path, b: Path) -> str:
    """"identical" (every column bit for bit, NaN equal to NaN); else, where the rows,
    detections and flags are the same, how far the numbers are: the distances in their
    own sigmas (``sigma_m``), the other numbers relative (the widths summed in another
    order, the ML fit's stop at a step below a part of its sigmas); "DIFFER: column"
    where a row, a detection or a flag differs."""
    x, y = np.load(a, allow_pickle=True), np.load(b, allow_pickle=True)
    if sorted(x.files) != sorted(y.files):
        return "DIFFER: columns"
    if any(x[c].shape != y[c].shape for c in x.files):
        return "DIFFER: rows"
    d_sig, rel, worst, big = 0.0, 0.0, "", 0
    for c in x.files:
        u, v = x[c], y[c]
        if u.dtype.kind != "f":
            if not np.array_equal(u, v):
                return f"DIFFER: {c}"
            continue
        if np.array_equal(u, v, equal_nan=True):
            continue
        if not np.array_equal(np.isnan(u), np.isnan(v)):
            return f"DIFFER: {c} (NaN)"
        f = np.isfinite(u) & (u != v)
        if c == "distance_m":
            s_ = np.asarray(x["sigma_m"], np.float64)[f]
            d_sig = max(d_sig, float(np.max(np.abs(u[f] - v[f]) / s_)))
            continue
        r = np.abs(u[f] / v[f] - 1)
        big += int(np.sum(r > 1e-3))
        if r.max() > rel:
            rel, worst = float(r.max()), c
    if d_sig == 0 and rel == 0:
        return "identical"
    return (f"distances to {d_sig:.0e} sigma, {worst} to {rel:.0e}"
            + (f" ({big} of {x[worst].size} values beyond 1e-3)" if big else ""))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, required=True, help="a `tcspc demo` output")
    ap.add_argument("--tree", action="append", type=Path, required=True)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--only", choices=("street", "pattern"), default=None)
    ap.add_argument("--spatial", action="store_true",
                    help="also [range] spatial = true (128 TDCs, the thesis128 geometry)")
    ap.add_argument("--spatial-only", action="store_true", help="only those cases")
    ap.add_argument("--parts", action="store_true",
                    help="also the CPU ms a measurement inside the range path's main steps")
    args = ap.parse_args()
    print("$ python benchmarks/range_stage.py " + " ".join(sys.argv[1:]))
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"Python {platform.python_version()}, load average {os.getloadavg()[0]:.1f} at "
          "start (one process at a time, one core)")
    trees = [t.resolve() for t in args.tree]
    names = " | ".join(f"{t} ms" for t in args.tree)
    print(f"\n| data | TDCs | K | estimator | {names} | ranges | M words/s at 20 k / 100 k "
          "cycles (last tree) | load |")
    print("|---|---|---|---|" + "---|" * len(trees) + "---|---|---|")
    sources = [args.only] if args.only else ["street", "pattern"]
    cases = [] if args.spatial_only else [
        (src, n, k, e) for src in sources for n in (64, 128) for k in (1, 3)
        for e in ("ml", "fast")]
    if args.spatial or args.spatial_only:
        cases += [(src, 128, k, "spatial") for src in sources for k in (1, 3)]
    with tempfile.TemporaryDirectory() as tmp:
        for source, n_tdc, k, est in cases:
            got, outs = [], []
            for i, tree in enumerate(trees):
                out = Path(tmp) / f"{source}-{n_tdc}-{k}-{est}-{i}.npz"
                env = {**os.environ, "PYTHONPATH": str(tree)}
                res = subprocess.run(
                    [sys.executable, "-c", WORKER, str(args.data.resolve()), source,
                     str(n_tdc), str(k), est, str(args.repeat), str(out),
                     PARTS if args.parts else ""],
                    capture_output=True, text=True, env=env, cwd=tree)
                if res.returncode != 0:
                    raise SystemExit(f"{tree}: {n_tdc} TDCs K={k} {est} failed:\n"
                                     f"{res.stderr[-2000:]}")
                got.append(json.loads(res.stdout.strip().splitlines()[-1]))
                outs.append(out)
            ok = "; ".join(same(outs[0], o) for o in outs[1:])
            last = got[-1]
            rate = [c * n_tdc * last["words_per_tdc_cycle"] / (last["ms"] * 1e-3) / 1e6
                    for c in (20_000, 100_000)]
            print(f"| {source} | {n_tdc} | {k} | {est} | "
                  + " | ".join(f"{g['ms']:.2f}" for g in got)
                  + f" | {ok} | {rate[0]:.0f} / "
                  f"{rate[1]:.0f} | {os.getloadavg()[0]:.1f} |", flush=True)
            if args.parts:
                for name in PARTS_SHOWN:
                    print(f"|   {name} | | | | " + " | ".join(
                        f"{g['parts'].get(name.rsplit('.', 1)[1], float('nan')):.2f}"
                        for g in got) + " | | | |")
    print(f"\n({got[-1]['measurements']} measurements a case; "
          f"{got[-1]['words_per_tdc_cycle']:.3f} words a TDC a cycle in the messages)")


if __name__ == "__main__":
    main()
