"""Fan-out by TDC range: worker i of a stage takes TDCs ``a_i .. b_i - 1`` of every cycle.

The source splits each batch of whole cycles into one contiguous sub-batch per range; a
worker's stream index counts its own words (cycle c of worker i starts at c * (b_i - a_i)),
and its journal reader maps a gap in that index back to the run's journal.
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from schemas.errors import TcspcError


class FanoutError(TcspcError, ValueError):
    """A fan-out that cannot work (ranges that do not tile the TDCs, batches not whole
    cycles)."""


def equal_ranges(n_tdc: int, workers: int) -> list[tuple[int, int]]:
    """``workers`` contiguous TDC ranges as equal as can be."""
    if not 1 <= workers <= n_tdc:
        raise FanoutError(f"{workers} workers for {n_tdc} TDCs: use 1..{n_tdc}")
    edges = np.linspace(0, n_tdc, workers + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:], strict=True)]


def parse_range(text: str) -> tuple[int, int]:
    a, sep, b = text.partition(":")
    if not sep:
        raise FanoutError(f"TDC range {text!r}: use FIRST:END, e.g. 0:64")
    return int(a), int(b)


class TdcSplitter:
    def __init__(self, n_tdc: int, ranges: list[tuple[int, int]]):
        flat = [x for r in ranges for x in r]
        if flat[0] != 0 or flat[-1] != n_tdc or any(
                ranges[i][1] != ranges[i + 1][0] for i in range(len(ranges) - 1)) or any(
                a >= b for a, b in ranges):
            raise FanoutError(f"TDC ranges {ranges} must tile 0..{n_tdc} in order")
        self.n_tdc, self.ranges = n_tdc, ranges

    def split(self, first: int, words: np.ndarray) -> list[tuple[int, np.ndarray]]:
        return [(f, np.ascontiguousarray(v).ravel()) for f, v in self.views(first, words)]

    def views(self, first: int, words: np.ndarray) -> list[tuple[int, np.ndarray]]:
        """Each range's (first word, (cycles, TDCs) view of ``words``), not copied."""
        n = self.n_tdc
        if first % n or words.size % n:
            raise FanoutError(f"fan-out by TDC range needs whole cycles: a batch of "
                              f"{words.size} words at word {first} with {n} TDCs per cycle")
        grid = words.reshape(-1, n)
        c0 = first // n
        return [(c0 * (b - a), grid[:, a:b]) for a, b in self.ranges]


def worker_reader(read_range, n_tdc: int, tdc_range: tuple[int, int]):
    """Map a worker's gap [start, stop) (its own index) onto the run's journal:
    ``read_range(full_start, full_stop)`` yields (first, words) of whole cycles."""
    a, b = tdc_range
    w = b - a

    def backfill(start: int, stop: int) -> Iterator[tuple[int, np.ndarray]]:
        c0, c1 = start // w, -(-stop // w)
        for first, words in read_range(c0 * n_tdc, c1 * n_tdc):
            sub_first = first // n_tdc * w
            sub = np.ascontiguousarray(words.reshape(-1, n_tdc)[:, a:b]).ravel()
            lo, hi = max(start, sub_first), min(stop, sub_first + sub.size)
            if lo < hi:
                yield lo, sub[lo - sub_first:hi - sub_first]

    return backfill
