"""The UDP ingest alone: its CPU per word and per datagram, each thread apart, side by side
with another source tree in the same run.

A sender process paces datagram v1 (127 cycles of 128 TDCs, 5 % hits from
stages.testpattern) over loopback to ``run_udp_ingest`` (journal on, zstd) in a process of
each ``--tree``, whose messages a consumer in that process drops. Printed per tree (median
of ``--repeat``, interleaved): the ingest process's CPU-seconds and M words per
CPU-second, microseconds per datagram, each thread's CPU-seconds (read from
/proc/self/task while it runs), datagrams lost; with ``--profile``, the main thread's
CPU-time profile (cProfile with thread_time; it slows the thread, read it for shares).

    python benchmarks/udp_ingest.py --tree /path/to/main --tree . [--cycles 400000]
        [--rate 40e6] [--repeat 3] [--profile]
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
N_TDC = 128

SENDER = r'''
import socket, sys, time
port, path, rate, per = int(sys.argv[1]), sys.argv[2], float(sys.argv[3]), int(sys.argv[4])
buf, dgs, i = open(path, "rb").read(), [], 0
while i < len(buf):
    n = int.from_bytes(buf[i:i + 4], "little")
    dgs.append(buf[i + 4:i + 4 + n])
    i += 4 + n
out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
out.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
sys.stdin.readline()  # the ingest listens
t0 = time.perf_counter()
for k, d in enumerate(dgs):
    ahead = k * per / rate - (time.perf_counter() - t0)
    if ahead > 0:
        time.sleep(ahead)
    out.sendto(d, ("127.0.0.1", port))
'''

INGEST = r'''
import cProfile, io, json, os, pstats, subprocess, sys, threading, time
import zmq
from pipeline.stream.udp import run_udp_ingest, udp_socket

dgs, rate, per, n_tdc, journal, profile = sys.argv[1:7]
TCK = os.sysconf("SC_CLK_TCK")


def cpu(tid):
    f = open(f"/proc/self/task/{tid}/stat").read().rsplit(")", 1)[1].split()
    return (int(f[11]) + int(f[12])) / TCK


ctx = zmq.Context()
ep = f"ipc://{journal}.sock"
rx = ctx.socket(zmq.PULL)
rx.bind(ep)


def drain():  # the consumer: takes the messages, drops them
    while True:
        frames = rx.recv_multipart()
        if b'"stop"' in bytes(frames[0][:300]):
            return


threading.Thread(target=drain, daemon=True, name="consumer").start()
sock = udp_socket("127.0.0.1:0")
sender = subprocess.Popen([sys.executable, "-c", sys.stdin.read(), str(sock.getsockname()[1]),
                           dgs, rate, per], stdin=subprocess.PIPE, text=True)
base = {t: cpu(t) for t in os.listdir("/proc/self/task")}
seen, res = {}, {}


def watch():  # each thread's CPU while it lives (they end with the ingest)
    while "s" not in res:
        names = {str(t.native_id): t.name for t in threading.enumerate()}
        for t in os.listdir("/proc/self/task"):
            try:
                seen[names.get(t, "zmq/other") + ":" + t] = cpu(t) - base.get(t, 0.0)
            except OSError:
                pass
        time.sleep(0.02)


threading.Thread(target=watch, daemon=True, name="watch").start()
prof = cProfile.Profile(time.thread_time) if profile == "1" else None
c0 = time.process_time()
sender.stdin.write("go\n")
sender.stdin.flush()
if prof:
    prof.enable()
s = run_udp_ingest(sock, ep, run="b", journal=journal, context=ctx, n_tdc=int(n_tdc),
                   gate_ps=140_000, first_seq=0, idle_s=5)
if prof:
    prof.disable()
total = time.process_time() - c0
res["s"] = s
time.sleep(0.05)
sender.wait()
threads = {}
for k, v in seen.items():
    name = k.split(":")[0]
    if name not in ("watch", "consumer"):
        name = {"MainThread": "main"}.get(name, name)
        threads[name] = threads.get(name, 0.0) + v
harness = sum(v for k, v in seen.items() if k.split(":")[0] in ("watch", "consumer"))
out = {"cpu_s": total - harness, "threads": threads, "words": s.words,
       "datagrams": s.datagrams, "lost": s.lost_datagrams, "ring_dropped": s.ring_dropped}
if prof:
    text = io.StringIO()
    pstats.Stats(prof, stream=text).sort_stats("tottime").print_stats(14)
    out["profile"] = text.getvalue()
print(json.dumps(out))
'''


def datagrams(path: Path, cycles: int, rng: int = 0) -> tuple[int, int]:
    """The capture as datagram v1, length-prefixed into ``path``: (datagrams, words each)."""
    sys.path.insert(0, str(ROOT))
    from pipeline.stream import datagram
    from stages.testpattern import pattern_words

    words, _ = pattern_words(cycles, N_TDC, hit_prob=0.05, rng=rng)
    per = (datagram.MAX_PAYLOAD - datagram.HEADER.size) // (4 * N_TDC)
    n = 0
    with open(path, "wb") as f:
        for i, c in enumerate(range(0, cycles, per)):
            d = datagram.encode(words[c * N_TDC:min(c + per, cycles) * N_TDC], i, c, N_TDC,
                                140_000, last=c + per >= cycles)
            f.write(len(d).to_bytes(4, "little") + d)
            n += 1
    return n, per * N_TDC


def run(tree: Path, dgs: Path, rate: float, per: int, tmp: Path, profile: bool) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree)}
    journal = tempfile.mkdtemp(dir=tmp)
    p = subprocess.run([sys.executable, "-c", INGEST, str(dgs), str(rate), str(per),
                        str(N_TDC), journal, "1" if profile else "0"], input=SENDER,
                       capture_output=True, text=True, env=env, cwd=tree, timeout=600)
    if p.returncode != 0:
        raise SystemExit(f"ingest from {tree} failed:\n{p.stderr[-3000:]}")
    return json.loads(p.stdout.strip().splitlines()[-1])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tree", action="append", type=Path, default=[])
    ap.add_argument("--cycles", type=int, default=400_000)
    ap.add_argument("--rate", type=float, default=40e6, help="words/s the sender paces")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--profile", action="store_true")
    args = ap.parse_args()
    trees = [t.resolve() for t in args.tree] or [ROOT]
    print("$ python benchmarks/udp_ingest.py " + " ".join(sys.argv[1:]))
    sys.path.insert(0, str(ROOT))
    from benchmarks.datapath import machine

    print(f"machine: {machine()}; load average {os.getloadavg()[0]:.1f} at start (shared "
          "with other work)")
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        n, per = datagrams(tmp / "dgs.bin", args.cycles)
        print(f"{n:,} datagrams of {per:,} words ({N_TDC} TDCs, 5 % hits), paced at "
              f"{args.rate / 1e6:.0f} M words/s; journal zstd; the consumer drops the "
              "messages\n")
        got: dict[Path, list[dict]] = {t: [] for t in trees}
        for _ in range(args.repeat):
            for t in trees:
                got[t].append(run(t, tmp / "dgs.bin", args.rate, per, tmp, False))
        for t, rs in got.items():
            cpu = float(np.median([r["cpu_s"] for r in rs]))
            words = rs[0]["words"]
            runs = ", ".join(f"{r['cpu_s']:.2f}" for r in rs)
            print(f"{t}: {cpu:.2f} CPU-s, {words / cpu / 1e6:.0f} M words per CPU-second, "
                  f"{cpu / rs[0]['datagrams'] * 1e6:.0f} us per datagram (median of "
                  f"{len(rs)}; runs {runs}); lost "
                  f"{[r['lost'] for r in rs]}, ring dropped {[r['ring_dropped'] for r in rs]}")
            for name in sorted({k for r in rs for k in r["threads"]}):
                s = float(np.median([r["threads"].get(name, 0.0) for r in rs]))
                print(f"    thread {name:12s} {s:5.2f} CPU-s")
        if args.profile:
            for t in trees:
                print(f"\n{t}: the main thread's CPU-time profile (cProfile, thread_time)")
                print(run(t, tmp / "dgs.bin", args.rate, per, tmp, True)["profile"])
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
