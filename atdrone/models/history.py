"""Per-drone memory of past observations and actions, for networks that read motion.

A single observation gives each teammate's distance and bearing but not where it is
heading, so a drone cannot tell a teammate that will pass from one that will fly into
it. With ``history`` h > 0 the networks read, besides the current observation (D), the
drone's own last h observations (newest first) and its last h actions (the NAHT-D idea
of reading recent steps, SPEC section 10): the network input is

    [obs_t (D), obs_t-1 (D), ..., obs_t-h (D), a_t-1, ..., a_t-h]   (D * (h + 1) + h)

At an episode's first step the past frames repeat the current observation and the past
actions are 0 (no motion seen yet). Memory is keyed by (environment, key): a pursuer
slot for zoo policies, a learner index for rollout workers.
"""

from __future__ import annotations

import numpy as np


def input_dim(obs_dim: int, history: int) -> int:
    """Width of the network input for raw observations of ``obs_dim`` and ``history`` past frames."""
    return obs_dim * (history + 1) + history


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
        """(num_envs, num_keys, obs_dim) this memory was made for."""
        B, K, _, D = self.obs.shape
        return B, K, D

    def _past(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Past frames (M, h, D) and actions (M, h); a fresh drone's past is ``obs`` and 0."""
        fresh = self.fresh[env, key]
        past = np.where(fresh[:, None, None], obs[:, None, :], self.obs[env, key])
        return past, np.where(fresh[:, None], 0.0, self.actions[env, key])

    def augment(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray) -> np.ndarray:
        """Network inputs (M, input_dim) for current observations (M, D) of drones (env, key)."""
        past, acts = self._past(obs, env, key)
        return np.concatenate([obs, past.reshape(len(obs), -1), acts], -1).astype(np.float32)

    def record(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray, actions: np.ndarray) -> None:
        """Push the observations (M, D) the drones acted on and their actions (M,) in [-1, 1]."""
        past, acts = self._past(obs, env, key)
        self.obs[env, key] = np.concatenate([obs[:, None, :], past[:, :-1]], 1)
        self.actions[env, key] = np.concatenate([actions[:, None], acts[:, :-1]], 1)
        self.fresh[env, key] = False

    def reset(self, done: np.ndarray) -> None:
        """Forget the drones of the environments where ``done`` (B,) is true."""
        self.fresh[np.asarray(done, dtype=bool)] = True
