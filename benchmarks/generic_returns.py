"""Speed of `tcspc range` on generic histograms with one and with up to three returns a
zone: the TMF8820's 80 captures (tests/data/tmf8820, 9 zones and a reference each)
calibrated on the three nearest 0.10, 0.20 and 0.30 m, ranged whole by ml and fast with
``max_returns`` 1 and 3. With ``--old CHECKOUT`` (another tree of this repository, e.g.
main before a change; the data and calibration made here) the same runs there too, in
turn with this tree's (best of ``--rounds`` each, one process a tree and round), and the
distances of both compared (bit for bit, else the largest difference). Histograms/s
count the reference rows (800 a file), as ``benchmarks/multi_return.py`` does. Prints
the command, the machine and a Markdown table.

    python benchmarks/generic_returns.py [--old CHECKOUT] [--rounds 3] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.datapath import emit, machine  # noqa: E402

RUNS = [(e, k) for e in ("ml", "fast") for k in (1, 3)]


def prepare(tmp: Path) -> None:
    """The captures as generic histograms and their calibration, in ``tmp``."""
    from pipeline.io.tmf8820 import convert
    from pipeline.offline import generic as g

    h, truth_csv = tmp / "h.parquet", tmp / "truth.csv"
    convert(ROOT / "tests" / "data" / "tmf8820" / "distance_data_even.json", h, truth_csv)
    truth = {k[0]: v for k, v in g.read_truth(truth_csv).items()}
    names = list(truth)
    near = [min(names, key=lambda n, x=x: abs(truth[n] - x)) for x in (0.10, 0.20, 0.30)]
    (tmp / "cal.csv").write_text("measurement,distance_m\n" + "".join(
        f"{n},{truth[n]}\n" for n in near))
    g.calibrate_distance(h, tmp / "cal.csv").save(tmp / "cal")


#: one round, run by ``python -c`` in a process whose path holds only the tree timed (its
#: argv: the data's directory, a tag): each run's seconds (after one untimed run of each)
#: as JSON, the distances kept beside the data
TIMED = """
import json, sys, time
from pathlib import Path
import numpy as np
from pipeline.offline import generic as g
tmp, tag = Path(sys.argv[1]), sys.argv[2]
runs = [(e, k) for e in ("ml", "fast") for k in (1, 3)]
cal = g.DistanceCalibration.load(tmp / "cal")
h = tmp / "h.parquet"
for est, k in runs:
    g.range_generic(h, cal, estimator=est, max_returns=k)
out = {"module": g.__file__}
for est, k in runs:
    t0 = time.perf_counter()
    table, _ = g.range_generic(h, cal, estimator=est, max_returns=k)
    out[f"{est}/{k}"] = time.perf_counter() - t0
    np.save(tmp / f"d-{tag}-{est}-{k}.npy", table.column("distance_m").to_numpy())
print(json.dumps(out))
"""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--old", type=Path, default=None, help="another tree to time beside")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    tmp = Path(tempfile.mkdtemp(prefix="generic-returns-"))
    prepare(tmp)
    trees = {"this tree": ROOT} | ({"--old": args.old.resolve()} if args.old else {})
    best = {t: {} for t in trees}
    for _ in range(args.rounds):
        for i, (name, tree) in enumerate(trees.items()):
            env = {**os.environ, "PYTHONPATH": str(tree)}
            r = subprocess.run([sys.executable, "-c", TIMED, str(tmp), str(i)],
                               capture_output=True, text=True, env=env, check=True, cwd=tmp)
            got = json.loads(r.stdout.splitlines()[-1])
            if not Path(got.pop("module")).resolve().is_relative_to(tree):
                sys.exit(f"{name}: its process imported another tree's code")
            for key, s in got.items():
                best[name][key] = min(best[name].get(key, np.inf), s)
    n = 800  # 80 captures x (9 zones + the reference)
    lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
             "| estimator | returns a zone | " + " | ".join(
                 f"histograms/s, {t}" for t in trees) + (" | speed-up | distances |"
                                                         if args.old else " |"),
             "|---|---|" + "---|" * len(trees) + ("---|---|" if args.old else "")]
    for est, k in RUNS:
        key = f"{est}/{k}"
        cells = [f"{n / best[t][key]:,.0f}" for t in trees]
        if args.old:
            a, b = (np.load(tmp / f"d-{i}-{est}-{k}.npy") for i in (0, 1))
            same = ("identical" if np.array_equal(a, b, equal_nan=True) else
                    f"differ: {np.nanmax(np.abs(a - b)):.2g} m" if a.shape == b.shape
                    else f"differ: {a.size} against {b.size} rows")
            cells += [f"{best['--old'][key] / best['this tree'][key]:.1f}x", same]
        lines.append(f"| {est} | {k} | " + " | ".join(cells) + " |")
    emit(lines, args.out)


if __name__ == "__main__":
    main()
