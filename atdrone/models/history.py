"""Per-drone memory: what a network reads besides the current observation.

A single observation gives each teammate's distance and bearing but not where it is
heading, so a drone cannot tell a teammate that will pass from one that will fly into
it. With ``history`` h > 0 the networks read, besides the current observation (D), the
drone's own last h observations (newest first) and its last h actions (the NAHT-D idea
of reading recent steps, SPEC section 10): the network input is

    [obs_t (D), obs_t-1 (D), ..., obs_t-h (D), a_t-1, ..., a_t-h]   (D * (h + 1) + h)

At an episode's first step the past frames repeat the current observation and the past
actions are 0 (no motion seen yet). Memory is keyed by (environment, key): a pursuer
slot for zoo policies, a learner index for rollout workers. It grows when handed an
environment or key beyond its size, so a policy needs no batch size in advance.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


def input_dim(obs_dim: int, history: int) -> int:
    """Width of the network input for raw observations of ``obs_dim`` and ``history`` past frames."""
    return obs_dim * (history + 1) + history


@runtime_checkable
class DroneMemory(Protocol):
    """Per-(environment, key) memory that turns observations into network inputs."""

    @property
    def input_dim(self) -> int:
        """Width of the network inputs :meth:`inputs` returns."""
        ...

    def inputs(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray) -> np.ndarray:
        """Network inputs (M, input_dim) float32 for observations (M, D) of drones (env (M,), key (M,))."""
        ...

    def record(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray, actions: np.ndarray) -> None:
        """Remember the observations (M, D) the drones acted on and their actions (M,) in [-1, 1]."""
        ...

    def reset(self, done: np.ndarray) -> None:
        """Forget the drones of the environments where ``done`` (one entry per environment row) is true."""
        ...

    def forget(self, env: np.ndarray, key: np.ndarray) -> None:
        """Forget the drones (env (M,), key (M,)) alone: a new drone took their slot mid-episode."""
        ...


class StatelessMemory:
    """The memory of a network that reads the current observation only: inputs are the observations."""

    def __init__(self, obs_dim: int) -> None:
        self.obs_dim = obs_dim

    @property
    def input_dim(self) -> int:
        return self.obs_dim

    def inputs(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(obs, dtype=np.float32)

    def record(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray, actions: np.ndarray) -> None:
        """Nothing to remember."""

    def reset(self, done: np.ndarray) -> None:
        """Nothing to forget."""

    def forget(self, env: np.ndarray, key: np.ndarray) -> None:
        """Nothing to forget."""


class ObsHistory:
    """The last ``history`` observations and actions of every (environment, key) drone."""

    def __init__(self, history: int, num_envs: int, num_keys: int, obs_dim: int) -> None:
        if history < 1:
            raise ValueError(f"history must be >= 1, got {history}")
        self.history = history
        self.obs = np.zeros((num_envs, num_keys, history, obs_dim), np.float32)
        self.actions = np.zeros((num_envs, num_keys, history), np.float32)
        self.fresh = np.ones((num_envs, num_keys), dtype=bool)

    @property
    def shape(self) -> tuple[int, int, int]:
        """(num_envs, num_keys, obs_dim) this memory holds now."""
        B, K, _, D = self.obs.shape
        return B, K, D

    @property
    def input_dim(self) -> int:
        return input_dim(self.shape[2], self.history)

    def grow(self, num_envs: int, num_keys: int) -> None:
        """Make room for at least ``num_envs`` x ``num_keys`` drones; new ones start fresh."""
        B, K, D = self.shape
        if num_envs <= B and num_keys <= K:
            return
        B2, K2 = max(B, num_envs), max(K, num_keys)
        obs = np.zeros((B2, K2, self.history, D), np.float32)
        actions = np.zeros((B2, K2, self.history), np.float32)
        fresh = np.ones((B2, K2), dtype=bool)
        obs[:B, :K], actions[:B, :K], fresh[:B, :K] = self.obs, self.actions, self.fresh
        self.obs, self.actions, self.fresh = obs, actions, fresh

    def _past(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Past frames (M, h, D) and actions (M, h); a fresh drone's past is ``obs`` and 0."""
        if len(env):
            self.grow(int(env.max()) + 1, int(key.max()) + 1)
        fresh = self.fresh[env, key]
        past = np.where(fresh[:, None, None], obs[:, None, :], self.obs[env, key])
        return past, np.where(fresh[:, None], 0.0, self.actions[env, key])

    def inputs(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray) -> np.ndarray:
        """Network inputs (M, input_dim) for current observations (M, D) of drones (env, key)."""
        past, acts = self._past(obs, env, key)
        return np.concatenate([obs, past.reshape(len(obs), -1), acts], -1).astype(np.float32)

    augment = inputs  # the name the rollout worker uses

    def record(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray, actions: np.ndarray) -> None:
        """Push the observations (M, D) the drones acted on and their actions (M,) in [-1, 1]."""
        past, acts = self._past(obs, env, key)
        self.obs[env, key] = np.concatenate([obs[:, None, :], past[:, :-1]], 1)
        self.actions[env, key] = np.concatenate([actions[:, None], acts[:, :-1]], 1)
        self.fresh[env, key] = False

    def reset(self, done: np.ndarray) -> None:
        """Forget the drones of the environments where ``done`` is true (rows beyond the memory hold nothing)."""
        done = np.asarray(done, dtype=bool)[: self.shape[0]]
        self.fresh[: len(done)][done] = True

    def forget(self, env: np.ndarray, key: np.ndarray) -> None:
        """Forget the drones (env (M,), key (M,)) alone (those beyond the memory hold nothing)."""
        B, K, _ = self.shape
        inside = (np.asarray(env) < B) & (np.asarray(key) < K)
        self.fresh[np.asarray(env)[inside], np.asarray(key)[inside]] = True
