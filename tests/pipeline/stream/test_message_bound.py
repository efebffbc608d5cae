"""A message bounded as a whole (issue 26.9): one message of 11 frames of 60 MiB sent to a
stage's tcp:// endpoint, as another local account would, must not take the stage to GBs."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zmq

from pipeline.stream import curve

MIB = 1 << 20


def _kib(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    raise AssertionError(f"no {key} for {pid}")


@pytest.fixture
def sink_stage(tmp_path):
    """A sink stage on tcp:// loopback, with CURVE as the daemon now turns it on there."""
    keys = curve.ensure_keys(tmp_path / "state")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    ep = f"tcp://127.0.0.1:{port}"
    proc = subprocess.Popen([sys.executable, "-m", "pipeline.cli", "stage", "sink", "--pull",
                             ep, "--out", tmp_path / "out", "--quarantine", tmp_path / "q"],
                            # (keys but no token: --insecure, what this test bounds is
                            # the message, whoever sends it)
                            env={**os.environ, curve.CURVE_ENV: str(keys),
                                 "TCSPC_INSECURE": "1"},
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.time() + 60
    while True:  # bound when it accepts a TCP connection
        try:
            socket.create_connection(("127.0.0.1", port), timeout=1).close()
            break
        except OSError:
            assert proc.poll() is None and time.time() < deadline
            time.sleep(0.1)
    time.sleep(1.0)  # its imports done: the baseline is the running stage's
    yield proc, ep, keys, tmp_path / "q"
    proc.kill()
    proc.wait()


def _send(ep: str, frames: list, keys: Path | None) -> zmq.Socket:
    """A PUSH socket that sends ``frames`` as one message to ``ep``. Without keys the
    stage refuses the handshake, and ZeroMQ may find no pipe to queue the message on
    (a clean clone's suite: the send blocked until the test's 300 s timeout): the send
    gives up after 20 s there, nothing delivered; with keys, a send that gives up fails
    the test."""
    ctx = zmq.Context.instance()
    s = ctx.socket(zmq.PUSH)
    s.setsockopt(zmq.SNDTIMEO, 20_000)
    if keys is not None:
        curve.client(s, keys)
    s.connect(ep)
    try:
        s.send_multipart(frames, copy=False)
    except zmq.Again:
        if keys is not None:
            raise
    return s


def test_a_many_frame_message_does_not_take_a_stage_to_gigabytes(sink_stage):
    proc, ep, keys, qdir = sink_stage
    before = _kib(proc.pid, "VmRSS")
    big = bytearray(60 * MIB)
    # another account, without the graph's keys: nothing it sends is taken or held
    evil = _send(ep, [b"{}", *[big] * 10], None)
    time.sleep(3.0)
    assert _kib(proc.pid, "VmHWM") - before < 64 * 1024, "the stage held the message"
    evil.close(linger=0)
    # a peer with the keys (a broken stage of our own): 11 frames of 8 MiB are refused
    # as bad_frames on delivery, quarantined without a copy of the message
    small = bytearray(8 * MIB)
    ours = _send(ep, [b"{}", *[small] * 10], keys)
    deadline = time.time() + 60
    while not list(qdir.glob("*.json")):
        assert time.time() < deadline and proc.poll() is None
        time.sleep(0.1)
    meta = json.loads(next(qdir.glob("*.json")).read_text())
    assert meta["frames"] == 11 and meta["bytes"] == 2 + 80 * MIB
    assert (next(qdir.glob("*.bin")).stat().st_size) == 1 * MIB  # its first MiB only
    grew = _kib(proc.pid, "VmHWM") - before
    assert grew < 2 * 80 * 1024, f"{grew} KiB for an 80 MiB message: copied"
    ours.close(linger=0)
