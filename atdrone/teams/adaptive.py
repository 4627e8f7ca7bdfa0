"""The adaptive-teaming Gymnasium env: one learner team beside unseen zoo partners.

Registered as ``atdrone/AdaptiveTeaming-v0`` by :func:`atdrone.envs.gym.register_envs`
(by import string, so the envs layer never imports the teams above it).
"""

from __future__ import annotations

import numpy as np
from gymnasium import spaces

from atdrone.config import TaskConfig
from atdrone.envs.core import OBS_BOUND, BatchedPursuit
from atdrone.envs.gym import SingleView
from atdrone.envs.single import SingleEnv
from atdrone.policies.zoo import Zoo, load_zoo
from atdrone.teams.match import Match


class AdaptiveTeamingEnv(SingleView):
    """Adaptive teaming: the agent steers the learner drones, unseen zoo partners the rest.

    Description
        One pursuit environment of ``task`` (SPEC sections 1-6). Every episode a
        :class:`~atdrone.teams.match.Match` shuffles which pursuer slots the agent's num_ctrl
        learner drones fill and draws a zoo member for each of the other num_unctrl
        slots; the partners act on their own, the evaders are the environment.

    Action Space
        Box(-1, 1, (num_ctrl,), float32): one turn per learner drone, heading +=
        a * pi/4 (45 degrees at most), in the order of ``team["learner_slots"]``.

    Observation Space
        Box(-1.5, 1.5, (num_ctrl, obs_dim), float32): the learner drones' rows of the
        core's observation (layout in :mod:`atdrone.envs.observation`, obs_dim = 4 (num_e + num_p)).

    Rewards
        The team's shared reward (:mod:`atdrone.envs.core`).

    Starting State
        The core's spawn; learner slots and partner members drawn anew per episode.

    Episode End
        Terminated when every evader is captured or on a collision; truncated at the
        task horizon. The step info that ends an episode carries ``team``:
        ``learner_slots``, ``partner_slots``, ``partner_members`` and ``partners``
        (member names) of that episode, besides the episode statistics. ``reset``
        returns the team of the episode it starts as ``info["team"]``.

    Arguments
        task: task name, path or TaskConfig (default "4p2e1o"); zoo: zoo name, path
        or Zoo (default "zoo1"); a zoo whose checkpoint members are missing raises
        :class:`~atdrone.policies.zoo.ZooError` here. render_mode: None or "rgb_array".

    Version History
        v0: first version (observation layout version 1).
    """

    def __init__(self, task: TaskConfig | str = "4p2e1o", zoo: Zoo | str = "zoo1", render_mode: str | None = None):
        self.zoo = zoo if not isinstance(zoo, str) else load_zoo(zoo)
        self.match = Match(BatchedPursuit(task, num_envs=1), self.zoo)
        self.env = SingleEnv(self.match)
        self.render_mode = render_mode
        core = self.env.core
        self.observation_space = spaces.Box(-OBS_BOUND, OBS_BOUND, (self.match.num_ctrl, core.obs_dim), np.float32)
        self.action_space = spaces.Box(-1.0, 1.0, (self.match.num_ctrl,), np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        super().reset(seed=seed)
        obs = self.env.reset(seed=seed)
        return obs, {"team": {k: v[0].tolist() for k, v in self.match.team().items()}}
