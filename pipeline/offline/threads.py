"""How many threads an offline command's compiled loops share (the chip's capture and an
instrument's file alike)."""

from __future__ import annotations

import os


def default_threads() -> int:
    """Threads for the histogram loop: ``TCSPC_THREADS`` if set, else the cores this
    process may use, at most 4 (each thread's loop reads ~1 GB/s of words: a few
    saturate a memory channel)."""
    if os.environ.get("TCSPC_THREADS"):
        return max(1, int(os.environ["TCSPC_THREADS"]))
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        n = os.cpu_count() or 1
    return max(1, min(4, n))
