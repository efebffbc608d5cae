"""Faults: every scenario of issue 16 against the daemon, each compared with a clean run of
the same input, as one table.

For each scenario the daemon runs the same 16-TDC scene (2 histogram workers, a histogram
per 10 000 cycles) or the same UDP datagrams, with the fault injected while it runs; its
histograms dataset is then compared measurement by measurement with the clean run's.
Columns: words (or datagrams) sent, journaled, lost silently (never journaled and not
counted as a gap, duplicate, late or rejection: must be 0), wrong measurements (differ from
the clean run: must be 0; a UDP measurement short by cycles the accounting counts as a gap
is counted, not wrong), withheld (measurements absent from the dataset, each of which
must be counted in the accounting), crashes (stage restarts), the run's end (the daemon's
state and exit status: only a run with every word of its stream in is "finished", 0) and
the run's delay against the clean run (the machine is shared: the delays are rough).

    python benchmarks/faults.py [--out benchmarks/results/faults.md] [--only WORD ...]
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.datapath import emit, machine  # noqa: E402

N, CYCLES, MC = 16, 200_000, 10_000
SCENE = (Path(__file__).resolve().parents[1] / "scenes" / "small16.toml").read_text()


def topology(d: Path, rate: float | None = 1.5e6, extra: str = "", udp_port=None,
             src_extra: str = "") -> Path:
    (d / "small.toml").write_text(SCENE)
    src = (f'kind = "udp"\nbind = "127.0.0.1:{udp_port}"\nn_tdc = {N}\nidle = 4\n'
           f'{src_extra}' if udp_port else
           f'kind = "sim"\nscene = "{d / "small.toml"}"\ncycles = {CYCLES}\nseed = 5\n'
           + (f"rate = {rate}" if rate else ""))
    mc = 640 if udp_port else MC
    (d / "topo.toml").write_text(f"""
[daemon]
state = "{d / 'state'}"
{extra}
[source]
{src}
[histogram]
workers = 2
measurement_cycles = {mc}
artifacts = "count-as-hits"
[sink]
out = "{d / 'out'}"
""")
    return d / "topo.toml"


def histograms(out: Path, run: str) -> dict:
    import polars as pl

    parts = list(out.glob(f"histograms/date=*/run={run}/*.parquet"))
    if not parts:
        return {}
    h = pl.read_parquet(parts)
    return {(m.rsplit("-m", 1)[1], t): (c, tuple(n)) for m, t, c, n in zip(
        h["measurement"], h["tdc"], h["cycles"], h["counts"].to_list(), strict=True)}


def run_daemon(topo: Path, run: str, during=None) -> tuple[dict, object, float]:
    from pipeline.stream.daemon import Supervisor
    from pipeline.stream.topology import load_topology

    sup = Supervisor(load_topology(topo, run), log=lambda m: None)
    res = {}
    t0 = time.perf_counter()
    t = threading.Thread(target=lambda: res.update(sup.run()))
    t.start()
    if during:
        during(sup)
    t.join()
    return res, sup, time.perf_counter() - t0


def wait_words(sup, words: float) -> None:
    deadline = time.time() + 120
    while sup.metrics.get("source", {}).get("words", 0) < words:
        if time.time() > deadline:
            raise RuntimeError("the source never got going")
        time.sleep(0.02)


def kill(sup, name: str) -> None:
    os.kill(sup.by_name[name].popen.pid, signal.SIGKILL)


def compare(ref: dict, got: dict) -> tuple[int, int]:
    """(wrong, withheld) measurement-TDC rows, as measurements of 16 TDCs."""
    wrong = sum(1 for k, v in got.items() if ref.get(k) != v)
    missing = sum(1 for k in ref if k not in got)
    return -(-wrong // N), -(-missing // N)


def end(res: dict) -> str:
    from pipeline.stream.daemon import exit_code, run_state

    if "end" in res:
        return res["end"]
    if "exit" in res:  # a daemon run as a process
        return f"{res.get('state', '?')} ({res['exit']})"
    state = res.get("state") or run_state({**res, "problems": res.get("problems", [])})
    return f"{state} ({exit_code({**res, 'state': state})})"


def row(name, injected, sent, res, sup, dt, ref_dt, ref, got, extra_lost=0):
    acc = res.get("accounting") or {}
    journaled = acc.get("words_in", 0)
    wrong, missing = compare(ref, got)
    # withheld measurements must each be in the accounting (a corrupt journal chunk)
    counted = {int(k) for k, _ in acc.get("corrupt_measurements", [])}
    absent = {int(k) for k, _ in ref} - {int(k) for k, _ in got}
    note = "" if not absent else (" (counted)" if absent <= counted else " (NOT counted)")
    lost = max(0, sent - journaled - acc.get("words_in_gaps", 0)) + extra_lost
    crashes = sum(res.get("restarts", {}).values())
    return (f"| {name} | {injected} | {sent:,} | {journaled:,} | {lost:,} | {wrong} | "
            f"{missing}{note} | {crashes} | {end(res)} | {dt - ref_dt:+.1f} |")


def daemon_proc(d: Path, topo: Path, run: str, stop_at: float | None = None,
                sig=signal.SIGINT) -> tuple[dict, float]:
    """``tcspc daemon`` as a process (signalled ``sig`` once the source has sent
    ``stop_at`` words): its printed result with its exit status, and its run time."""
    cmd = [sys.executable, "-m", "pipeline.cli", "daemon", "--config", str(topo), "--run",
           run]
    t0 = time.perf_counter()
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    if stop_at is not None:
        status = d / "state" / "status.json"
        while True:
            try:
                if json.loads(status.read_text())["stages"]["source"].get("words",
                                                                          0) > stop_at:
                    break
            except (OSError, ValueError, KeyError):
                pass
            time.sleep(0.05)
        p.send_signal(sig)
    out, _ = p.communicate()
    res = json.loads(out) if out.strip() else {}
    return {**res, "exit": p.returncode}, time.perf_counter() - t0


def sim_scenarios(tmp: Path, lines: list[str], only=None) -> None:
    ref_dir = tmp / "ref"
    ref_dir.mkdir()
    res, sup, ref_dt = run_daemon(topology(ref_dir), "r")
    ref = histograms(ref_dir / "out", "r")
    sent = CYCLES * N
    lines.append(row("clean run", "nothing", sent, res, sup, ref_dt, ref_dt, ref, ref))

    def scenario(name, injected, during=None, extra="", pre=None, post=None, cleanup=None):
        if only and not any(w in name for w in only):
            return
        d = tmp / name.replace(" ", "_")
        d.mkdir()
        topo = topology(d, extra=extra)
        if pre:
            pre(d, topo)
        res, sup, dt = run_daemon(topo, "r", during)
        if post:
            res = post(d, topo, res) or res
        lines.append(row(name, injected, sent, res, sup, dt, ref_dt, ref,
                         histograms(d / "out", "r")))
        if cleanup:
            cleanup(d)
        print(lines[-1], flush=True)

    scenario("kill a worker", "SIGKILL histogram-1 at 1 M words",
             lambda s: (wait_words(s, 1e6), kill(s, "histogram-1")))
    scenario("kill sink and source", "SIGKILL sink at 0.6 M, source at 1.4 M words",
             lambda s: (wait_words(s, 6e5), kill(s, "sink"), wait_words(s, 1.4e6),
                        kill(s, "source")))

    def freeze(s):  # SIGSTOP, never SIGCONT: only the daemon's heartbeat deadline helps
        wait_words(s, 1e6)
        os.kill(s.by_name["histogram-1"].popen.pid, signal.SIGSTOP)

    scenario("frozen worker", "SIGSTOP histogram-1 at 1 M words, never continued "
             "(heartbeat_deadline_s = 5)", freeze, extra="heartbeat_deadline_s = 5")

    def kill_server(s):  # (issue 38.9) the fork server the stages were forked from
        wait_words(s, 1e6)
        stat = Path(f"/proc/{s.by_name['source'].popen.pid}/stat").read_text()
        os.kill(int(stat.rsplit(")", 1)[1].split()[1]), signal.SIGKILL)

    scenario("kill the fork server", "SIGKILL the stages' fork server at 1 M words "
             "(every stage dies with it)", kill_server)

    def lost_part(d, topo, res):  # (issue 38.7) a part gone after the run's end: a daemon
        # killed while it reconciled, a disk under the sink repaired by hand
        from pipeline.stream.daemon import reconcile_offline
        from pipeline.stream.topology import load_topology

        sorted((d / "out" / "histograms").rglob("*.parquet"))[1].unlink()
        return reconcile_offline(load_topology(topo, "r"))

    scenario("a part lost, tcspc reconcile", "a histograms part deleted after the run, then "
             "`tcspc reconcile` offline", post=lost_part)

    def torn_checkpoint(s):
        wait_words(s, 1e6)
        p = s.by_name["histogram-1"].popen
        ck = s.topo.state / "checkpoints" / "r" / "histogram-1.npz"
        os.kill(p.pid, signal.SIGKILL)
        p.wait()
        ck.write_bytes(ck.read_bytes()[:100])

    scenario("corrupt checkpoint", "SIGKILL histogram-1, its checkpoint cut to 100 B",
             torn_checkpoint)

    def forged(s):
        import pyarrow as pa
        import zmq

        from pipeline.stream import wire
        from schemas import RAW_WORDS

        wait_words(s, 5e5)
        ctx = zmq.Context()
        tx = ctx.socket(zmq.PUSH)
        tx.connect(s.topo.endpoint(s.topo.histogram, "histogram-0", 0))
        head = {"kind": "data", "schema": RAW_WORDS.name, "version": RAW_WORDS.version,
                "run": "r", "seq": 1, "step": "source", "first_word": 0, "n_tdc": 8,
                "t_laser_win_ns": 140.0}
        words = pa.record_batch([pa.array(np.full(800, 0x202, np.uint32))],
                                schema=RAW_WORDS.schema)
        tx.send_multipart(wire.encode({**head, "kind": "stop"}, None))
        tx.send_multipart(wire.encode(head, words))
        for _ in range(6):
            tx.send_multipart(wire.encode({k: v for k, v in head.items()
                                           if k != "t_laser_win_ns"}, words))
        tx.send_multipart(wire.encode({**head, "date": "../../.."}, words))
        tx.close(linger=2000)
        ctx.term()

    scenario("forged and poisoned messages", "a stop, a batch, 7 bad headers, no token",
             forged)

    def corrupt_repair(d, topo, res):
        from pipeline.stream import daemon
        from pipeline.stream.journal import _entries, segment_path

        # the sink lost measurements 3 and 11 in flight; one journal frame of 3 is flipped
        for k in (3, 11):
            for p in (d / "out").glob(f"histograms/date=*/run=r/part-{k:06d}-*.parquet"):
                p.unlink()
        j = d / "state" / "journal"
        e = next(e for e in _entries(j / "r.index.jsonl") if not e.get("end")
                 and e["first_word"] <= 3 * MC * N < e["first_word"] + e["words"])
        seg = segment_path(j, "r", e["segment"], e.get("enc"))
        b = bytearray(seg.read_bytes())
        b[e["offset"] + e["bytes"] // 2] ^= 1
        seg.write_bytes(bytes(b))
        from pipeline.stream.topology import load_topology

        topo_ = load_topology(topo, "r")
        rec = daemon.reconcile(topo_)
        res = {**res, "reconciled": rec, "accounting": daemon.accounting(topo_, {}, rec)}
        res["problems"] = daemon.problems(res)
        res["state"] = daemon.run_state(res)
        return res

    scenario("corrupt journal frame", "a bit flipped in a frame the repair reads",
             post=corrupt_repair)

    def daemon_kill(d, topo):
        cmd = [sys.executable, "-m", "pipeline.cli", "daemon", "--config", str(topo),
               "--run", "r"]
        p = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        status = d / "state" / "status.json"
        while True:
            try:
                if json.loads(status.read_text())["stages"]["source"].get("words", 0) > 1e6:
                    break
            except (OSError, ValueError, KeyError):
                pass
            time.sleep(0.05)
        p.send_signal(signal.SIGKILL)
        p.wait()
        time.sleep(0.5)

    scenario("kill the daemon", "SIGKILL the daemon at 1 M words, start it again (delay: "
             "the second daemon's run only)",
             pre=daemon_kill)
    first_end = {}

    def graceful(d, topo):  # Ctrl-C; the scenario's daemon then resumes the run
        first, _ = daemon_proc(d, topo, "r", stop_at=0.6e6)
        first_end["end"] = f"{first.get('state')} ({first['exit']})"

    scenario("Ctrl-C and resume", "SIGINT the daemon at 0.6 M words, start it again "
             "(delay: the second daemon's run only)", pre=graceful,
             post=lambda d, topo, res: {**res, "end": f"{first_end['end']} then "
                                        f"{end(res)}"})

    def damaged_part(d, topo, res):
        from pipeline.stream import daemon
        from pipeline.stream.topology import load_topology

        parts = sorted((d / "out").glob("histograms/date=*/run=r/*.parquet"))
        parts[5].write_bytes(parts[5].read_bytes()[:300])  # cut short on disk
        topo_ = load_topology(topo, "r")
        rec = daemon.reconcile(topo_)
        res = {**res, "reconciled": rec, "accounting": daemon.accounting(topo_, {}, rec)}
        res["problems"] = daemon.problems(res)
        res["state"] = daemon.run_state(res)
        rebuilt = rec["rebuilt"]
        return {**res, "end": f"{end(res)}; rebuilt {len(rebuilt)} part, named"}

    scenario("damaged parquet part", "a part cut to 300 B after the run, reconciled again",
             post=damaged_part)
    if os.geteuid() == 0:
        for which, stage in (("out", "sink"), ("state", "source")):
            def full(s, which=which, stage=stage):
                # the output disk is filled before the sink's first file: the 3.2 M words
                # of the run were all written before a filler at 0.5 M words was complete
                # on the loaded machine, and the row never saw a pause
                wait_words(s, 1e5 if which == "out" else 5e5)
                filler = _fill_disk(s.topo.state if which == "state"
                                    else Path(s.topo.sink["out"]))
                deadline = time.time() + 120  # (a run that never pauses must not hang)
                while stage not in s.status()["paused"] and time.time() < deadline:
                    time.sleep(0.05)
                time.sleep(2.0)
                filler.unlink()

            def mount(d, topo, which=which):
                (d / which).mkdir()
                subprocess.run(["mount", "-t", "tmpfs", "-o", "size=48m,mode=700", "tmpfs",
                                str(d / which)], check=True)

            scenario(f"full {which} disk", f"{which} tmpfs filled for 2 s", full,
                     pre=mount, cleanup=lambda d, which=which: subprocess.run(
                         ["umount", "-l", str(d / which)]))


def udp_scenarios(tmp: Path, lines: list[str], only=None) -> None:
    from pipeline.stream import datagram
    from stages.testpattern import pattern_words

    n, cyc = 1000, 64
    words, _ = pattern_words(n * cyc, N, hit_prob=0.1, rng=3)
    dgs = [datagram.encode(words[i * cyc * N:(i + 1) * cyc * N], i, i * cyc, N, 140_000,
                           last=(i == n - 1)) for i in range(n)]

    def feed(schedule, rate, stall=None, kill_at=None, freeze_at=None, outs=None,
             fill=None):
        # ``schedule``: datagrams, or (sender, datagram) with ``outs`` the senders' sockets
        def during(sup):
            while "source" not in sup.metrics:
                time.sleep(0.05)
            port = int(sup.topo.source["bind"].rsplit(":", 1)[1])
            out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            filler = None
            t0 = time.perf_counter()
            for i, data in enumerate(schedule):
                sock = out
                if isinstance(data, tuple):
                    sock, data = outs[data[0]], data[1]
                if fill is not None and i == fill[0]:  # the state disk full for fill[1] s
                    filler = _fill_disk(sup.topo.state)
                if filler is not None and time.perf_counter() - t0 > fill[0] / rate + fill[1]:
                    filler.unlink()
                    filler = None
                if kill_at is not None and i == kill_at:
                    kill(sup, "source")  # the FPGA goes on while the ingest is down
                if freeze_at is not None and i == freeze_at:
                    os.kill(sup.by_name["histogram-1"].popen.pid, signal.SIGSTOP)
                if stall and i == 100:
                    os.kill(sup.by_name[stall].popen.pid, signal.SIGSTOP)
                if stall and i == 100 + int(3 * rate):
                    os.kill(sup.by_name[stall].popen.pid, signal.SIGCONT)
                sock.sendto(data, ("127.0.0.1", port))
                ahead = (i + 1) / rate - (time.perf_counter() - t0)
                if ahead > 0:
                    time.sleep(ahead)
            out.close()
            if freeze_at is not None:  # stopped across the end, until the supervisor ends it
                w = sup.by_name["histogram-1"]
                while not (sup.by_name["source"].finished and w.terminated):
                    time.sleep(0.2)
                os.kill(w.popen.pid, signal.SIGCONT)
        return during

    def run(name, schedule, rate, stall=None, kill_at=None, src_extra="", freeze_at=None,
            outs=None, fill=None):
        d = tmp / f"udp_{name.replace(' ', '_')}"
        d.mkdir()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        topo = topology(d, udp_port=port, src_extra=src_extra)
        if fill is not None:  # the state directory on a RAM disk to fill (root only)
            (d / "state").mkdir(mode=0o700)
            if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=48m,mode=700", "tmpfs",
                               str(d / "state")], capture_output=True).returncode:
                return None
        try:
            res, sup, dt = run_daemon(topo, "u", feed(schedule, rate, stall, kill_at,
                                                      freeze_at, outs, fill))
            res["taken"] = _journaled_datagrams(d / "state" / "journal", "u")
            return res, sup, dt, histograms(d / "out", "u")
        finally:
            if fill is not None:
                subprocess.run(["umount", "-l", str(d / "state")], capture_output=True)

    res, sup, ref_dt, ref = run("clean", dgs, 1000)

    def line(name, injected, res, sup, dt, got, n_sent, counted_too=False):
        acc = res.get("accounting") or {}
        src = sup.metrics.get("source", {})
        # lost silently: datagrams neither journaled (counted in the journal's chunks,
        # whichever ingest process took them) nor counted (duplicate, late, rejected, lost)
        taken = res["taken"]
        counted = (src.get("duplicates", 0) + sum(src.get("rejected", {}).values())
                   + acc.get("lost_datagrams", 0) + acc.get("ring_dropped_datagrams", 0)
                   + sum(b["datagrams"] for b in src.get("other_senders", {}).values()))
        lost_silent = n_sent - taken - counted
        # a measurement short by cycles the accounting counts as a gap is counted, not wrong
        short = {k for k, v in got.items() if k in ref and v != ref[k] and v[0] < ref[k][0]}
        wrong, missing = compare({k: v for k, v in ref.items() if k not in short},
                                 {k: v for k, v in got.items() if k not in short})
        gaps = acc.get("words_in_gaps", 0)
        return (f"| {name} | {injected} | {n_sent:,} datagrams | {acc.get('words_in', 0):,}"
                f" words ({taken:,} datagrams; {acc.get('lost_datagrams', 0):,} counted "
                f"lost) | {lost_silent} | {wrong} | {missing} (gaps {gaps:,} words"
                f"{f', {-(-len(short) // N)} measurement(s) short by them' if short else ''}) | "
                f"{sum(res.get('restarts', {}).values())} | {end(res)}"
                f"{_counted(acc) if counted_too else ''} | {dt - ref_dt:+.1f} |")

    lines.append(line("UDP clean", "nothing", res, sup, ref_dt, ref, n))
    print(lines[-1], flush=True)

    def want(name):
        return not only or any(word in name for word in only)

    order = list(range(n))
    rng = np.random.default_rng(0)
    for i in rng.choice(n - 2, 90, replace=False):
        order[i], order[i + 1] = order[i + 1], order[i]
    schedule = [dgs[i] for i in order]
    for i in sorted(rng.choice(n - 1, 70, replace=False), reverse=True):
        schedule.insert(i + 3, dgs[i])
    w = np.zeros(cyc * N, np.uint32)
    schedule[500:500] = [datagram.encode(w, 7, 2**62, N, 140_000),
                         datagram.encode(w, 8, 2**40, N, 140_000),
                         b"garbage", datagram.encode(w, 9, 5, 8, 140_000)[:-4]]
    if want("UDP reordered/duplicated/poisoned"):
        res, sup, dt, got = run("hostile", schedule, 1000)
        lines.append(line("UDP reordered/duplicated/poisoned",
                          "~90 swaps, 70 duplicates, 4 poisoned", res, sup, dt, got,
                          len(schedule)))
        print(lines[-1], flush=True)
    if want("UDP, a stage stalled"):
        res, sup, dt, got = run("stalled", dgs, 200, stall="histogram-0")
        lines.append(line("UDP, a stage stalled", "SIGSTOP histogram-0 for 3 s at 200/s",
                          res, sup, dt, got, n))
        print(lines[-1], flush=True)
    if want("UDP, strays before the stream"):
        strays = [datagram.encode(w, 0, 0, N, 150_000),
                  datagram.encode(w, 2**31, 0, N, 140_000),
                  datagram.encode(w, 1, 1_000_000, N, 140_000)]
        res, sup, dt, got = run("strays", [*strays, *dgs], 1000)
        lines.append(line("UDP, strays before the stream", "another gate, sequence 2^31, a "
                          "cycle 1,000,000 ahead, before datagram 0", res, sup, dt, got,
                          n + 3))
        print(lines[-1], flush=True)
    if want("UDP, a worker stopped across the end"):
        res, sup, dt, got = run("frozen", dgs, 1000, freeze_at=800)
        lines.append(line("UDP, a worker stopped across the end", "SIGSTOP histogram-1 at "
                          "datagram 800, until the ingest has ended and the supervisor has "
                          "SIGTERMed it", res, sup, dt, got, n))
        print(lines[-1], flush=True)
    if want("UDP ingest restarted"):
        res, sup, dt, got = run("restart", dgs, 200, kill_at=300,
                                src_extra=f"max_jump_cycles = {10 * cyc}")
        lines.append(line("UDP ingest restarted", "SIGKILL the ingest at datagram 300 of "
                          "1 000 (200/s); the stream goes on, past max_jump_cycles", res,
                          sup, dt, got, n))
        print(lines[-1], flush=True)
    udp_bad_days(run, line, want, dgs, words, lines)


def udp_bad_days(run, line, want, dgs, words, lines) -> None:
    """Issue 38 points 2-3: an FPGA reset, a sequence jump, a full state disk; and, in
    a "hostile" section, issue 36 point 3 and 38 point 1: other senders on the port."""
    from pipeline.stream import datagram
    from stages.testpattern import pattern_words

    n, cyc = len(dgs), 64

    def enc(i, seq, cycle, w=words, gate=140_000, last=None):
        return datagram.encode(w[i * cyc * N:(i + 1) * cyc * N], seq, cycle, N, gate,
                               last=(i == n - 1) if last is None else last)

    def emit_row(name, injected, out, n_sent):
        if out is None:
            lines.append(f"| {name} | {injected} | (skipped: a tmpfs needs root) |")
        else:
            lines.append(line(name, injected, *out, n_sent, counted_too=True))
        print(lines[-1], flush=True)

    if want("UDP, an FPGA reset (cycle counter restarted)"):
        sched = dgs[:500] + [enc(i, i - 500, (i - 500) * cyc) for i in range(500, n)]
        emit_row("UDP, an FPGA reset (cycle counter restarted)", "sequence and cycle "
                 "restart at 0 at datagram 500", run("reset", sched, 1000), n)
    if want("UDP, an FPGA reset (cycle counter continued)"):
        sched = dgs[:500] + [enc(i, i - 500, i * cyc) for i in range(500, n)]
        emit_row("UDP, an FPGA reset (cycle counter continued)", "sequence restarts at 0 "
                 "at datagram 500, cycles go on", run("reset2", sched, 1000), n)
    if want("UDP, a sequence jump"):
        sched = dgs[:500] + [enc(i, i + 10_000, i * cyc) for i in range(500, n)]
        emit_row("UDP, a sequence jump", "+10,000 sequence numbers at datagram 500, "
                 "contiguous cycles", run("jump", sched, 1000), n)
    if want("UDP, state disk full longer than idle"):
        emit_row("UDP, state disk full longer than idle", "the state tmpfs full for 20 s "
                 "from datagram 100, 40 datagrams/s, idle = 4 s",
                 run("statefull", dgs, 40, fill=(100, 20.0)), n)

    hostile = ["| **hostile** | | | | | | | | | |"]  # (the section's head, with its first row)
    other, _ = pattern_words(n * cyc, N, hit_prob=0.1, rng=11)  # another stream's words
    socks = {k: socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for k in ("fpga", "x")}
    for sk in socks.values():
        sk.bind(("127.0.0.1", 0))
    peers = f'peers = ["127.0.0.1:{socks["fpga"].getsockname()[1]}"]\n'
    real = [("fpga", d) for d in dgs]

    def both(name, injected, sched, n_sent, rate=1000, only_peers=False):
        for with_peers in (True,) if only_peers else (True, False):
            label = f"{name}, {'peers set' if with_peers else 'no peers'}"
            if want(label):
                lines.extend(hostile)
                hostile.clear()
                emit_row(label, injected, run(label.replace(",", ""), sched, rate,
                                              src_extra=peers if with_peers else "",
                                              outs=socks), n_sent)

    forged = [("x", enc(i, i, i * cyc, w=other, last=False)) for i in range(158)]
    both("UDP, forged datagrams first", "158 consistent datagrams from another sender, "
         "before the stream", forged + real, n + 158)
    spoofed = [("fpga", enc(i, i, i * cyc, w=other, last=False)) for i in range(158)]
    both("UDP, forged from the FPGA's own address", "158 datagrams (the stream's sequence "
         "numbers and cycles, other bytes) from its address, before it", spoofed + real,
         n + 158, only_peers=True)
    junk = []
    for d in real:
        junk += [("x", b"\0" * 1000), d]
    both("UDP, a junk flood from elsewhere", "1,000 junk datagrams/s interleaved 1:1",
         junk, 2 * n, rate=2000, only_peers=True)
    rig = [("x", enc(i, i, i * cyc, w=other, gate=150_000, last=False)) for i in range(n)]
    both("UDP, an old rig of another gate", "gate 150 ns against 140, interleaved 1:1, "
         "sending first", [x for pair in zip(rig, real, strict=True) for x in pair], 2 * n)
    rig = [("x", enc(i, i, i * cyc, w=other, last=False)) for i in range(n)]
    both("UDP, an identical rig started earlier", "the same gate, 500 datagrams ahead, "
         "then interleaved 1:1", rig[:500] + [x for pair in zip(rig[500:], real[:500],
                                                              strict=True) for x in pair]
         + real[500:], 2 * n)
    for sk in socks.values():
        sk.close()


def _counted(acc: dict) -> str:
    """What the accounting counted of a bad day (other senders, conflicts, restarts)."""
    out = []
    others = acc.get("other_senders") or {}
    if others:
        kept = sum(b["datagrams"] for b in others.values())
        consistent = sum(b.get("consistent", False) for b in others.values())
        out.append(f"{kept:,} datagrams of {len(others)} other sender(s) kept out"
                   f"{f' ({consistent} consistent)' if consistent else ''}")
    if acc.get("conflicting_datagrams"):
        out.append(f"{acc['conflicting_datagrams']:,} conflicts")
    if acc.get("stream_restarts"):
        out.append("restarts: " + ", ".join(f"{e['event']} at cycle {e['at_cycle']:,}"
                                             for e in acc["stream_restarts"]))
    if acc.get("ring_dropped_datagrams"):
        out.append(f"{acc['ring_dropped_datagrams']:,} dropped by the ring")
    return "; " + "; ".join(out) if out else ""


def _fill_disk(d: Path) -> Path:
    """Fill the file system of ``d`` to its last byte; the file to delete to free it."""
    filler = d / "filler"
    with open(filler, "wb", buffering=0) as fh:
        for size in (1 << 20, 1 << 12, 1):
            try:
                while True:
                    fh.write(b"\0" * size)
            except OSError:
                continue
    return filler


def _journaled_datagrams(journal: Path, run: str) -> int:
    from pipeline.stream.journal import _entries

    # a chunk is a batch of consecutive datagrams (``datagrams``; one before batches)
    return sum(int(e.get("datagrams", 1)) for e in _entries(journal / f"{run}.index.jsonl")
               if "first_word" in e)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None)
    ap.add_argument("--only", nargs="*", default=None,
                    help="run the clean runs and the scenarios whose name holds a WORD")
    args = ap.parse_args()
    lines = ["# Faults: the daemon against a clean run of the same input", "",
             machine(), "",
             "| scenario | injected | sent | journaled | lost silently | wrong measurements "
             "| withheld (counted) | crashes | run's end (exit) | delay vs clean (s) |",
             "|---|---|---:|---:|---:|---:|---:|---:|---|---:|"]
    with tempfile.TemporaryDirectory(dir=Path.cwd()) as d:
        sim_scenarios(Path(d), lines, args.only)
        udp_scenarios(Path(d), lines, args.only)
    emit(lines, args.out)


if __name__ == "__main__":
    main()
