"""Where the daemon's cycles go, and its words/s, side by side with another source tree in
the same run.

1. ``--codecs``: the journal's candidate codecs on the capture's words in the source's
   1 MiB chunks (zstd levels, LZ4 frames as pyarrow ships them, and the zstd-nohit frames:
   the words less their no-hit pattern, then zstd, pipeline.io.nohit): M words per
   CPU-second (best of 3, interleaved) and the bytes kept.
2. The source's work per batch of a capture replay, each step timed apart (CPU seconds of
   this process): read as stored, one swap-and-cut copy into the message
   (pipeline.stream.rawwire), and the journal's frame at its default encoding
   (``journal.DEFAULT_COMPRESSION``, on its own thread in the source).
3. ``tcspc daemon`` (journal on at each tree's default encoding, ``--workers`` histogram
   workers by TDC range,
   measurements of ``--measurement-cycles`` cycles, the sink; a range stage with
   ``--calibration``) from each ``--tree``, interleaved: words/s from the source's first
   batch to the last measurement written, the accounting balanced, and each process's
   CPU-seconds over that time (read from /proc while it runs). ``--source capture``
   replays the capture; ``--source udp`` sends it as datagram v1 (127 cycles a datagram)
   over loopback to a udp source, paced at ``--udp-rate`` words/s by a sender process on
   the same two cores (its CPU is printed apart).

    python benchmarks/source_path.py --tree /path/to/main --tree . [--cycles 500000]
        [--hit-prob 0.05] [--workers 1] [--repeat 2] [--calibration DIR] [--codecs]
        [--source capture|udp] [--udp-rate 60e6] [--measurement-cycles 20000]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import re
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

TICK = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def codec_table(capture: Path, rounds: int = 3) -> dict[str, tuple[float, float]]:
    """{codec: (M words per CPU-second, compressed / raw bytes)} on the capture's chunks."""
    import pyarrow as pa
    import zstandard

    from pipeline.io import nohit
    from pipeline.io.capture import Capture

    cap = Capture(capture)
    n_tdc = cap.meta.n_tdc
    chunk = max(1, (1 << 18) // n_tdc) * n_tdc
    chunks = [(f, np.array(w)) for f, w in cap.iter_chunks(chunk, native=False)][:200]
    zstd = {lv: zstandard.ZstdCompressor(level=lv, write_checksum=True, write_content_size=True)
            for lv in (1, -1, -3, -5, -7, -20, -50)}
    codecs = {f"zstd {lv}": lambda f, w, z=z: z.compress(memoryview(w).cast("B"))
              for lv, z in zstd.items() if lv > -20}
    lz4 = pa.Codec("lz4")
    codecs["lz4 frame (pyarrow)"] = lambda f, w: lz4.compress(memoryview(w).cast("B"),
                                                              asbytes=True)
    for lv in (1, -3, -20, -50):  # (the journal's frame: pipeline.stream.journal.FrameEncoder)
        codecs[f"zstd-nohit {lv}"] = lambda f, w, z=zstd[lv]: z.compress(
            nohit.encode(w, f, n_tdc))
    best = dict.fromkeys(codecs, float("inf"))
    size = {}
    for _ in range(rounds):  # interleaved: the machine's load weighs on all alike
        for k, fn in codecs.items():
            t = time.process_time()
            size[k] = sum(len(fn(f, w)) for f, w in chunks)
            best[k] = min(best[k], time.process_time() - t)
    raw = sum(w.nbytes for _, w in chunks)
    return {k: (raw / 4 / best[k] / 1e6, size[k] / raw) for k in codecs}


def segment_reads(capture: Path, tmp: Path, rounds: int = 3) -> dict[str, float]:
    """{encoding: M words per CPU-second} reading a closed journal segment of the capture's
    first 200 chunks back through :class:`pipeline.io.capture.Capture` (best of 3)."""
    from pipeline.io.capture import Capture
    from pipeline.stream.journal import JournalWriter, segment_path

    cap = Capture(capture)
    chunk = max(1, (1 << 18) // cap.meta.n_tdc) * cap.meta.n_tdc
    segs = {}
    for enc in ("zstd", "zstd-nohit"):
        j = JournalWriter(tmp / f"read-{enc}", "r", cap.meta.n_tdc, 140.0, compression=enc)
        for i, (f, w) in enumerate(cap.iter_chunks(chunk, native=False)):
            if i == 200:
                break
            j.append(f, w)
        j.close()
        segs[enc] = segment_path(tmp / f"read-{enc}", "r", 0, enc)
    best = dict.fromkeys(segs, float("inf"))
    for _ in range(rounds):
        for enc, seg in segs.items():
            t = time.process_time()
            n = sum(w.size for _, w in Capture(seg).iter_chunks())
            best[enc] = min(best[enc], time.process_time() - t)
    return {enc: n / b / 1e6 for enc, b in best.items()}


def source_steps(capture: Path, ranges, rounds: int = 2) -> dict[str, float]:
    from pipeline.io.capture import Capture
    from pipeline.stream.fanout import TdcSplitter
    from pipeline.stream.journal import DEFAULT_COMPRESSION, FrameEncoder
    from pipeline.stream.rawwire import RawWordsEncoder
    from schemas.words import RAW_WORDS

    cap = Capture(capture)
    n = cap.meta.n_tdc
    chunk = max(1, (1 << 18) // n) * n
    sp = TdcSplitter(n, ranges)
    journal = FrameEncoder(DEFAULT_COMPRESSION, n)
    enc = RawWordsEncoder()
    head = {"kind": "data", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
            "run": "r", "seq": 0, "step": "source", "first_word": 0, "n_tdc": 1,
            "t_laser_win_ns": 140.0}
    d: dict[str, float] = {}
    zstd = f"journal {DEFAULT_COMPRESSION} {journal.level} (its thread)"

    def tick(k, t0):
        t = time.process_time()
        d[k] = d.get(k, 0.0) + t - t0
        return t

    for _ in range(rounds):
        t = time.process_time()
        for first, w in cap.iter_chunks(chunk, native=False):
            t = tick("read as stored", t)
            journal.encode(first, w)
            t = tick(zstd, t)
            for f, view in sp.views(first, w):
                enc.frames({**head, "first_word": f}, view)
            t = tick("swap + cut + IPC, one copy", t)
    words = cap.n_words * rounds
    return {s: words / v / 1e6 for s, v in d.items()} | {
        "total (one thread)": words / sum(d.values()) / 1e6}


def _stage_name(cmd: list[str]) -> str:
    """A daemon process's name from its command line."""
    if "--name" in cmd:
        return cmd[cmd.index("--name") + 1]
    if "stage" in cmd and cmd.index("stage") + 1 < len(cmd):
        name = cmd[cmd.index("stage") + 1]
        return "source" if name.startswith(("source-", "ingest-")) else name
    return ("daemon (supervisor)" if "daemon" in cmd else
            " ".join(cmd[-2:]) or "(a process gone before it was named)")


#: the names a process has before its own command line is readable
PROVISIONAL = ("daemon (supervisor)", "(a process gone before it was named)")


class CpuWatch:
    """CPU-seconds (user + system) of a process and its descendants, by name, polled from
    /proc while they run; ``stop(t0, t1)`` gives each one's CPU between two wall times
    (the streaming, not the start-up's imports)."""

    def __init__(self, pid: int, every_s: float = 0.05):
        self.root, self.every = pid, every_s
        self.names: dict[int, str] = {}
        self.samples: dict[int, list[tuple[float, float]]] = {}
        self.done = threading.Event()
        self.thread = threading.Thread(target=self._poll, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        kids: dict[int, list[int]] = {}
        stats = {}
        now = time.time()
        for p in Path("/proc").iterdir():
            if not p.name.isdigit():
                continue
            try:
                f = (p / "stat").read_text().rsplit(")", 1)[1].split()
            except OSError:
                continue
            kids.setdefault(int(f[1]), []).append(int(p.name))
            stats[int(p.name)] = (int(f[11]) + int(f[12])) / TICK
        todo = [self.root]
        while todo:
            pid = todo.pop()
            todo += kids.get(pid, [])
            if pid not in stats:
                continue
            if pid not in self.names or (pid != self.root and self.names[pid] in PROVISIONAL):
                # (a child seen between its fork and its exec has the supervisor's command
                # line, or none: named again at the next poll)
                try:
                    cmd = Path(f"/proc/{pid}/cmdline").read_bytes().decode().split("\0")
                    comm = Path(f"/proc/{pid}/comm").read_text().strip()
                except OSError:
                    continue
                if any("multiprocessing.forkserver" in c for c in cmd):
                    # the daemon's fork server (pipeline.stream.forkstart), or a stage forked
                    # from it: named by its process name once it has set it
                    self.names[pid] = (comm if not comm.startswith("python") else
                                       "fork server" if pid in kids.get(self.root, [])
                                       else PROVISIONAL[1])
                    if self.names[pid].startswith(("source-", "ingest-")):
                        self.names[pid] = "source"
                else:
                    self.names[pid] = _stage_name([c for c in cmd if c])
                self.samples.setdefault(pid, [(now, 0.0)])  # (born in the window: from 0)
            self.samples[pid].append((now, stats[pid]))

    def _poll(self) -> None:
        while not self.done.is_set():
            self._read()
            time.sleep(self.every)

    def stop(self, t0: float, t1: float) -> dict[str, float]:
        self.done.set()
        self.thread.join()
        out: dict[str, float] = {}

        def at(samples, t):
            return max((c for s, c in samples if s <= t), default=0.0)

        for pid, samples in self.samples.items():
            name = self.names[pid]
            out[name] = out.get(name, 0.0) + at(samples, t1) - at(samples, t0)
        return out


def send_datagrams(port: int, capture: str, rate: float, status: str) -> None:
    """The sensor: the capture as datagram v1 to 127.0.0.1:port, paced at ``rate``
    words/s, the last one flagged; starts once the ingest beats (STATE/status.json)."""
    from pipeline.io.capture import Capture
    from pipeline.stream import datagram

    cap = Capture(capture)
    n = cap.meta.n_tdc
    per = (datagram.MAX_PAYLOAD - datagram.HEADER.size) // (4 * n)
    words = np.concatenate([w for _, w in cap.iter_chunks(per * n * 64)])
    total = words.size // n
    gate_ps = round(cap.meta.t_laser_win_ns * 1000)
    dgs = [datagram.encode(words[c * n:min(c + per, total) * n], i, c, n, gate_ps,
                           last=c + per >= total)
           for i, c in enumerate(range(0, total, per))]
    del words
    deadline = time.time() + 120
    while time.time() < deadline:  # the ingest listens once it beats
        try:
            src = json.loads(Path(status).read_text()).get("stages", {}).get("source", {})
            if src.get("heartbeat_age_s") is not None:
                break
        except (OSError, ValueError):
            pass
        time.sleep(0.05)
    out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    out.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    per_words = per * n
    t_first, t0 = time.time(), time.perf_counter()
    for i, dg in enumerate(dgs):
        ahead = i * per_words / rate - (time.perf_counter() - t0)
        if ahead > 0:
            time.sleep(ahead)
        out.sendto(dg, ("127.0.0.1", port))
    dt = time.perf_counter() - t0
    print(json.dumps({"sent_words": total * n, "seconds": dt, "t_first": t_first,
                      "cpu_s": time.process_time()}))


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def daemon_run(tree: Path, tmp: Path, capture: Path, workers: int, tag: str,
               calibration: str | None, source: str = "capture", n_tdc: int = 128,
               udp_rate: float = 60e6, mc: int = 20_000
               ) -> tuple[float, dict, dict[str, float], dict]:
    from pipeline.io.capture import Capture

    state, outd = tmp / f"state-{tag}", tmp / f"out-{tag}"
    topo = tmp / f"topo-{tag}.toml"
    port = _free_port()
    src = (f'kind = "capture"\ncapture = "{capture}"' if source == "capture" else
           f'kind = "udp"\nbind = "127.0.0.1:{port}"\nn_tdc = {n_tdc}\n'
           f'gate_ps = {round(Capture(capture).meta.t_laser_win_ns * 1000)}\n'
           f'first_seq = 0\nidle = 5')
    knows = "count-as-hits" in (tree / "pipeline/stream/topology.py").read_text()
    hist = (f'calibration = "{calibration}"' if calibration else  # (a tree before the key
            'artifacts = "count-as-hits"' if source == "udp" and knows else "")  # counts them)
    topo.write_text(f"""
[daemon]
state = "{state}"
[source]
{src}
[histogram]
workers = {workers}
measurement_cycles = {mc}
{hist}
{f'[range]{chr(10)}calibration = "{calibration}"' if calibration else ''}
[sink]
out = "{outd}"
""")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONDONTWRITEBYTECODE"}
    env["PYTHONPATH"] = str(tree)
    daemon = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "daemon", "--config",
                               str(topo), "--run", "bench"], stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True, env=env, cwd=tree)
    watch = CpuWatch(daemon.pid)
    sender = None
    if source == "udp":
        sender = subprocess.Popen([sys.executable, __file__, "--send", str(port), str(capture),
                                   str(udp_rate), str(state / "status.json")],
                                  stdout=subprocess.PIPE, text=True, cwd=ROOT)
    out, err = daemon.communicate(timeout=3600)
    sent = json.loads(sender.communicate(timeout=600)[0]) if sender is not None else None
    if daemon.returncode != 0 and not (source == "udp" and daemon.returncode == 3):
        raise SystemExit(f"daemon from {tree} failed ({daemon.returncode}):\n{err[-3000:]}"
                         f"\n{out[-3000:]}")
    if source == "capture":
        log = (state / "logs" / "source.log").read_text()
        first = float(re.findall(r"first batch sent at ([0-9.]+)", log)[-1])
    else:  # the sender's first datagram
        first = sent["t_first"]
    # the last measurement written (the daemon's reconciliation and exit after it are a
    # fixed cost of the run, not of its words)
    end = max(p.stat().st_mtime for p in outd.glob("*/date=*/run=bench/*.parquet"))
    acc = json.loads(out)["accounting"]
    # the steady state: from the measurement a fifth of the way in to the last (the stages'
    # start-up, which overlaps the run's first measurements, left out)
    done: dict[int, float] = {}
    for p in outd.glob("*/date=*/run=bench/part-*.parquet"):
        k = int(p.name.split("-")[1])
        done[k] = max(done.get(k, 0.0), p.stat().st_mtime)
    ks = sorted(done)
    k0 = ks[len(ks) // 5] if len(ks) >= 5 else ks[0]
    steady = {"words": (ks[-1] - k0) * mc * n_tdc, "wall": done[ks[-1]] - done[k0],
              "cpu": watch.stop(done[k0], done[ks[-1]]) if ks[-1] > k0 else {}}
    cpu = watch.stop(first, end)
    if sent is not None:
        cpu["(sender, not the daemon's)"] = sent["cpu_s"]
    return end - first, acc, cpu, steady


def main() -> None:
    if sys.argv[1:2] == ["--send"]:  # (the sender process of a udp run)
        port, capture, rate, status = sys.argv[2:6]
        return send_datagrams(int(port), capture, float(rate), status)
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tree", action="append", type=Path, default=[])
    ap.add_argument("--cycles", type=int, default=500_000)
    ap.add_argument("--n-tdc", type=int, default=128)
    ap.add_argument("--hit-prob", type=float, default=0.05)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--capture", type=Path, default=None,
                    help="replay this capture (e.g. a simulated scene's, whose calibration "
                         "--calibration is) instead of the test pattern")
    ap.add_argument("--times", type=int, default=1,
                    help="with --capture: its words this many times over (one run)")
    ap.add_argument("--calibration", default=None)
    ap.add_argument("--measurement-cycles", type=int, default=20_000)
    ap.add_argument("--codecs", action="store_true", help="the journal codecs' table")
    ap.add_argument("--source", choices=("capture", "udp"), default="capture")
    ap.add_argument("--udp-rate", type=float, default=60e6, help="words/s the sender paces")
    args = ap.parse_args()
    if args.calibration:  # (each tree's daemon runs in that tree)
        args.calibration = str(Path(args.calibration).resolve())
    print("$ python benchmarks/source_path.py " + " ".join(sys.argv[1:]))
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, Python "
          f"{platform.python_version()}, load average {os.getloadavg()[0]:.1f} at start "
          "(shared with other work)")
    from pipeline.io.capture import CaptureWriter
    from pipeline.stream.fanout import equal_ranges
    from stages.testpattern import pattern_words

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        if args.capture is not None:  # a scene's words, the same chip as its calibration
            from pipeline.io.capture import Capture

            src = Capture(args.capture)
            words = src.read_words(0, src.n_words)
            args.n_tdc, gate = src.meta.n_tdc, src.meta.t_laser_win_ns
            with CaptureWriter(tmp / "cap", args.n_tdc, src.meta.window_ns, gate,
                               kind="range") as w:
                for _ in range(args.times):
                    w.write(words)
            hits = float(np.mean((words.astype(np.uint32) & 0x7FFFF000) != 0))
            what = f"{args.capture.name} x {args.times}, ~{hits:.1%} words with a code"
            n_words = words.size * args.times
        else:
            words, _ = pattern_words(args.cycles, args.n_tdc, hit_prob=args.hit_prob, rng=0)
            gate = 140.0
            with CaptureWriter(tmp / "cap", args.n_tdc, kind="pattern") as w:
                w.write(words)
            n_words = words.size
            what = f"{args.hit_prob:.0%} hits (stages.testpattern)"
        del words
        print(f"capture: {n_words / 1e6:.1f} M words, {args.n_tdc} TDCs, {what}\n")
        if args.codecs:
            print("journal codecs on the capture's 1 MiB chunks (M words per CPU-second, "
                  "best of 3; bytes kept):")
            for k, (speed, ratio) in codec_table(tmp / "cap.bin").items():
                print(f"  {k:20s} {speed:6.0f}  {ratio:6.1%}")
            print("reading a closed segment back (Capture, M words per CPU-second, best of "
                  "3): " + "; ".join(f"{k} {v:.0f}" for k, v in
                                      segment_reads(tmp / "cap.bin", tmp).items()))
        steps = source_steps(tmp / "cap.bin", equal_ranges(args.n_tdc, args.workers))
        print(f"source steps, M words per CPU-second ({args.workers} TDC ranges): "
              + "; ".join(f"{k} {v:.0f}" for k, v in steps.items()))
        if not args.tree:
            return
        walls: dict[Path, list[float]] = {t: [] for t in args.tree}
        cpus: dict[Path, list[dict[str, float]]] = {t: [] for t in args.tree}
        steadies: dict[Path, list[dict]] = {t: [] for t in args.tree}
        for k in range(args.repeat):
            for i, tree in enumerate(args.tree):
                cal = args.calibration
                wall, acc, cpu, steady = daemon_run(tree, tmp, tmp / "cap.bin", args.workers,
                                            f"{i}-{k}", cal, args.source, args.n_tdc,
                                            args.udp_rate, args.measurement_cycles)
                lost = acc.get("lost_datagrams", 0)
                if args.source == "udp" and lost:  # (the ingest did not keep up)
                    print(f"  {tree}: {lost} datagrams lost at this rate "
                          f"({acc.get('words_in_gaps', 0):,} words); run left out")
                    continue
                if not acc.get("balanced") or acc["words_in"] != n_words:
                    raise SystemExit(f"{tree}: the run did not balance: {acc}")
                walls[tree].append(wall)
                cpus[tree].append(cpu)
                steadies[tree].append(steady)
        what = (f"udp datagram v1 paced at {args.udp_rate / 1e6:.0f} M words/s"
                if args.source == "udp" else "capture replay")
        print(f"\ndaemon ({what}), journal at each tree's default encoding, "
              f"{args.workers} histogram workers"
              f"{', range' if args.calibration else ''}, sink; M words/s from the first "
              f"batch to the last measurement written (best, median of {args.repeat}); "
              "CPU-seconds per process (median), and M words per CPU-second:")
        for tree, ws in walls.items():
            if not ws:
                continue
            print(f"  {tree}: {n_words / min(ws) / 1e6:.1f} "
                  f"(median {n_words / float(np.median(ws)) / 1e6:.1f}); balanced")
            for name in sorted({n for c in cpus[tree] for n in c}):
                s = float(np.median([c.get(name, 0.0) for c in cpus[tree]]))
                print(f"    {name:28s} {s:6.2f} CPU-s  "
                      f"{n_words / max(s, 1e-3) / 1e6:7.0f} M words/CPU-s")
        print("\nthe steady state: from the measurement a fifth of the way in to the last "
              "written (the stages' start-up left out); M words/s (best, median) and each "
              "process's M words per CPU-second (median), and the cores the processes "
              "would need at 110 M words/s:")
        for tree, st in steadies.items():
            st = [x for x in st if x["wall"] > 0 and x["words"]]
            if not st:
                continue
            rates = [x["words"] / x["wall"] / 1e6 for x in st]
            print(f"  {tree}: {max(rates):.1f} (median {float(np.median(rates)):.1f})")
            total = 0.0
            for name in sorted({n for x in st for n in x["cpu"]}):
                per = float(np.median([x["words"] / max(x["cpu"].get(name, 0.0), 1e-6)
                                       for x in st])) / 1e6
                cores = 110 / per if per < 1e5 else 0.0
                total += cores if "sender" not in name else 0.0
                print(f"    {name:28s} {per:7.0f} M words/CPU-s  {cores:5.2f} cores")
            print(f"    {'(the daemon, all)':28s} {'':7s}                 {total:5.2f} cores")
    print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
