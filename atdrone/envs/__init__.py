"""Simulators of the AT-Drone pursuit tasks and their PettingZoo / Gymnasium views."""

from atdrone.envs.core import DONE_REASONS, OBS_LAYOUT_VERSION, BatchedPursuit, PursuitState
from atdrone.envs.gym import PursuitEnv, PursuitVectorEnv, register_envs
from atdrone.envs.parallel import PursuitParallelEnv

register_envs()

__all__ = [
    "DONE_REASONS",
    "OBS_LAYOUT_VERSION",
    "BatchedPursuit",
    "PursuitEnv",
    "PursuitParallelEnv",
    "PursuitState",
    "PursuitVectorEnv",
]
