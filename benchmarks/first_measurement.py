"""Time to the first measurement: from ``tcspc daemon``'s start to the first parquet file of
each dataset in the sink's output, with the stages forked from the pre-started server
(``[daemon] fork_server = true``, the default; pipeline.stream.forkstart) and exec'd one
interpreter each (``false``), runs interleaved.

The graph: a capture replay of the demo's street scene (128 TDCs; ``--data``, the directory
``make demo`` wrote: ``raw/street.bin`` and ``calibration/current``), 2 histogram workers,
a measurement per ``--measurement-cycles`` cycles, the journal on, the sink; with
``--range`` the range stage too (ml, the demo's calibration). The time is the daemon's
process start (``Popen``) to the file's appearance, polled every 5 ms; "stages forked" is
the daemon's log line of the stages' start (its own start, topology and state checks), and
"first batch" the source's first message, from its log.

    python benchmarks/first_measurement.py [--data data] [--repeat 5] [--range]
        [--measurement-cycles 20000] [--forked-only] [--code DIR] [--keep DIR]
"""

from __future__ import annotations

import argparse
import datetime as dt
import glob
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def one(tmp: Path, data: Path, fork: bool, rng: bool, mc: int, tag: str,
        code: Path = ROOT) -> dict:
    cal = (data / "calibration" / "current").resolve()
    state, out = tmp / f"state-{tag}", tmp / f"out-{tag}"
    topo = tmp / f"topo-{tag}.toml"
    topo.write_text(f"""
[daemon]
state = "{state}"
fork_server = {str(fork).lower()}
[source]
kind = "capture"
capture = "{(data / 'raw' / 'street').resolve()}"
[histogram]
workers = 2
measurement_cycles = {mc}
calibration = "{cal}"
{f'[range]{chr(10)}calibration = "{cal}"' if rng else ''}
[sink]
out = "{out}"
""")
    env = {**os.environ, "PYTHONPATH": str(code)}
    t0 = time.time()
    with open(tmp / f"daemon-{tag}.log", "w") as log:
        p = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                              str(topo), "--run", "bench"], stdout=subprocess.DEVNULL,
                             stderr=log, env=env, cwd=code)
        first: dict[str, float] = {}
        while p.poll() is None:
            for k in ("histograms", "ranges"):
                if k not in first and glob.glob(f"{out}/{k}/date=*/run=bench/*.parquet"):
                    first[k] = time.time() - t0
            time.sleep(0.005)
    if p.returncode != 0:
        raise SystemExit(f"the daemon failed ({p.returncode}): "
                         f"{(tmp / f'daemon-{tag}.log').read_text()[-2000:]}")
    first["run"] = time.time() - t0
    text = (tmp / f"daemon-{tag}.log").read_text()
    m = re.search(r"^(\S+) \S+ daemon: run bench: \d+ stages started", text, re.M)
    if m:
        first["forked"] = dt.datetime.fromisoformat(m.group(1).replace("Z", "+00:00")
                                                    ).timestamp() - t0
    src = (state / "logs" / "source.log").read_text()
    first["batch"] = float(re.findall(r"first batch sent at ([0-9.]+)", src)[-1]) - t0
    return first


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", type=Path, default=ROOT / "data",
                    help="what `make demo` wrote (raw/street.bin, calibration/current)")
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--range", action="store_true", help="the range stage too")
    ap.add_argument("--measurement-cycles", type=int, default=20_000)
    ap.add_argument("--forked-only", action="store_true",
                    help="only the stages forked from the server (no exec'd runs)")
    ap.add_argument("--code", type=Path, action="append",
                    help="the checkout whose daemon runs (default: this one's); given "
                         "twice or more, their runs interleaved, a row each")
    ap.add_argument("--keep", type=Path, help="keep the runs' state and logs here")
    args = ap.parse_args()
    if not (args.data / "raw" / "street.bin").exists() or \
            not (args.data / "calibration" / "current").exists():
        raise SystemExit(f"{args.data}: no raw/street.bin or calibration/current "
                         "(run `make demo` first, or give --data)")
    print("$ python benchmarks/first_measurement.py " + " ".join(sys.argv[1:]))
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, load average {os.getloadavg()[0]:.1f} at start")
    keys = ["forked", "batch", "histograms"] + (["ranges"] if args.range else []) + ["run"]
    codes = args.code or [ROOT]
    modes = [(code, fork) for fork in ((True,) if args.forked_only else (True, False))
             for code in codes]
    res: dict[tuple, list[dict]] = {m: [] for m in modes}
    with tempfile.TemporaryDirectory() as tmp:
        where = args.keep or Path(tmp)
        where.mkdir(parents=True, exist_ok=True)
        for k in range(args.repeat):
            for i, (code, fork) in enumerate(modes):
                res[code, fork].append(one(where, args.data, fork, args.range,
                                           args.measurement_cycles, f"{i}-{k}", code))
    print(f"load average {os.getloadavg()[0]:.1f} at the end\n")
    print("s from the daemon's start, median (min-max) of", args.repeat)
    print("| stages | " + " | ".join(keys) + " |")
    print("|---|" + "---:|" * len(keys))
    for code, fork in modes:
        cells = []
        for key in keys:
            v = [r[key] for r in res[code, fork] if key in r]
            cells.append(f"{statistics.median(v):.2f} ({min(v):.2f}-{max(v):.2f})" if v
                         else "-")
        label = f"{code}: " if len(codes) > 1 else ""
        print(f"| {label}{'forked from the server' if fork else 'an interpreter each'} | "
              + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
