"""The one turn rule of the pursuers: at most 45 degrees a step, then a straight move.

Every pursuer obeys it, in simulation (:class:`~atdrone.envs.core.BatchedPursuit`)
and in the policies that plan a turn (greedy, VICSEK, the demo chase), so the limit
and the angle wrapping are written here once.
"""

from __future__ import annotations

import numpy as np

MAX_TURN = np.pi / 4  # radians per unit action: an action in [-1, 1] turns at most 45 degrees


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """``angle`` wrapped into [-pi, pi]."""
    return np.arctan2(np.sin(angle), np.cos(angle))


def turn(heading: np.ndarray, action: np.ndarray) -> np.ndarray:
    """The new heading after ``action`` (NaN counts as 0, clipped to [-1, 1]), wrapped."""
    return wrap_angle(heading + np.clip(np.nan_to_num(action), -1.0, 1.0) * MAX_TURN)


def turn_towards(heading: np.ndarray, desired: np.ndarray) -> np.ndarray:
    """The action in [-1, 1] that turns ``heading`` towards ``desired`` as far as the limit allows."""
    return np.clip(wrap_angle(desired - heading) / MAX_TURN, -1.0, 1.0)


def advance(pos: np.ndarray, heading: np.ndarray, step: float, width: float, height: float) -> np.ndarray:
    """Positions (..., 2) moved ``step`` metres along ``heading`` (...), held inside the arena."""
    out = pos + step * np.stack([np.cos(heading), np.sin(heading)], -1)
    out[..., 0] = np.clip(out[..., 0], 0.0, width)
    out[..., 1] = np.clip(out[..., 1], 0.0, height)
    return out
