"""A stage's restart budget as a rate (issue 38.8): a token bucket.

The bucket holds at most ``burst`` restarts and earns one back every ``refill_s`` seconds.
A death takes one; a death with the bucket empty fails the run. So a burst of ``burst``
deaths is restarted back to back, and deaths spread wider than ``refill_s`` apart are
restarted for ever: with the defaults (10, one per 60 s) a stage may die 60 times an hour,
1,440 a day, for the whole of a week-long run, while one crash-looping every few seconds
spends its 10 in under a minute and fails the run. (The window it replaces, 10 deaths in
any 600 s, has the same long-run rate but no headroom: the soak's source spent all 10 of
its window, and the 11th kill would have failed a run that was fine.)

The clock is a parameter, so the budget is tested without sleeping.
"""

from __future__ import annotations

import time
from collections.abc import Callable


class RestartBudget:
    """A token bucket of restarts: ``burst`` at most, one earned back per ``refill_s``."""

    def __init__(self, burst: int, refill_s: float,
                 clock: Callable[[], float] = time.monotonic):
        if burst < 0 or refill_s <= 0:
            raise ValueError(f"a restart budget needs burst >= 0 and refill_s > 0, got "
                             f"{burst}, {refill_s}")
        self.burst, self.refill_s, self.clock = burst, refill_s, clock
        self.tokens = float(burst)
        self.at = clock()

    def _refill(self) -> None:
        now = self.clock()
        self.tokens = min(float(self.burst), self.tokens + (now - self.at) / self.refill_s)
        self.at = now

    def available(self) -> float:
        """Restarts left now (a fraction: part of the next one earned)."""
        self._refill()
        return self.tokens

    def spent(self) -> int:
        """Restarts taken and not yet earned back (the backoff doubles with each)."""
        self._refill()
        return self.burst - int(self.tokens)

    def take(self) -> bool:
        """One restart: True when the budget has one (taken), False when it is spent."""
        self._refill()
        if self.tokens < 1.0:
            return False
        self.tokens -= 1.0
        return True

    def describe(self) -> str:
        return f"{self.burst} at once, one more every {self.refill_s:g} s"
