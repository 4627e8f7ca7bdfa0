"""Time for the deploy layer: real time, or a scaled clock that runs faster than real time.

Every deploy component reads time from one :class:`Clock` so the simulated fleet, the
simulated motion capture, the watchdogs and the 10 Hz loop agree. ``ScaledClock(rate)``
runs ``rate`` simulated seconds per wall second (rate 1 is real time): tests fly minutes
in seconds. The radio link (cflib's threads and timeouts) always runs in wall time.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol


class Clock(Protocol):
    """Seconds since the clock started, and sleeping in those seconds."""

    rate: float

    def now(self) -> float: ...

    def sleep(self, seconds: float) -> None: ...

    def sleep_until(self, t: float) -> None: ...


class ScaledClock:
    """``rate`` clock seconds per wall second, starting at 0 when made."""

    def __init__(self, rate: float = 1.0, t0: float | None = None) -> None:
        if not rate > 0:
            raise ValueError(f"clock rate must be > 0, got {rate!r}")
        self.rate = float(rate)
        self._t0 = time.perf_counter() if t0 is None else t0  # perf_counter is one monotonic clock for every process

    @property
    def origin(self) -> float:
        """The ``time.perf_counter()`` at which this clock read 0 (another process's clock can share it)."""
        return self._t0

    def now(self) -> float:
        return (time.perf_counter() - self._t0) * self.rate

    def sleep(self, seconds: float) -> None:
        if seconds > 0:
            time.sleep(seconds / self.rate)

    def sleep_until(self, t: float) -> None:
        self.sleep(t - self.now())

    def wall(self, seconds: float) -> float:
        """Wall seconds that ``seconds`` of this clock take."""
        return seconds / self.rate


def RealClock() -> ScaledClock:
    """The wall clock (rate 1)."""
    return ScaledClock(1.0)


class Ticker:
    """Calls at a fixed period on a clock, counting overruns (a tick that started late)."""

    def __init__(self, clock: Clock, period: float) -> None:
        self.clock, self.period = clock, period
        self.next = clock.now()
        self.overruns = 0
        self.late_by = 0.0  # clock seconds the last tick was called or woke after its scheduled time (a host pause)
        self._lock = threading.Lock()

    def wait(self) -> float:
        """Sleep until the next tick; return its scheduled time. A late tick counts an overrun
        and the schedule restarts from now (no burst of catch-up ticks)."""
        with self._lock:
            now = self.clock.now()
            self.late_by = max(0.0, now - self.next)
            if now > self.next + self.period:
                self.overruns += 1
                self.next = now
            self.clock.sleep_until(self.next)
            # a pause while asleep (the host descheduled or stopped the process) shows only on waking
            woke = self.clock.now()
            self.late_by = max(self.late_by, woke - self.next)
            if woke > self.next + self.period:
                self.overruns += 1
                self.next = woke
            t = self.next
            self.next += self.period
            return t
