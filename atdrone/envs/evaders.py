"""The built-in evader escape policy (SPEC section 3), batched over environments.

Evaders are part of the environment. Each step an evader either wanders (calm: panic
below 0.2 and no obstacle within 0.3 m) or flees: away from the pursuers it perceives,
weighted by 1/distance, pushed off nearby obstacles, walls and other evaders, slipping
between two close pursuers when the gap allows, and following a wall rather than
running into it. Evaders turn freely and move at constant speed; a move that would
enter an obstacle slides along it or is dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from atdrone.envs.geometry import Geometry, obstacle_distances, pick_nearest, signed_distances


@dataclass(frozen=True)
class EscapeParams:
    """Constants of the escape policy (metres, steps)."""

    panic_scale: float = 2.0
    calm_panic: float = 0.2
    calm_clearance: float = 0.3
    repulsion_range: float = 0.8
    repulsion_gain: float = 0.3
    evader_radius: float = 0.1
    slip_range: float = 0.5
    follow_range: float = 0.3
    follow_drift: float = 0.5
    inertia: float = 0.25
    body_margin: float = 0.05
    wander_turn: float = np.pi / 4
    wander_steps: tuple[int, int] = (10, 15)


def panic(distance: np.ndarray, scale: float = 2.0) -> np.ndarray:
    """Panic level (exp(1 - d/scale) - 1) / (e - 1): 1 at d = 0, 0 at d = scale."""
    return (np.exp(1.0 - distance / scale) - 1.0) / (np.e - 1.0)


def _norm(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.sqrt(x * x + y * y)


def escape_directions(
    pos_e: np.ndarray,
    heading_e: np.ndarray,
    pos_p: np.ndarray,
    active: np.ndarray,
    geo: Geometry,
    perception: float,
    capture_range: float,
    p: EscapeParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Flee headings (B, E) for every evader and which evaders are calm (B, E).

    pos_e (B, E, 2), heading_e (B, E), pos_p (B, P, 2), active (B, E): not captured.
    """
    ex, ey = pos_e[..., 0], pos_e[..., 1]
    dx = ex[:, :, None] - pos_p[:, None, :, 0]  # (B, E, P)
    dy = ey[:, :, None] - pos_p[:, None, :, 1]
    d2 = dx * dx + dy * dy
    d = np.sqrt(d2)
    dmin = d.min(-1)
    obs_d, obs_n = signed_distances(pos_e, geo)  # (B, E, K), (B, E, K, 2)
    calm = (panic(dmin, p.panic_scale) < p.calm_panic) & (obs_d.min(-1) > p.calm_clearance)

    w = (d < perception) / np.maximum(d2, 1e-9)
    fx, fy = (dx * w).sum(-1), (dy * w).sum(-1)
    f = np.maximum(_norm(fx, fy), 1e-12)
    fx, fy = fx / f, fy / f

    # Obstacles, walls and the other active evaders (as discs) push the evader away.
    rx = ex[:, :, None] - ex[:, None, :]  # (B, E, E)
    ry = ey[:, :, None] - ey[:, None, :]
    rl = np.maximum(_norm(rx, ry), 1e-12)
    others = active[:, None, :] & ~np.eye(pos_e.shape[1], dtype=bool)
    ee_push = np.where(
        others, np.maximum(0.0, 1.0 / np.maximum(rl - p.evader_radius, 1e-2) - 1.0 / p.repulsion_range), 0.0
    )
    ob_push = np.maximum(0.0, 1.0 / np.maximum(obs_d, 1e-2) - 1.0 / p.repulsion_range)
    g = p.repulsion_gain
    ee_x, ee_y = g * (ee_push * rx / rl).sum(-1), g * (ee_push * ry / rl).sum(-1)

    # Intent: away from the pursuers, or through the gap between the two nearest ones.
    ix, iy = fx, fy
    if pos_p.shape[1] >= 2:
        i1 = d.argmin(-1)[..., None]
        d_rest = d.copy()
        np.put_along_axis(d_rest, i1, np.inf, -1)
        i2 = d_rest.argmin(-1)[..., None]
        d2nd = np.take_along_axis(d_rest, i2, -1)[..., 0]
        ax, ay = np.take_along_axis(dx, i1, -1)[..., 0], np.take_along_axis(dy, i1, -1)[..., 0]
        bx, by = np.take_along_axis(dx, i2, -1)[..., 0], np.take_along_axis(dy, i2, -1)[..., 0]
        slip = (d2nd < p.slip_range) & (_norm(ax - bx, ay - by) > 2 * capture_range)
        # midpoint (pa + pb) / 2 - pos_e, with pa = pos_e - (ax, ay)
        mx, my = -(ax + bx) / 2, -(ay + by) / 2
        m = np.maximum(_norm(mx, my), 1e-12)
        ix, iy = np.where(slip, mx / m, ix), np.where(slip, my / m, iy)

    # Free running: intent plus repulsion from obstacles, walls and other evaders.
    vx = ix + g * (ob_push * obs_n[..., 0]).sum(-1) + ee_x
    vy = iy + g * (ob_push * obs_n[..., 1]).sum(-1) + ee_y

    # Wall following: when the intent runs into the nearest obstacle, run along it
    # (keeping the current sense of travel when the intent is square on) and drift
    # off it gently, instead of letting the repulsion turn the evader back.
    near_d, near_n = pick_nearest(obs_d, obs_n)
    nx, ny = near_n[..., 0], near_n[..., 1]
    into = ix * nx + iy * ny
    follow = (near_d < p.follow_range) & (into < 0)
    tx, ty = -ny, nx
    along = ix * tx + iy * ty
    sense = np.where(
        np.abs(along) > 1e-6, np.sign(along), np.where(np.cos(heading_e) * tx + np.sin(heading_e) * ty >= 0, 1.0, -1.0)
    )
    off = p.follow_drift * (p.follow_range - near_d) / p.follow_range
    vx = np.where(follow, sense * tx + off * nx + ee_x, vx)
    vy = np.where(follow, sense * ty + off * ny + ee_y, vy)

    # Inertia: near a balance of pushes keep going rather than flip back and forth.
    vx = vx + p.inertia * np.cos(heading_e)
    vy = vy + p.inertia * np.sin(heading_e)

    still = (np.abs(vx) + np.abs(vy)) < 1e-12
    heading = np.where(still, heading_e, np.arctan2(vy, vx))
    return heading, calm


def move_evaders(
    pos_e: np.ndarray, heading: np.ndarray, step: float, active: np.ndarray, geo: Geometry, p: EscapeParams
) -> np.ndarray:
    """Advance active evaders by ``step`` metres along ``heading``; slide or stop at obstacles."""
    delta = (step * active)[..., None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    cand = pos_e + delta
    blocked = obstacle_distances(cand, geo).min(-1) < p.body_margin
    if not blocked.any():
        return cand
    # Only the blocked evaders need the nearest obstacle's normal: work out theirs alone.
    moved, d = cand[blocked], delta[blocked]
    n = pick_nearest(*signed_distances(moved, geo))[1]
    slid = moved - np.minimum((d * n).sum(-1), 0.0)[..., None] * n
    slid_ok = obstacle_distances(slid, geo).min(-1) >= p.body_margin
    cand[blocked] = np.where(slid_ok[..., None], slid, pos_e[blocked])
    return cand
