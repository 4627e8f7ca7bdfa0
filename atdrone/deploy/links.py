"""Link health: how long each radio link has been silent, with the ground station's own pauses left out.

A link's age is the wall time since the last packet cflib received from that drone
(log data, acknowledgements, answers), scaled to the flight's clock. Two things look
alike from the loop's seat and are told apart here:

- **a host pause**: the loop's tick started later than its period (the process was
  descheduled, stopped, or starved of the interpreter). Every link looks silent for
  the pause's length, though nothing happened on the radio; ages count again from the
  moment the loop resumed, so a pause never marks a drone lost.
- **all links silent together** (the radio or cflib's receiving threads stalled, the
  sender blocked): one stall of the ground station, not N lost drones. The shield holds
  every drone, then lands them all (``links_silent``); nobody is marked lost.

Only a link silent while others are heard is a lost drone: the loop keeps sending it the
land command on every tick until it is heard again (then it lands under the loop's
watch) or the flight ends without it (its firmware's watchdogs take over).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class LinkView:
    """One tick's link health: per drone the silence (clock s, host pauses excluded), and, when every link is
    silent beyond the timeout together, the shortest of their silences (clock s; 0 otherwise)."""

    silence: np.ndarray  # (D,)
    all_silent: float


class LinkHealth:
    """Link ages for the shield (see the module docstring).

    ``rate``: clock seconds per wall second; ``timeout``: clock seconds of silence that make a link silent
    (the shield's ``link_timeout``); ``wall``: the wall clock (monotonic seconds), replaceable in tests.
    """

    def __init__(
        self, names: Sequence[str], rate: float, timeout: float, wall: Callable[[], float] = time.monotonic
    ) -> None:
        self.names, self.rate, self.timeout, self.wall = tuple(names), float(rate), float(timeout), wall
        self.resumed = -math.inf  # wall time the loop last resumed after a pause
        self.pauses = 0

    def host_paused(self, late_by: float, period: float) -> bool:
        """Tell a tick that started ``late_by`` clock seconds late; a tick late by more than ``period`` is a host
        pause: silence counts again from now. True when it was one."""
        if late_by > period:
            self.resumed = self.wall()
            self.pauses += 1
            return True
        return False

    def update(self, ages: Mapping[str, float], sender_age: float = 0.0) -> LinkView:
        """Per-link wall ages (s since the last packet; missing: never heard) and the sender's clock age (s since
        it last finished a round: a blocked sender reaches no drone) -> this tick's view."""
        now = self.wall()
        since_resume = now - self.resumed
        wall_age = np.array([min(ages.get(n, math.inf), since_resume) for n in self.names])
        silence = np.maximum(wall_age * self.rate, sender_age)
        quiet = silence > self.timeout
        if len(self.names) > 1 and quiet.all():
            return LinkView(silence, float(silence.min()))
        return LinkView(silence, 0.0)
