"""One environment of the batched core, with episode-at-a-time semantics.

The PettingZoo and Gymnasium views sit on this: it returns the final observation of a
finished episode (not the auto-reset one) and starts the next episode from the state
the core already drew, so a view and ``BatchedPursuit(num_envs=1)`` with the same seed
and actions produce the same trajectories.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from atdrone.config import TaskConfig
from atdrone.envs.core import CAPTURED, COLLISION, DONE_REASONS, TIMEOUT, BatchedPursuit


@dataclass(frozen=True)
class Outcome:
    """One step of one environment."""

    obs: np.ndarray  # (num_p, obs_dim)
    reward: float
    terminated: bool  # captured all or collision
    truncated: bool  # horizon reached
    info: dict[str, Any]


class SingleEnv:
    """A BatchedPursuit of one environment that stops at the end of each episode."""

    def __init__(self, task: TaskConfig | str, seed: int | None = None) -> None:
        self.core = BatchedPursuit(task, num_envs=1, seed=seed)
        self._pending_reset = False  # the core auto-reset at the last episode end
        self.needs_reset = True

    @property
    def cfg(self) -> TaskConfig:
        return self.core.cfg

    def reset(self, seed: int | None = None) -> np.ndarray:
        """Start an episode: reseed when ``seed`` is given, else continue the core's draws."""
        if seed is not None or not self._pending_reset:
            self.core.reset(seed=seed)
        self._pending_reset = False
        self.needs_reset = False
        return self.core.observe()[0]

    def step(self, actions: np.ndarray) -> Outcome:
        """Step all pursuers with ``actions`` (num_p,)."""
        if self.needs_reset:
            raise RuntimeError("the episode has ended (or never started): call reset()")
        obs, rewards, dones, info = self.core.step(np.asarray(actions, dtype=np.float64).reshape(1, -1))
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
        return Outcome(
            obs=obs[0],
            reward=float(rewards[0, 0]),
            terminated=reason in (CAPTURED, COLLISION),
            truncated=reason == TIMEOUT,
            info=record,
        )
