"""One environment of the batched core, with episode-at-a-time semantics.

The PettingZoo and Gymnasium views sit on this: it returns the final observation of a
finished episode (not the auto-reset one) and starts the next episode from the state
the core already drew, so a view and ``BatchedPursuit(num_envs=1)`` with the same seed
and actions produce the same trajectories.

It steps either the core itself (every pursuer) or a :class:`~atdrone.teams.match.Match` of
one environment (the learners' slots; zoo partners steer the rest).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, cast

import numpy as np

from atdrone.config import TaskConfig
from atdrone.envs.core import CAPTURED, COLLISION, DONE_REASONS, TIMEOUT, BatchedPursuit

if TYPE_CHECKING:  # atdrone.teams builds on atdrone.envs: no import at run time
    from atdrone.teams.match import Match


@dataclass(frozen=True)
class Outcome:
    """One step of one environment."""

    obs: np.ndarray  # (num_p or num_ctrl, obs_dim)
    reward: float
    terminated: bool  # captured all or collision
    truncated: bool  # horizon reached
    info: dict[str, Any]


class Stepper(Protocol):
    """What SingleEnv steps: BatchedPursuit (all pursuers) or Match (the learners' slots)."""

    def reset(self, seed: int | None = None) -> np.ndarray: ...

    def observe(self) -> np.ndarray: ...

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]: ...


class SingleEnv:
    """One environment of a BatchedPursuit (or of a Match on one) that stops at the end of each episode.

    ``source``: a task (the agent steers every pursuer; ``seed`` seeds the core) or a
    Match on a core of one environment (the agent steers the learners' slots; the
    episode's team, ``info["team"]``, is reported in the step info at episode end).
    """

    stepper: Stepper  # what reset() and step() drive: the core itself or a Match on it

    def __init__(self, source: TaskConfig | str | Match, seed: int | None = None) -> None:
        core = getattr(source, "core", None)
        if isinstance(core, BatchedPursuit):  # a Match
            self.core, self.stepper = core, cast("Match", source)
        else:
            self.core = BatchedPursuit(cast(TaskConfig | str, source), num_envs=1, seed=seed)
            self.stepper = self.core
        if self.core.num_envs != 1:
            raise ValueError(f"SingleEnv needs one environment, got {self.core.num_envs}")
        self._pending_reset = False  # the core auto-reset at the last episode end
        self.needs_reset = True

    @property
    def cfg(self) -> TaskConfig:
        return self.core.cfg

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start an episode: reseed when ``seed`` is given, else continue the core's draws."""
        if seed is not None or not self._pending_reset:
            self.stepper.reset(seed=seed)
        self._pending_reset = False
        self.needs_reset = False
        return self.stepper.observe()[0]

    def step(self, actions: np.ndarray) -> Outcome:
        """Step with ``actions`` (num_p,) for the core, (num_ctrl,) for a Match."""
        if self.needs_reset:
            raise RuntimeError("the episode has ended (or never started): call reset()")
        obs, rewards, dones, info = self.stepper.step(np.asarray(actions, dtype=np.float64).reshape(1, -1))
        reason = int(info["done_reason"][0])
        done = bool(dones[0])
        record = {
            "t": int(info["episode_length"][0]),
            "collided": info["collided"][0],
            "captured_now": info["captured_now"][0],
        }
        if done:
            self._pending_reset = True
            self.needs_reset = True
            obs = info["final_obs"]
            record.update(
                done_reason=DONE_REASONS[reason],
                episode_length=int(info["episode_length"][0]),
                episode_return=float(info["episode_return"][0]),
                episode_collided=bool(info["episode_collided"][0]),
                episode_captured=int(info["episode_captured"][0]),
            )
            if "team" in info:
                record["team"] = {k: v[0].tolist() for k, v in info["team"].items()}
        return Outcome(
            obs=obs[0],
            reward=float(rewards[0, 0]),
            terminated=reason in (CAPTURED, COLLISION),
            truncated=reason == TIMEOUT,
            info=record,
        )
