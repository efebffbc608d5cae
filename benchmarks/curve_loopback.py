"""What CURVE costs on a loopback tcp:// endpoint (the daemon's "auto" turns it on there):
PUSH -> PULL over tcp://127.0.0.1, messages of the stream's shape ([header, payload]),
plain and under CURVE, alternated in one run so both see the same machine.

    python benchmarks/curve_loopback.py [--mib 1] [--messages 400] [--rounds 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
import threading
import time
from pathlib import Path

import zmq

from pipeline.stream import curve


def one(keys: Path | None, payload: bytes, n: int) -> float:
    """Seconds to move ``n`` messages through a fresh PUSH/PULL pair."""
    ctx = zmq.Context()
    rx, tx = ctx.socket(zmq.PULL), ctx.socket(zmq.PUSH)
    for s in (rx, tx):
        s.setsockopt(zmq.LINGER, 0)
        s.setsockopt(zmq.SNDHWM, 4)
        s.setsockopt(zmq.RCVHWM, 4)
    if keys is not None:
        curve.serve(rx, keys)
        curve.client(tx, keys)
    port = rx.bind_to_random_port("tcp://127.0.0.1")
    tx.connect(f"tcp://127.0.0.1:{port}")
    head = b'{"kind":"data"}'
    tx.send_multipart([head, payload])  # the handshake, outside the timing
    rx.recv_multipart()
    done = threading.Event()

    def take():
        for _ in range(n):
            rx.recv_multipart(copy=False)
        done.set()

    t = threading.Thread(target=take)
    t0 = time.perf_counter()
    t.start()
    for _ in range(n):
        tx.send_multipart([head, payload], copy=False)
    t.join()
    dt = time.perf_counter() - t0
    rx.close()
    tx.close()
    if keys is not None:
        curve.stop_authenticators()
    ctx.term()
    return dt


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mib", type=float, default=1.0, help="payload per message, MiB")
    ap.add_argument("--messages", type=int, default=400)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args()
    payload = os.urandom(int(args.mib * (1 << 20)))
    keys = curve.ensure_keys(Path(tempfile.mkdtemp()) / "state")
    print(f"$ python {' '.join(sys.argv)}")
    print(f"machine: {platform.node()} {platform.machine()}, {os.cpu_count()} cores, load "
          f"{os.getloadavg()[0]:.1f} (shared); zmq {zmq.zmq_version()}, "
          f"pyzmq {zmq.__version__}")
    rates = {"plain": [], "curve": []}
    for _ in range(args.rounds):
        for name, k in (("plain", None), ("curve", keys)):
            dt = one(k, payload, args.messages)
            rates[name].append(args.messages * len(payload) / dt / 1e6)
    for name, r in rates.items():
        print(f"{name:>5}: {max(r):8.0f} MB/s best of {args.rounds} "
              f"({', '.join(f'{x:.0f}' for x in r)})")
    print(f"CURVE / plain (best): {max(rates['curve']) / max(rates['plain']):.2f}")


if __name__ == "__main__":
    main()
