"""Stream throughput: capture replay -> histogram stage(s) -> [range] -> parquet sink.

Writes a capture of synthetic words (5 % hits unless --hit-prob), then measures words/s
(a) of the bare three-process graph started by hand, without the journal and with it (raw
segments, and zstd frames: the default), and (b) of the daemon (`tcspc daemon`: journal
on, histograms per measurement, 1 or 2 histogram workers by TDC range, the range stage
when --calibration is given), beside the raw ZeroMQ throughput of 1 MiB messages between
two processes, and the disk's sequential write rate with fdatasync.

    python benchmarks/stream.py [--words 128e6] [--calibration data/calibration/current]
        [--hit-prob 0.05]
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402
from pipeline.io.capture import CaptureWriter  # noqa: E402
from stages.testpattern import pattern_words  # noqa: E402

CLI = [sys.executable, "-m", "pipeline.cli", "stage"]


def zmq_baseline(tmp: Path, mib: int = 2048) -> float:
    """Bytes/s of 1 MiB messages from one process to another over ipc://, zero-copy on
    both ends (what ZeroMQ itself does, without Python's copies)."""
    code = ("import zmq,sys,time;c=zmq.Context();s=c.socket(zmq.PULL);s.bind(sys.argv[1]);"
            "n=int(sys.argv[2]);s.recv();t=time.perf_counter();"
            "exec('for _ in range(n-1): s.recv(copy=False)');"
            "print((n-1)*(1<<20)/(time.perf_counter()-t))")
    ep = f"ipc://{tmp}/zb"
    rx = subprocess.Popen([sys.executable, "-c", code, ep, str(mib)], stdout=subprocess.PIPE,
                          text=True)
    import zmq

    ctx = zmq.Context()
    tx = ctx.socket(zmq.PUSH)
    tx.setsockopt(zmq.SNDHWM, 4)
    tx.connect(ep)
    payload = np.zeros(1 << 20, np.uint8).tobytes()
    for _ in range(mib):  # zero-copy: the payload outlives the run
        tx.send(payload, copy=False)
    out = float(rx.communicate(timeout=120)[0])
    tx.close()
    ctx.term()
    return out


def run_graph(tmp: Path, capture: Path, journal: str | None) -> float:
    """``journal``: None (off), "zstd" or "none" (raw segments)."""
    tag = f"j{journal}" if journal else "n"
    ep_h, ep_s = f"ipc://{tmp}/h{tag}", f"ipc://{tmp}/s{tag}"
    sink = subprocess.Popen(CLI + ["sink", "--pull", ep_s, "--out", str(tmp / f"data{tag}")],
                            stderr=subprocess.DEVNULL)
    hist = subprocess.Popen(CLI + ["histogram", "--pull", ep_h, "--push", ep_s],
                            stderr=subprocess.DEVNULL)
    time.sleep(2.0)  # both stages up before the clock starts
    src = CLI + ["source-capture", str(capture), "--push", ep_h]
    if journal:
        src += ["--journal", str(tmp / f"journal-{journal}"), "--journal-compression", journal]
    t0 = time.perf_counter()
    subprocess.run(src, check=True, stderr=subprocess.DEVNULL)
    for p in (hist, sink):
        p.wait(timeout=600)
    return time.perf_counter() - t0


def disk_rate(tmp: Path, mib: int = 1024) -> float:
    """Bytes/s of 4 MiB writes with an fdatasync per write (what a journal needs)."""
    import os

    block = np.ones(4 << 20, np.uint8).tobytes()
    t0 = time.perf_counter()
    with open(tmp / "disk.bin", "wb") as fh:
        for _ in range(mib // 4):
            fh.write(block)
            fh.flush()
            os.fdatasync(fh.fileno())
    dt = time.perf_counter() - t0
    (tmp / "disk.bin").unlink()
    return mib * (1 << 20) / dt


def run_daemon(tmp: Path, capture: Path, workers: int, calibration: str | None,
               tag: str, compression: str = "zstd") -> tuple[float, dict]:
    """Seconds from the source's start to the last dataset file, and the daemon's result."""
    import datetime as dt
    import json

    state, out = tmp / f"state-{tag}", tmp / f"out-{tag}"
    topo = tmp / f"{tag}.toml"
    topo.write_text(f"""
[daemon]
state = "{state}"
journal_compression = "{compression}"
[source]
kind = "capture"
capture = "{capture}"
[histogram]
workers = {workers}
measurement_cycles = 20000
""" + (f'[range]\ncalibration = "{calibration}"\n' if calibration else "")
        + f'[sink]\nout = "{out}"\n')
    res = subprocess.run([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                          str(topo), "--run", tag], capture_output=True, text=True, check=True)
    log = (state / "logs" / "source.log").read_text().splitlines()
    t_start = dt.datetime.fromisoformat(log[0].split()[1]).timestamp()
    t0 = float(next(x for x in log if x.startswith("first batch sent at")).split()[-1])
    t1 = max(p.stat().st_mtime for p in out.rglob("part-*.parquet"))
    return t1 - t0, t0 - t_start, json.loads(res.stdout)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--words", type=float, default=128e6)
    ap.add_argument("--out", type=Path, default=Path("benchmarks/results/stream.md"))
    ap.add_argument("--calibration", default=None,
                    help="A 128-TDC calibration directory: adds the range stage.")
    ap.add_argument("--hit-prob", type=float, default=0.05,
                    help="Share of hit words (5 %%: photon-starving; the street scene ~18 %%).")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(dir=Path.cwd()) as d:
        tmp = Path(d)
        block, _ = pattern_words((1 << 22) // 128, 128, hit_prob=args.hit_prob, rng=1)
        reps = max(1, int(args.words) // block.size)
        with CaptureWriter(tmp / "cap", 128) as w:
            for _ in range(reps):
                w.write(block)
        n = reps * block.size
        base = zmq_baseline(tmp)
        disk = disk_rate(tmp)
        journal_bytes: dict[str, int] = {}
        lines = [f"command: `python {' '.join(sys.argv)}`", f"machine: {machine()}", "",
                 f"synthetic words, {args.hit_prob:.0%} hits", "",
                 "| path | words | s | M words/s | MB/s |", "|---|---:|---:|---:|---:|",
                 f"| raw ZeroMQ, 1 MiB messages, ipc:// | | | {base / 4e6:,.0f} | "
                 f"{base / 1e6:,.0f} |",
                 f"| disk, 4 MiB writes + fdatasync | | | {disk / 4e6:,.0f} | "
                 f"{disk / 1e6:,.0f} |"]
        label = {None: "", "none": " (journal on, raw segments)",
                 "zstd": " (journal on, zstd segments)"}
        for journal in (None, "none", "zstd"):
            dt = run_graph(tmp, tmp / "cap.bin", journal)
            lines.append(f"| replay -> histogram -> sink{label[journal]}"
                         f" | {n:,} | {dt:.2f} | {n / dt / 1e6:,.1f} | {4 * n / dt / 1e6:,.0f} |")
            if journal:
                size = sum(p.stat().st_size for p in (tmp / f"journal-{journal}").glob("*.bin*"))
                journal_bytes[journal] = size
        starts = []
        for workers, comp in ((1, "none"), (1, "zstd"), (2, "zstd")):
            dt, startup, res = run_daemon(tmp, tmp / "cap", workers, args.calibration,
                                          f"d{workers}{comp}", comp)
            acc = res["accounting"]
            assert acc["balanced"] and acc["words_in"] == n, acc
            lines.append(f"| daemon: replay -> {workers} histogram worker(s) -> "
                         f"{'range -> ' if args.calibration else ''}sink{label[comp]} | "
                         f"{n:,} | {dt:.2f} | {n / dt / 1e6:,.1f} | {4 * n / dt / 1e6:,.0f} |")
            starts.append(startup)
        lines.append("\nThe hand-started rows' wall time includes the source process's "
                     "start-up (~0.7 s). The daemon rows run from the source's first batch "
                     "to the last dataset file, every word accounted for (accounting "
                     "balanced); the graph's start-up before the first batch took "
                     + ", ".join(f"{x:.1f}" for x in starts) + " s. Journal on disk: "
                     + f"raw {journal_bytes['none'] / 1e6:,.0f} MB, zstd "
                     + f"{journal_bytes['zstd'] / 1e6:,.0f} MB "
                     + f"({journal_bytes['zstd'] / journal_bytes['none']:.1%}).")
    emit(lines, args.out)


if __name__ == "__main__":
    main()
