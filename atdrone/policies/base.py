"""The policy interface: everything that drives a pursuer implements :class:`Policy`.

A policy acts on a flat batch of M drones drawn from any environments and pursuer
slots of one :class:`~atdrone.envs.BatchedPursuit`: their observations, and for
rule-based policies the simulator state they need. It returns one action in
[-1, 1] per drone. Policies with per-episode memory key it by (env, slot) and clear
it in :meth:`Policy.reset` for the environments whose episode ended.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from atdrone.envs.core import BatchedPursuit


class PolicyError(RuntimeError):
    """A policy cannot be had: an unknown name, a missing or unreadable checkpoint."""


@dataclass(frozen=True)
class DroneBatch:
    """M drones to act for: obs (M, obs_dim), env (M,), slot (M,) into ``core``."""

    obs: np.ndarray
    env: np.ndarray
    slot: np.ndarray
    core: BatchedPursuit

    @classmethod
    def all_slots(cls, core: BatchedPursuit, obs: np.ndarray, slots: np.ndarray | None = None) -> DroneBatch:
        """Every environment's drones in ``slots`` (default: all pursuers), env-major order."""
        slots = np.arange(core.num_p) if slots is None else np.asarray(slots)
        env = np.repeat(np.arange(core.num_envs), len(slots))
        slot = np.tile(slots, core.num_envs)
        return cls(obs=obs[env, slot], env=env, slot=slot, core=core)

    def __len__(self) -> int:
        return len(self.env)

    @property
    def pos(self) -> np.ndarray:
        """(M, 2) own positions."""
        return self.core.state.pos[self.env, self.slot]

    @property
    def heading(self) -> np.ndarray:
        """(M,) own headings."""
        return self.core.state.heading[self.env, self.slot]


@runtime_checkable
class Policy(Protocol):
    """Anything that steers pursuers."""

    name: str

    def act(self, batch: DroneBatch) -> np.ndarray:
        """Actions (M,) in [-1, 1] for the drones of ``batch``."""
        ...

    def reset(self, done: np.ndarray) -> None:
        """Forget per-episode memory of the environments where ``done`` (B,) is true."""
        ...


class StatelessPolicy:
    """Base for policies without per-episode memory."""

    name = "stateless"

    def reset(self, done: np.ndarray) -> None:
        """Nothing to forget."""

    def act(self, batch: DroneBatch) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError


def turn_towards(heading: np.ndarray, desired: np.ndarray) -> np.ndarray:
    """The action in [-1, 1] that turns ``heading`` towards ``desired`` (radians) under the 45-degree limit."""
    diff = np.arctan2(np.sin(desired - heading), np.cos(desired - heading))
    return np.clip(diff / (np.pi / 4), -1.0, 1.0)
