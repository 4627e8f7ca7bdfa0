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
_WALL_NORMALS = ((1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0))
_WALL_NX, _WALL_NY = np.array(_WALL_NORMALS)[:, :1], np.array(_WALL_NORMALS)[:, 1:]  # (4, 1) each


def signed_distances(points: np.ndarray, geo: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance and outward unit normal from every obstacle to every point.

    points: (..., 2). Returns dist (..., K) and normal (..., K, 2), K = geo.num_obstacles.
    """
    dist, nx, ny = obstacle_columns(points.reshape(-1, 2), geo, normals=True)
    assert nx is not None and ny is not None
    shape = points.shape[:-1]
    return np.ascontiguousarray(dist.T).reshape(*shape, -1), np.stack([nx.T, ny.T], -1).reshape(*shape, -1, 2)


def obstacle_distances(points: np.ndarray, geo: Geometry) -> np.ndarray:
    """Signed distances (..., K) from every obstacle to every point, without normals."""
    return np.ascontiguousarray(obstacle_columns(points.reshape(-1, 2), geo, normals=False)[0].T).reshape(
        *points.shape[:-1], -1
    )


def obstacle_columns(
    points: np.ndarray, geo: Geometry, normals: bool
) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """Signed distances (K, M) and, with ``normals``, the normals' x and y (K, M) of M points (M, 2).

    Obstacles first, points innermost, so numpy's inner loops run over every point (a
    broadcast over a short trailing obstacle axis is several times slower).
    """
    x, y = np.ascontiguousarray(points[:, 0]), np.ascontiguousarray(points[:, 1])
    dist = np.empty((geo.num_obstacles, len(x)))
    nx = np.empty_like(dist) if normals else None
    ny = np.empty_like(dist) if normals else None
    dist[0] = x
    np.subtract(geo.width, x, out=dist[1])
    dist[2] = y
    np.subtract(geo.height, y, out=dist[3])
    if nx is not None and ny is not None:
        nx[:NUM_WALLS] = _WALL_NX
        ny[:NUM_WALLS] = _WALL_NY
    k0, k1 = NUM_WALLS, NUM_WALLS + len(geo.box_half)
    if k1 > k0:
        rx = x - geo.box_center[:, :1]  # (Kb, M)
        ry = y - geo.box_center[:, 1:]
        qx = np.abs(rx) - geo.box_half[:, :1]
        qy = np.abs(ry) - geo.box_half[:, 1:]
        ox, oy = np.maximum(qx, 0.0), np.maximum(qy, 0.0)
        out_len = np.sqrt(ox * ox + oy * oy)
        np.add(out_len, np.minimum(np.maximum(qx, qy), 0.0), out=dist[k0:k1])
        if nx is not None and ny is not None:
            sx, sy = np.sign(rx), np.sign(ry)
            outside = out_len > 0
            inv = 1.0 / np.maximum(out_len, 1e-12)
            axis_x = qx >= qy
            np.copyto(nx[k0:k1], np.where(outside, sx * ox * inv, sx * axis_x))
            np.copyto(ny[k0:k1], np.where(outside, sy * oy * inv, sy * ~axis_x))
    if len(geo.disc_radius):
        rx = x - geo.disc_center[:, :1]  # (Kd, M)
        ry = y - geo.disc_center[:, 1:]
        length = np.sqrt(rx * rx + ry * ry)
        np.subtract(length, geo.disc_radius[:, None], out=dist[k1:])
        if nx is not None and ny is not None:
            inv = 1.0 / np.maximum(length, 1e-12)
            np.copyto(nx[k1:], np.where(length > 0, rx * inv, 1.0))
            np.multiply(ry, inv, out=ny[k1:])
    return dist, nx, ny


def offsets(points: np.ndarray, others: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x and y (K, B * M) of each point (B, M, 2) from each of the K ``others`` (B, K, 2) of its batch row,
    the points innermost (a broadcast over a short trailing K axis is several times slower in numpy)."""
    M = points.shape[1]
    flat = points.reshape(-1, 2)
    return (
        flat[:, 0] - np.repeat(others[:, :, 0].T, M, axis=1),
        flat[:, 1] - np.repeat(others[:, :, 1].T, M, axis=1),
    )


def first_argmin(values: np.ndarray, smallest: np.ndarray | None = None) -> np.ndarray:
    """``values.argmin(0)`` of (K, M) NaN-free ``values`` (the first smallest of each column), given or
    taking ``smallest = values.min(0)``: K - 1 whole-row passes, faster than numpy's argmin across rows."""
    if smallest is None:
        smallest = values.min(0)
    index = np.full(values.shape[1], values.shape[0] - 1, dtype=np.intp)
    for k in range(values.shape[0] - 2, -1, -1):
        index[values[k] == smallest] = k
    return index


def nearest_obstacle(points: np.ndarray, geo: Geometry) -> tuple[np.ndarray, np.ndarray]:
    """Distance (...) and outward normal (..., 2) of the nearest obstacle or wall."""
    return nearest_obstacles(points, geo)[1:]


def nearest_obstacles(points: np.ndarray, geo: Geometry) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index into ``geo.names`` (...), distance (...) and outward normal (..., 2) of the nearest obstacle or wall."""
    shape = points.shape[:-1]
    dist, nx, ny = obstacle_columns(points.reshape(-1, 2), geo, normals=True)
    assert nx is not None and ny is not None
    k, cols = first_argmin(dist), np.arange(dist.shape[1])
    normal = np.empty((len(k), 2))
    normal[:, 0], normal[:, 1] = nx[k, cols], ny[k, cols]
    return k.reshape(shape), dist[k, cols].reshape(shape), normal.reshape(*shape, 2)


def pick_nearest(dist: np.ndarray, normal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reduce (..., K) distances and (..., K, 2) normals to the nearest obstacle's."""
    return take_obstacle(dist, normal, dist.argmin(-1))


def take_obstacle(dist: np.ndarray, normal: np.ndarray, k: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (...) and normal (..., 2) of obstacle ``k`` (...) from (..., K) distances and (..., K, 2) normals."""
    rows, cols = np.arange(k.size), k.ravel()
    d = dist.reshape(-1, dist.shape[-1])[rows, cols].reshape(k.shape)
    return d, normal.reshape(-1, *normal.shape[-2:])[rows, cols].reshape(*k.shape, 2)
