"""Instrument files through the whole command, as a user runs them: `tcspc histogram` and
`tcspc decode` on the shared 106 k-record HydraHarp T3 file (tests/data/picoquant), on a
synthetic 50 M-record HydraHarp T3 file (``write_ptu``, photons on 4 inputs, an overflow
record every 1,000) and on the LinoSPAD2 sample (tests/data/linospad2), with a chip
capture of the same words as the 106 k file (``tcspc pattern``) for reference.

Each command runs from each source tree given (``--tree``, e.g. the main branch's and
this one's: the same files, the same run, interleaved so a loaded machine weighs on both
alike), each with its own bytecode and numba caches under a temporary directory, after
one untimed run (bytecode, kernels); best and median wall time of ``--repeat`` runs, the
median CPU time (user + system, all threads: steadier than the wall on a shared machine)
and the load average after each row. The files are read from the page cache (written or
read just before). The first rows are the floor: the interpreter with the libraries an
instrument command needs (numpy, pyarrow and its parquet writer, click), as a plain
``python -c`` loads them and with one OpenBLAS thread (``OPENBLAS_NUM_THREADS=1``, as the
commands load numpy), and `tcspc --help`. Threads: the commands' default
(``TCSPC_THREADS`` if set, else the cores, at most 4).

    python benchmarks/instruments_startup.py --tree /path/to/main --tree . [--repeat 5]
                                             [--records 50000000]
"""

from __future__ import annotations

import argparse
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HYDRAHARP = ROOT / "tests" / "data" / "picoquant" / "hydraharp_v20_t3.ptu"
LINOSPAD2 = ROOT / "tests" / "data" / "linospad2" / "test_data_2212b.dat"


#: one process: the file's pass as the command makes it, best of argv[2] after one untimed
PASS = """
import sys, time
from pipeline.offline.instruments import histogram_ptu
histogram_ptu(sys.argv[1])
best = float("inf")
for _ in range(int(sys.argv[2])):
    t0 = time.perf_counter()
    histogram_ptu(sys.argv[1])
    best = min(best, time.perf_counter() - t0)
print(best)
"""


def env_for(tree: Path, cache: Path) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    return {**env, "PYTHONPATH": str(tree), "PYTHONPYCACHEPREFIX": str(cache / "pyc"),
            "NUMBA_CACHE_DIR": str(cache / "numba")}


def run(cmd: list[str], env: dict) -> tuple[float, float]:
    """(wall, CPU) seconds of ``cmd`` in a fresh process."""
    t0 = time.perf_counter()
    # (cwd: `python -m` puts the working directory first on the path, before PYTHONPATH)
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env,
                            cwd=env["PYTHONPATH"])
    stderr = proc.stderr.read()
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.stderr.close()
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed ({proc.returncode}):\n"
                         f"{stderr[-2000:].decode(errors='replace')}")
    return wall, usage.ru_utime + usage.ru_stime


def big_t3(path: Path, records: int) -> Path:
    import numpy as np

    sys.path.insert(0, str(ROOT))
    from pipeline.io.ptu import write_ptu

    def chunks():
        rng = np.random.default_rng(0)
        step = 1 << 22
        for start in range(0, records, step):
            n = min(step, records - start)
            ch = rng.integers(0, 4, n, dtype=np.uint32)
            dt = rng.integers(0, 3000, n, dtype=np.uint32)
            ns = rng.integers(0, 1024, n, dtype=np.uint32)
            w = (ch << 25) | (dt << 10) | ns
            w[999::1000] = np.uint32((1 << 31) | (63 << 25) | 1)  # overflow records
            yield w

    return write_ptu(path, 0x01010304, chunks(), n_records=records)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tree", action="append", type=Path, required=True)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--records", type=int, default=50_000_000)
    args = ap.parse_args()
    print("$ python benchmarks/instruments_startup.py " + " ".join(sys.argv[1:]))
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, "
          f"{platform.python_version()}, load average {os.getloadavg()[0]:.1f} at start")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        big = big_t3(tmp / "big.ptu", args.records)
        subprocess.run([sys.executable, "-m", "pipeline.cli", "pattern", str(tmp / "chip"),
                        "--cycles", str(106_000 // 16), "--n-tdc", "16"], check=True,
                       capture_output=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        floor = "import numpy, pyarrow, pyarrow.parquet, click"
        cases = [
            (f"`python -c '{floor}'` (no tcspc)", ["-c", floor], 1),
            ("the same, `OPENBLAS_NUM_THREADS=1`", ["-c", floor, "blas1"], 1),
            ("`tcspc --help`", ["--help"], 1),
            ("histogram hydraharp 106 k", ["histogram", str(HYDRAHARP)], 1),
            ("decode hydraharp 106 k", ["decode", str(HYDRAHARP)], 1),
            ("histogram linospad2 sample", ["histogram", str(LINOSPAD2)], 1),
            ("decode linospad2 sample", ["decode", str(LINOSPAD2)], 1),
            ("histogram chip 106 k words", ["histogram", str(tmp / "chip")], 1),
            (f"histogram T3 {args.records / 1e6:g} M records", ["histogram", str(big)],
             args.records),
        ]
        caches = {t: tmp / f"cache{i}" for i, t in enumerate(args.tree)}
        print(f"\n| command | {' | '.join(str(t) for t in args.tree)} | load |")
        print("|---|" + "---|" * len(args.tree) + "---|")
        for name, argv, records in cases:
            times: dict[Path, list[float]] = {t: [] for t in args.tree}
            cpus: dict[Path, list[float]] = {t: [] for t in args.tree}
            for k in range(args.repeat + 1):
                for tree in args.tree:  # interleaved: the machine's load weighs alike
                    env = env_for(tree, caches[tree])
                    cmd = [sys.executable, *argv[:2]] if argv[0] == "-c" else \
                        [sys.executable, "-m", "pipeline.cli", *argv]
                    if argv[-1] == "blas1":
                        env["OPENBLAS_NUM_THREADS"] = "1"
                    if argv[0] not in ("-c", "--help"):
                        cmd += ["--out", str(tmp / "out.parquet"), "-q"]
                    wall, cpu = run(cmd, env)
                    if k:  # the first: bytecode and kernels
                        times[tree].append(wall)
                        cpus[tree].append(cpu)
            cells = []
            for tree in args.tree:
                best, med = min(times[tree]), statistics.median(times[tree])
                cell = (f"{best:.3f} s (median {med:.3f}, CPU "
                        f"{statistics.median(cpus[tree]):.3f})")
                if records > 1:
                    cell += f", {records / best / 1e6:.0f} M records/s"
                cells.append(cell)
            print(f"| {name} | {' | '.join(cells)} | {os.getloadavg()[0]:.1f} |", flush=True)
        # the file's pass alone (read, loop, table; no start-up), in one process per tree:
        # `histogram_ptu` as the command calls it, best of --repeat after one untimed run
        print(f"\n| `histogram_ptu` in one process, T3 {args.records / 1e6:g} M records | "
              + " | ".join(str(t) for t in args.tree) + " | load |")
        print("|---|" + "---|" * len(args.tree) + "---|")
        for threads in ("1", ""):
            cells = []
            for tree in args.tree:
                env = {**env_for(tree, caches[tree]), "TCSPC_THREADS": threads}
                res = subprocess.run([sys.executable, "-c", PASS, str(big), str(args.repeat)],
                                     env=env,
                                     cwd=tree, capture_output=True, text=True, check=True)
                best = float(res.stdout)
                cells.append(f"{best:.3f} s, {args.records / best / 1e6:.0f} M records/s")
            name = "one thread" if threads else "default threads"
            print(f"| {name} | {' | '.join(cells)} | {os.getloadavg()[0]:.1f} |", flush=True)
    print(f"\nload average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
