"""Issue 38.9: a UDP run ending on ``idle`` stalled 60 s in ZeroMQ's context termination
about one run in ten: a histogram worker idle past the journal's end ends on it (it
fetches what it lacks from the journal) before the ingest's stop reaches it, and the stop,
queued to a consumer gone, held ``ctx.term()`` for the whole linger. The ingest now
watches each consumer's connection: one that hung up after the run's end was journaled
has all it will take, and its socket closes without lingering."""

import time

import zmq

from pipeline.stream.stage import connections
from pipeline.stream.udp.ingest import _hung_up


class _Beat:
    def __init__(self):
        self.states = []

    def beat(self, **fields):
        self.states.append(fields.get("state"))


def _pair(ctx, path):
    pull = ctx.socket(zmq.PULL)
    pull.bind(f"ipc://{path}")
    push = ctx.socket(zmq.PUSH)
    mon = push.get_monitor_socket(zmq.EVENT_CONNECTED | zmq.EVENT_DISCONNECTED)
    push.connect(f"ipc://{path}")
    push.send(b"words")
    assert pull.recv() == b"words"
    return pull, push, mon


def _close(ctx, push, mon, gone):
    push.disable_monitor()
    mon.close(linger=0)
    push.close(linger=60_000 if not gone else 0)
    t0 = time.monotonic()
    ctx.term()
    return time.monotonic() - t0


def test_a_consumer_that_ended_on_the_journals_end_is_not_lingered_over(tmp_path):
    ctx = zmq.Context()
    pull, push, mon = _pair(ctx, tmp_path / "a")
    at_end = connections([mon])
    assert at_end == [zmq.EVENT_CONNECTED]
    pull.close(linger=0)  # the worker ended on the journal's end ...
    time.sleep(0.2)
    push.send(b"stop", zmq.NOBLOCK)  # ... before its stop, now queued to nobody
    gone = _hung_up([mon], _Beat(), at_end, wait_s=10)
    assert gone == [True]
    assert _close(ctx, push, mon, gone[0]) < 3  # (60 s lingered before)


def test_a_consumer_still_taking_is_waited_for_then_lingered_over(tmp_path):
    ctx = zmq.Context()
    pull, push, mon = _pair(ctx, tmp_path / "b")
    at_end = connections([mon])
    push.send(b"stop")
    beat = _Beat()
    t0 = time.monotonic()
    gone = _hung_up([mon], beat, at_end, wait_s=0.5)  # it never hangs up
    assert gone == [False] and time.monotonic() - t0 >= 0.5 and "finished" in beat.states
    assert pull.recv() == b"stop"
    pull.close(linger=0)
    push.disable_monitor()
    mon.close(linger=0)
    push.close(linger=1000)
    ctx.term()


def test_a_consumer_gone_before_the_end_keeps_its_stop_queued(tmp_path):
    """One not connected when the end was journaled (a worker restarting) is not taken for
    one that finished: its stop stays queued for the restarted worker."""
    ctx = zmq.Context()
    pull, push, mon = _pair(ctx, tmp_path / "c")
    pull.close(linger=0)
    time.sleep(0.2)
    at_end = connections([mon])
    assert at_end == [zmq.EVENT_DISCONNECTED]
    push.send(b"stop", zmq.NOBLOCK)
    assert _hung_up([mon], _Beat(), at_end, wait_s=10) == [False]
    again = ctx.socket(zmq.PULL)  # the restarted worker binds again and gets it
    again.bind(f"ipc://{tmp_path / 'c'}")
    assert again.poll(5000) and again.recv() == b"stop"
    again.close(linger=0)
    push.disable_monitor()
    mon.close(linger=0)
    push.close(linger=0)
    ctx.term()
