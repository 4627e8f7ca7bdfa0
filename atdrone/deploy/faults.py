"""What can interrupt a flight from outside the drones: injected faults (sim backend) and stop requests.

:class:`FaultClock` fires the config's faults at their flight time (or, for a fault given a ``step``, at that
step of its episode, whatever the host's pace); :class:`StopRequest`
is set by SIGINT/SIGTERM (every drone lands; a second request stops the motors).
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field


@dataclass
class FaultClock:
    """Faults of the sim backend fired once their time comes (callables taking nothing).

    A fault with ``step`` >= 0 fires at the first tick at or after flight time ``at`` whose (episode, step) is at
    least (``episode``, ``step``) (ticks between episodes have step -1 and count for the next episode): at that
    step, or on the first tick after its episode when the episode ended sooner."""

    pending: list[tuple[float, str, str, Callable[[], None], tuple[int, int]]] = field(
        default_factory=list
    )  # at, drone, kind, fire, (episode, step) or (-1, -1)
    stall: float = 0.0  # s the next policy step is stalled (a policy_stall fault; consumed once)
    hang: float = 0.0  # s the loop thread hangs (a loop_hang fault; consumed once)
    raise_now: bool = False  # an exception fault: the loop raises

    def add(self, at: float, drone: str, kind: str, fire: Callable[[], None], episode: int = 0, step: int = -1) -> None:
        self.pending.append((at, drone, kind, fire, (episode, step) if step >= 0 else (-1, -1)))

    def fire(self, t: float, episode: int = 0, step: int = -1) -> list[tuple[str, str]]:
        """Fire the faults due at flight time ``t`` on a tick of ``episode`` flying ``step`` (-1: between episodes);
        their (drone, "fault:kind"), drone "" for all."""
        due = [f for f in self.pending if f[0] <= t and (episode, step) >= f[4]]
        self.pending = [f for f in self.pending if f not in due]
        for f in due:
            f[3]()
        return [(drone, f"fault:{kind}") for _, drone, kind, *_ in due]


class InjectedFault(RuntimeError):
    """The exception an ``exception`` fault raises inside the loop."""


class StopRequest:
    """Set by SIGINT/SIGTERM (or :meth:`set`): every drone lands; a second request: emergency stop."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: str = ""
        self.count = 0

    def set(self, why: str = "request") -> None:
        self.signal = why
        self.count += 1
        self.event.set()

    def __bool__(self) -> bool:
        return self.event.is_set()

    @property
    def urgent(self) -> bool:
        """A second request arrived: the heartbeat sends the emergency stop at once."""
        return self.count >= 2

    @contextmanager
    def handling_signals(self) -> Iterator[None]:
        """Install SIGINT/SIGTERM handlers for the block (main thread only; elsewhere no-op)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        for s in old:
            signal.signal(s, lambda num, _frame: self.set(signal.Signals(num).name))
        try:
            yield
        finally:
            for s, h in old.items():
                signal.signal(s, h)
