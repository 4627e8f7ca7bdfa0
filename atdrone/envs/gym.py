"""Gymnasium views of the pursuit core, registered under the "atdrone/" namespace.

- ``atdrone/Pursuit-v0``: one environment in which the agent steers every pursuer
  (observation (num_p, obs_dim), action (num_p,)); ``gymnasium.make_vec`` with
  ``vectorization_mode="vector_entry_point"`` returns :class:`PursuitVectorEnv`,
  the batched core itself as a Gymnasium VectorEnv.
- ``atdrone/AdaptiveTeaming-v0``: the learner steers the task's num_ctrl pursuers and
  unseen zoo partners the rest (:class:`atdrone.teams.adaptive.AdaptiveTeamingEnv`,
  registered here by its import string: envs imports nothing from teams).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv

from atdrone.config import TaskConfig
from atdrone.envs.core import CAPTURED, COLLISION, DONE_REASONS, OBS_BOUND, TIMEOUT, BatchedPursuit
from atdrone.envs.single import SingleEnv


def _spaces(core: BatchedPursuit) -> tuple[spaces.Box, spaces.Box]:
    obs = spaces.Box(-OBS_BOUND, OBS_BOUND, (core.num_p, core.obs_dim), np.float32)
    act = spaces.Box(-1.0, 1.0, (core.num_p,), np.float32)
    return obs, act


class SingleView(gym.Env):
    """A Gymnasium env over a SingleEnv (``self.env``): stepping and rendering."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}
    env: SingleEnv
    render_mode: str | None

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict]:
        out = self.env.step(action)
        return out.obs, out.reward, out.terminated, out.truncated, out.info

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        from atdrone.envs.render import render_frame

        return render_frame(self.env.core, 0)


class PursuitEnv(SingleView):
    """One pursuit environment, every pursuer steered by the agent."""

    def __init__(self, task: TaskConfig | str = "4p2e1o", render_mode: str | None = None) -> None:
        self.env = SingleEnv(task)
        self.render_mode = render_mode
        self.observation_space, self.action_space = _spaces(self.env.core)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        return self.env.reset(seed=seed), {}


class PursuitVectorEnv(VectorEnv):
    """The batched core as a Gymnasium VectorEnv (same-step autoreset)."""

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, task: TaskConfig | str = "4p2e1o", num_envs: int = 1, seed: int | None = None, **_: Any):
        self.core = BatchedPursuit(task, num_envs=num_envs, seed=seed)
        self.num_envs = num_envs
        self.single_observation_space, self.single_action_space = _spaces(self.core)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, num_envs)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        return self.core.reset(seed=seed), {}

    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        obs, rewards, _, info = self.core.step(actions)
        reason = info["done_reason"]
        terminated = (reason == CAPTURED) | (reason == COLLISION)
        info = dict(info, done_reason_name=np.array(DONE_REASONS)[reason])
        return obs, rewards[:, 0], terminated, reason == TIMEOUT, info


def register_envs() -> None:
    """Register the "atdrone/" ids with Gymnasium (idempotent)."""
    if "atdrone/Pursuit-v0" not in gym.registry:
        gym.register(
            id="atdrone/Pursuit-v0",
            entry_point="atdrone.envs.gym:PursuitEnv",
            vector_entry_point="atdrone.envs.gym:PursuitVectorEnv",
            max_episode_steps=None,
            disable_env_checker=False,
        )
    if "atdrone/AdaptiveTeaming-v0" not in gym.registry:
        gym.register(
            id="atdrone/AdaptiveTeaming-v0",
            entry_point="atdrone.teams.adaptive:AdaptiveTeamingEnv",
            max_episode_steps=None,
            disable_env_checker=False,
        )
