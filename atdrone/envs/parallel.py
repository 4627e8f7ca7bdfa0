"""PettingZoo ParallelEnv view of the pursuit core: one agent per pursuer.

Description
    The AT-Drone pursuit task of :mod:`atdrone.envs.core` as a PettingZoo parallel
    environment. Agents are ``pursuer_0`` ... ``pursuer_{num_p-1}``; evaders are part
    of the environment.

Action Space
    Box(-1, 1, (1,)) per agent: the turn, as a fraction of 45 degrees.

Observation Space
    Box(-1.5, 1.5, (obs_dim,)) per agent, the layout of ``atdrone.envs.core``.

Rewards
    The shared team reward, the same for every agent.

Episode End
    terminations: every evader captured, or a collision; truncations: the horizon.
    After either every agent leaves ``agents`` and ``reset()`` starts the next episode.

Arguments
    task: task name, path or TaskConfig; seed: seeds the core's Generator;
    render_mode: None or "rgb_array".
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np
from gymnasium import spaces
from pettingzoo import ParallelEnv

from atdrone.config import TaskConfig
from atdrone.envs.core import OBS_BOUND
from atdrone.envs.single import SingleEnv


class PursuitParallelEnv(ParallelEnv):
    """PettingZoo view of one pursuit environment (see the module docstring)."""

    metadata = {
        "name": "atdrone_pursuit_v0",
        "render_modes": ["rgb_array"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(self, task: TaskConfig | str = "4p2e1o", seed: int | None = None, render_mode: str | None = None):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode must be None or 'rgb_array', got {render_mode!r}")
        self.env = SingleEnv(task, seed=seed)
        self.render_mode = render_mode
        self.possible_agents = [f"pursuer_{i}" for i in range(self.env.core.num_p)]
        self.agents: list[str] = []
        self._obs_space = spaces.Box(-OBS_BOUND, OBS_BOUND, (self.env.core.obs_dim,), np.float32)
        self._act_space = spaces.Box(-1.0, 1.0, (1,), np.float32)

    @functools.cache  # noqa: B019 - spaces are fixed per agent
    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    @functools.cache  # noqa: B019
    def action_space(self, agent: str) -> spaces.Box:
        return self._act_space

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        obs = self.env.reset(seed=seed)
        self.agents = list(self.possible_agents)
        return {a: obs[i] for i, a in enumerate(self.agents)}, {a: {} for a in self.agents}

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ValueError(f"no action for {missing}")
        act = np.array([np.asarray(actions[a], dtype=np.float64).reshape(-1)[0] for a in self.possible_agents])
        out = self.env.step(act)
        names = self.agents
        obs = {a: out.obs[i] for i, a in enumerate(names)}
        rewards = dict.fromkeys(names, out.reward)
        terms = dict.fromkeys(names, out.terminated)
        truncs = dict.fromkeys(names, out.truncated)
        infos = {a: out.info for a in names}
        if out.terminated or out.truncated:
            self.agents = []
        return obs, rewards, terms, truncs, infos

    def state(self) -> np.ndarray:
        """Global state: every drone's position and heading, flattened."""
        s = self.env.core.state
        return np.concatenate([s.pos[0].ravel(), s.heading[0]]).astype(np.float32)

    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            return None
        from atdrone.envs.render import render_frame

        return render_frame(self.env.core, 0)

    def close(self) -> None:
        pass
