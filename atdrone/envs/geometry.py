"""Exact distances from points to the arena walls and to box and disc obstacles.

Every obstacle, the four walls included, is a signed distance function: positive
outside, negative inside, with a unit normal pointing from the obstacle towards the
point. The walls come first (left, right, bottom, top), then boxes, then discs, in
the order of the task's ``site.obstacles``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from atdrone.config import Box, TaskConfig


@dataclass(frozen=True)
class Geometry:
    """The static obstacles of a task as arrays.

    width, height: arena size. box_center, box_half: (Kb, 2). disc_center: (Kd, 2),
    disc_radius: (Kd,). names: one per obstacle, walls first.
    """

    width: float
    height: float
    box_center: np.ndarray
    box_half: np.ndarray
    disc_center: np.ndarray
    disc_radius: np.ndarray
    names: tuple[str, ...]

    @classmethod
    def from_config(cls, cfg: TaskConfig) -> Geometry:
        boxes = [(n, o) for n, o in cfg.site.obstacles.items() if isinstance(o, Box)]
        discs = [(n, o) for n, o in cfg.site.obstacles.items() if not isinstance(o, Box)]
        lo = np.array([[o.x[0], o.y[0]] for _, o in boxes], dtype=np.float64).reshape(-1, 2)
        hi = np.array([[o.x[1], o.y[1]] for _, o in boxes], dtype=np.float64).reshape(-1, 2)
        return cls(
            width=cfg.site.boundary.width,
            height=cfg.site.boundary.height,
            box_center=(lo + hi) / 2,
            box_half=(hi - lo) / 2,
            disc_center=np.array([o.center for _, o in discs], dtype=np.float64).reshape(-1, 2),
            disc_radius=np.array([o.radius for _, o in discs], dtype=np.float64),
            names=(
                "wall_left",
                "wall_right",
                "wall_bottom",
                "wall_top",
                *tuple(n for n, _ in boxes),
                *tuple(n for n, _ in discs),
            ),
        )

    @property
    def num_obstacles(self) -> int:
        """Obstacles including the four walls."""
        return len(self.names)


NUM_WALLS = 4  # the first entries of Geometry.names
_WALL_NX = np.array([1.0, -1.0, 0.0, 0.0])
_WALL_NY = np.array([0.0, 0.0, 1.0, -1.0])


def signed_distances(points: np.ndarray, geo: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance and outward unit normal from every obstacle to every point.

    points: (..., 2). Returns dist (..., K) and normal (..., K, 2), K = geo.num_obstacles.
    """
    dist, normal = _sdf(points, geo, normals=True)
    assert normal is not None
    return dist, normal


def obstacle_distances(points: np.ndarray, geo: Geometry) -> np.ndarray:
    """Signed distances (..., K) from every obstacle to every point, without normals."""
    return _sdf(points, geo, normals=False)[0]


def _sdf(points: np.ndarray, geo: Geometry, normals: bool) -> tuple[np.ndarray, np.ndarray | None]:
    x, y = points[..., 0], points[..., 1]
    dists = [np.stack([x, geo.width - x, y, geo.height - y], -1)]
    nx = [np.broadcast_to(_WALL_NX, dists[0].shape)]
    ny = [np.broadcast_to(_WALL_NY, dists[0].shape)]
    if len(geo.box_half):
        rx = x[..., None] - geo.box_center[:, 0]
        ry = y[..., None] - geo.box_center[:, 1]
        qx = np.abs(rx) - geo.box_half[:, 0]
        qy = np.abs(ry) - geo.box_half[:, 1]
        ox, oy = np.maximum(qx, 0.0), np.maximum(qy, 0.0)
        out_len = np.sqrt(ox * ox + oy * oy)
        dists.append(out_len + np.minimum(np.maximum(qx, qy), 0.0))
        if normals:
            sx, sy = np.sign(rx), np.sign(ry)
            outside = out_len > 0
            inv = 1.0 / np.maximum(out_len, 1e-12)
            axis_x = qx >= qy
            nx.append(np.where(outside, sx * ox * inv, sx * axis_x))
            ny.append(np.where(outside, sy * oy * inv, sy * ~axis_x))
    if len(geo.disc_radius):
        rx = x[..., None] - geo.disc_center[:, 0]
        ry = y[..., None] - geo.disc_center[:, 1]
        length = np.sqrt(rx * rx + ry * ry)
        dists.append(length - geo.disc_radius)
        if normals:
            inv = 1.0 / np.maximum(length, 1e-12)
            nx.append(np.where(length > 0, rx * inv, 1.0))
            ny.append(ry * inv)
    dist = np.concatenate(dists, -1)
    if not normals:
        return dist, None
    return dist, np.stack([np.concatenate(nx, -1), np.concatenate(ny, -1)], -1)


def nearest_obstacle(points: np.ndarray, geo: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Distance (...) and outward normal (..., 2) of the nearest obstacle or wall."""
    dist, normal = signed_distances(points, geo)
    return pick_nearest(dist, normal)


def pick_nearest(dist: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reduce (..., K) distances and (..., K, 2) normals to the nearest obstacle's."""
    k = dist.argmin(-1)[..., None]
    d = np.take_along_axis(dist, k, -1)[..., 0]
    n = np.take_along_axis(normal, k[..., None], -2)[..., 0, :]
    return d, n
