"""The policy interface: everything that drives a pursuer implements :class:`Policy`.

A policy acts on a flat batch of M drones drawn from any environments and pursuer
slots: their observations, and for rule-based policies a poses record
(:class:`~atdrone.envs.observation.Poses`: what a motion-capture frame gives, which
the simulator fills too). No simulator is needed. It returns one action in [-1, 1]
per drone. Policies with per-episode memory key it by (env, slot) and clear it in
:meth:`Policy.reset` for the environments whose episode ended.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from atdrone.envs.kinematics import turn_towards as turn_towards
from atdrone.envs.observation import Poses
from atdrone.errors import UserError


class PolicyError(UserError, RuntimeError):
    """A policy cannot be had: an unknown name, a missing or unreadable checkpoint."""


@dataclass(frozen=True)
class DroneBatch:
    """M drones to act for.

    obs (M, obs_dim) their observations; env (M,) and slot (M,) the environment row
    and pursuer slot of each (the keys of per-drone memory, and rows into ``poses``);
    poses: the poses of every drone of those environments, for policies that read
    positions rather than observations (None: observations only); keys (M,) uint64:
    each drone's random key for this step (from its episode, step and slot), for
    policies that sample (None: they use a generator of their own).
    """

    obs: np.ndarray
    env: np.ndarray
    slot: np.ndarray
    poses: Poses | None = None
    keys: np.ndarray | None = None

    @classmethod
    def all_slots(cls, obs: np.ndarray, poses: Poses | None = None, slots: np.ndarray | None = None) -> DroneBatch:
        """Every environment's drones in ``slots`` (default: all), env-major, from obs (B, num_p, obs_dim)."""
        num_envs, num_p = obs.shape[:2]
        slots = np.arange(num_p) if slots is None else np.asarray(slots)
        env = np.repeat(np.arange(num_envs), len(slots))
        slot = np.tile(slots, num_envs)
        return cls(obs=obs[env, slot], env=env, slot=slot, poses=poses)

    def __len__(self) -> int:
        return len(self.env)

    def need_poses(self, who: str) -> Poses:
        """The poses record; a ValueError naming ``who`` when the batch carries none."""
        if self.poses is None:
            raise ValueError(f"{who} acts on poses, but this DroneBatch has none (pass poses=Poses(...))")
        return self.poses

    @property
    def pos(self) -> np.ndarray:
        """(M, 2) own positions."""
        return self.need_poses("DroneBatch.pos").pos[self.env, self.slot]

    @property
    def heading(self) -> np.ndarray:
        """(M,) own headings."""
        return self.need_poses("DroneBatch.heading").heading[self.env, self.slot]


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
