"""Clocks for the flight loop: the wall clock, and a fake one that tests advance by hand.

Everything ``aswarm fly`` does with time goes through a :class:`Clock`: ``now()``, ``sleep(s)`` and ``every(period,
fn)`` (a periodic callback, e.g. a simulated mocap's frames). On :class:`RealClock` a periodic callback runs on its own
thread; on :class:`FakeClock` it runs inside ``sleep``, at its due times in order, so a whole flight sequence with a
100 Hz pose stream and a 25 Hz control loop runs in milliseconds and the same way every time.
"""

from __future__ import annotations

import heapq
import itertools
import threading
import time
from collections.abc import Callable
from typing import Protocol


class Clock(Protocol):
    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...

    def every(self, period: float, fn: Callable[[float], None]) -> Callable[[], None]:
        """Call ``fn(now)`` every ``period`` s from now on; returns a function that stops it."""
        ...


class RealClock:
    """``time.monotonic``; periodic callbacks on daemon threads, scheduled on absolute times (no drift)."""

    def now(self) -> float:
        return time.monotonic()

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds)

    def every(self, period: float, fn: Callable[[float], None]) -> Callable[[], None]:
        stop = threading.Event()

        def loop() -> None:
            due = time.monotonic()
            while not stop.is_set():
                fn(time.monotonic())
                due += period
                # A callback that overran skips the ticks it missed rather than firing them in a burst.
                due = max(due, time.monotonic())
                stop.wait(max(0.0, due - time.monotonic()))

        threading.Thread(target=loop, daemon=True, name="aswarm-every").start()
        return stop.set


class FakeClock:
    """Time that moves only in ``sleep``; periodic callbacks fire at their due times inside it, in time order."""

    def __init__(self, start: float = 0.0):
        self.t = float(start)
        self._queue: list[tuple[float, int, float, Callable[[float], None], list[bool]]] = []
        self._order = itertools.count()

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        end = self.t + max(0.0, seconds)
        while self._queue and self._queue[0][0] <= end + 1e-12:
            due, _, period, fn, alive = heapq.heappop(self._queue)
            if not alive[0]:
                continue
            self.t = max(self.t, due)
            fn(self.t)
            heapq.heappush(self._queue, (due + period, next(self._order), period, fn, alive))
        self.t = end

    def every(self, period: float, fn: Callable[[float], None]) -> Callable[[], None]:
        if not period > 0:
            raise ValueError(f"invalid period={period!r}: must be > 0 s")
        alive = [True]
        heapq.heappush(self._queue, (self.t, next(self._order), period, fn, alive))

        def stop() -> None:
            alive[0] = False

        return stop
