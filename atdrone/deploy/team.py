"""The policies of a flight and the thread they run in.

:class:`Team`: the learner and the partner policies of one flight (a zoo draws the
partners per episode). :class:`PolicyRunner`: the team's ``act`` in a worker thread, so a
late policy never delays a tick: the loop holds the drones from outside the call. What
changes the policies' state (a new episode's partners and memory, a slot's memory forgotten
when a backup takes it) runs in that thread too, between two steps: a late step still
running never sees half a change, nor writes its memory back over a forgotten slot.
"""

from __future__ import annotations

import concurrent.futures
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from atdrone.deploy.clock import Clock
from atdrone.deploy.faults import FaultClock
from atdrone.envs.observation import Poses
from atdrone.policies.base import DroneBatch, Policy


@dataclass
class Team:
    """The policies of one flight: the learner, and the partner policy of each partner slot this episode."""

    learner: Policy
    partners: list[Policy]
    draw_partners: Callable[[np.random.Generator], list[Policy]] | None = None  # per episode (a zoo)

    def draw(self, rng: np.random.Generator) -> list[Policy]:
        """The partner policies of a new episode: drawn from the zoo with the flight's generator, else the same."""
        return self.draw_partners(rng) if self.draw_partners is not None else self.partners

    def start(self, partners: list[Policy]) -> None:
        """A new episode with ``partners``: every policy's memory reset."""
        self.partners = partners
        for p in [self.learner, *self.partners]:
            p.reset(np.ones(1, dtype=bool))

    def forget(self, slot: int) -> None:
        """Every policy with per-drone memory forgets pursuer ``slot``: another drone took it mid-episode."""
        for p in [self.learner, *self.partners]:
            forget = getattr(p, "forget", None)
            if forget is not None:
                forget(np.zeros(1, dtype=np.intp), np.array([slot]))

    def act(self, obs: np.ndarray, poses: Poses, learner_slots: np.ndarray, partner_slots: np.ndarray) -> np.ndarray:
        """Actions (num_p,) of every pursuer slot from observations (1, num_p, obs_dim)."""
        actions = np.zeros(obs.shape[1])
        env = np.zeros(len(learner_slots), dtype=np.intp)
        actions[learner_slots] = self.learner.act(DroneBatch(obs[0, learner_slots], env, learner_slots, poses))
        for slot, policy in zip(partner_slots, self.partners, strict=True):
            s = np.array([slot])
            actions[slot] = policy.act(DroneBatch(obs[0, s], np.zeros(1, dtype=np.intp), s, poses))[0]
        return actions


class PolicyRunner:
    """The team's ``act`` in a worker thread, so a late policy never delays a tick (see the module docstring)."""

    def __init__(self, team: Team, clock: Clock, faults: FaultClock) -> None:
        self.team, self.clock, self.faults = team, clock, faults
        self._pool = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="policy")
        self._pending: concurrent.futures.Future[np.ndarray] | None = None
        self._changes: list[concurrent.futures.Future[None]] = []  # submitted between steps, not yet seen done
        self.late_since: float | None = None  # clock time the pending step became late

    def between_steps(self, change: Callable[..., None], *args: Any) -> None:
        """Run ``change(*args)`` in the policy thread after the step in progress (if any) and before the next one;
        returns at once (the flight never waits on a late step). Its error is raised by the next :meth:`act`."""
        self._changes.append(self._pool.submit(change, *args))

    def _act(self, *args: Any) -> np.ndarray:
        if self.faults.stall:
            stall, self.faults.stall = self.faults.stall, 0.0
            self.clock.sleep(stall)
        return self.team.act(*args)

    def act(self, timeout: float, *args: Any) -> np.ndarray | None:
        """Actions, or None when the step did not finish within ``timeout`` clock seconds (still pending)."""
        for done in [c for c in self._changes if c.done()]:
            self._changes.remove(done)
            done.result()  # a change between steps failed: raise its error here
        if self._pending is not None and self._pending.done():
            self._pending.result()  # a stale step finished: re-raise its error, drop its actions
            self._pending = None
        if self._pending is None:
            self._pending = self._pool.submit(self._act, *args)
        try:
            actions = self._pending.result(timeout / self.clock.rate)
        except concurrent.futures.TimeoutError:
            if self.late_since is None:
                self.late_since = self.clock.now() - timeout
            return None
        self._pending, self.late_since = None, None
        return actions

    def late_for(self) -> float:
        return 0.0 if self.late_since is None else self.clock.now() - self.late_since

    def close(self) -> None:
        self._pool.shutdown(wait=False, cancel_futures=True)
