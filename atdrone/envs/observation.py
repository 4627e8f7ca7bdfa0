"""What a pursuer sees: a poses record in, egocentric observations out (a pure function).

A :class:`Poses` record holds what a motion-capture frame gives (positions,
headings, which evaders are caught) plus the :class:`Arena` they move in;
:func:`observe` turns it into the observation every policy reads. The simulator
(:class:`~atdrone.envs.core.BatchedPursuit`) fills the same record and calls the
same function, so a drone flying from mocap sees exactly what it saw in training.

Layout (``OBS_LAYOUT_VERSION`` 1), per pursuer, blocks of 4 features
``[mask, distance / 5, sin(bearing), cos(bearing)]``, bearing from the pursuer's own
heading (counter-clockwise positive): num_e evader blocks (mask 0 and zeros when the
evader is captured or beyond reception_range), 1 block for the nearest obstacle or
wall (mask 1, signed distance), num_p - 1 teammate blocks (mask 0 and zeros beyond
reception_range). obs_dim = 4 (num_e + num_p).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from atdrone.config import TaskConfig, load_task
from atdrone.envs.geometry import Geometry, nearest_obstacle

OBS_LAYOUT_VERSION = 1
ENTITY_FEATURES = 4
DIST_SCALE = 5.0
OBS_BOUND = 1.5  # |feature| never exceeds this: distances / 5 in a 3.6 x 5 arena, sin, cos, masks


def obs_dim(num_p: int, num_e: int) -> int:
    """Length of one pursuer's observation."""
    return ENTITY_FEATURES * (num_e + num_p)


@dataclass(frozen=True)
class Arena:
    """The fixed facts of a task that observing and steering need.

    geometry: walls and obstacles; num_p pursuers, num_e evaders; reception_range
    (metres a pursuer perceives); capture_range; step: metres a pursuer moves a step
    (velocity_p * dt).
    """

    geometry: Geometry
    num_p: int
    num_e: int
    reception_range: float
    capture_range: float
    step: float

    @classmethod
    def from_config(cls, cfg: TaskConfig | str) -> Arena:
        """The arena of a task (a TaskConfig, task name or path)."""
        cfg = load_task(cfg)
        return cls(
            geometry=Geometry.from_config(cfg),
            num_p=cfg.players.num_p,
            num_e=cfg.players.num_e,
            reception_range=cfg.players.reception_range,
            capture_range=cfg.task.capture_range,
            step=cfg.players.velocity_p * cfg.dt,
        )

    @property
    def num_agents(self) -> int:
        return self.num_p + self.num_e

    @property
    def obs_dim(self) -> int:
        return obs_dim(self.num_p, self.num_e)


@dataclass(frozen=True)
class Poses:
    """Where every drone of B environments is: a motion-capture frame, batched.

    pos (B, N, 2) metres, pursuers first then evaders; heading (B, N) radians;
    captured (B, E) bool; arena: the task they play.
    """

    pos: np.ndarray
    heading: np.ndarray
    captured: np.ndarray
    arena: Arena

    def __post_init__(self) -> None:
        n, e = self.arena.num_agents, self.arena.num_e
        b = self.pos.shape[0] if self.pos.ndim == 3 else -1
        for name, arr, shape in (
            ("pos", self.pos, (b, n, 2)),
            ("heading", self.heading, (b, n)),
            ("captured", self.captured, (b, e)),
        ):
            if arr.shape != shape:
                raise ValueError(f"Poses.{name} must have shape (B, {', '.join(map(str, shape[1:]))}), got {arr.shape}")

    @property
    def num_envs(self) -> int:
        return self.pos.shape[0]


@cache
def _entities(num_p: int, num_e: int) -> tuple[np.ndarray, np.ndarray]:
    """(S, P) the entity (index into the N drones) each pursuer sees in each of its S = num_e + num_p - 1
    evader and teammate blocks, and (S,) the observation blocks they fill (the obstacle block sits
    between; read-only, shared)."""
    others = np.array([[j for j in range(num_p) if j != i] for i in range(num_p)], dtype=np.intp)
    ev = np.arange(num_p, num_p + num_e)[None].repeat(num_p, 0)
    ents = np.ascontiguousarray(np.concatenate([ev, others.reshape(num_p, num_p - 1)], 1).T)
    blocks = np.r_[0:num_e, num_e + 1 : num_e + num_p]
    ents.flags.writeable = blocks.flags.writeable = False
    return ents, blocks


def observe(poses: Poses, obstacles: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Observations (B, num_p, obs_dim) float32 of every pursuer in ``poses`` (layout above).

    ``obstacles``: the distance (B, P) and normal (B, P, 2) of each pursuer's nearest obstacle
    or wall (:func:`~atdrone.envs.geometry.nearest_obstacle`), when already known. Worked out as
    (block, B, P) arrays (the long axes innermost) and transposed into place once.
    """
    a = poses.arena
    P, E, B = a.num_p, a.num_e, poses.pos.shape[0]
    N = P + E
    pos_p, head_p = poses.pos[:, :P], poses.heading[:, :P]
    hx, hy = np.cos(head_p), np.sin(head_p)
    ents, blocks = _entities(P, E)
    to = ents[:, None, :] + N * np.arange(B)[:, None]  # (S, B, P) flat indices of each block's entity
    flat = poses.pos.reshape(-1, 2)
    dx = flat[:, 0].take(to) - pos_p[..., 0]
    dy = flat[:, 1].take(to) - pos_p[..., 1]
    d = np.sqrt(dx * dx + dy * dy)
    inv = 1.0 / np.maximum(d, 1e-12)
    mask = d <= a.reception_range
    mask[:E] &= ~poses.captured.T[:, :, None]
    o_d, o_n = obstacles if obstacles is not None else nearest_obstacle(pos_p, a.geometry)
    tx, ty = -o_n[..., 0], -o_n[..., 1]  # towards the obstacle
    out = np.empty((E + P, ENTITY_FEATURES, B, P), dtype=np.float32)
    out[blocks, 0] = mask
    out[blocks, 1] = d * (mask / DIST_SCALE)
    out[blocks, 2] = (hx * dy - hy * dx) * inv * mask
    out[blocks, 3] = (hx * dx + hy * dy) * inv * mask
    out[E, 0] = 1.0
    out[E, 1] = o_d / DIST_SCALE
    out[E, 2] = hx * ty - hy * tx
    out[E, 3] = hx * tx + hy * ty
    return out.transpose(2, 3, 0, 1).reshape(B, P, obs_dim(P, E))
