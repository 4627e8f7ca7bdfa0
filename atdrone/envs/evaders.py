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

from atdrone.envs.geometry import (
    Geometry,
    first_argmin,
    obstacle_columns,
    obstacle_distances,
    offsets,
    pick_nearest,
    signed_distances,
)


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


def last_axis_sum(terms: np.ndarray) -> np.ndarray:
    """``terms.sum(0)`` rounded as numpy sums a contiguous short last axis (``np.moveaxis(terms, 0, -1).sum(-1)``).

    numpy adds a row from 0.0 one term after another below 8 terms and in 8 running
    partial sums from 8 on (up to its pairwise block of 128 terms; the simulator sums a few);
    adding whole (n, M) rows the same way keeps those bits with long inner loops.
    """
    n = terms.shape[0]
    if n > 128:
        raise ValueError(f"last_axis_sum follows numpy's order up to 128 terms, got {n}")
    if n < 8:
        acc = -0.0 + terms[0]
        for i in range(1, n):
            acc += terms[i]
        return 0.0 + acc
    r = [terms[k].copy() for k in range(8)]
    i = 8
    while i + 8 <= n:
        for k in range(8):
            r[k] += terms[i + k]
        i += 8
    acc = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    for k in range(i, n):
        acc += terms[k]
    return 0.0 + acc


def _column_pick(values: np.ndarray, index: np.ndarray) -> np.ndarray:
    """values[index[m], m] for every column m of (n, M) ``values``."""
    return values[index, np.arange(values.shape[1])]


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
    Pairs are worked out as (other, evader) arrays, the B * E evaders innermost.
    """
    B, E, P = pos_e.shape[0], pos_e.shape[1], pos_p.shape[1]
    flat = pos_e.reshape(-1, 2)
    dx, dy = offsets(pos_e, pos_p)  # (P, M)
    d2 = dx * dx + dy * dy
    d = np.sqrt(d2)
    dmin = d.min(0)
    obs_d, obs_nx, obs_ny = obstacle_columns(flat, geo, normals=True)  # (K, M) each
    assert obs_nx is not None and obs_ny is not None
    obs_min = obs_d.min(0)
    calm = (panic(dmin, p.panic_scale) < p.calm_panic) & (obs_min > p.calm_clearance)

    w = (d < perception) / np.maximum(d2, 1e-9)
    fx, fy = last_axis_sum(dx * w), last_axis_sum(dy * w)
    f = np.maximum(_norm(fx, fy), 1e-12)
    fx, fy = fx / f, fy / f

    # Obstacles, walls and the other active evaders (as discs) push the evader away.
    rx, ry = offsets(pos_e, pos_e)  # (E, M): evader m from evader k of its env
    rl = np.maximum(_norm(rx, ry), 1e-12)
    others = np.repeat(active.T, E, axis=1) & (np.arange(E)[:, None] != np.arange(B * E) % E)
    ee_push = np.maximum(0.0, 1.0 / np.maximum(rl - p.evader_radius, 1e-2) - 1.0 / p.repulsion_range)
    ee_push[~others] = 0.0
    ob_push = np.maximum(0.0, 1.0 / np.maximum(obs_d, 1e-2) - 1.0 / p.repulsion_range)
    g = p.repulsion_gain
    ee_x, ee_y = g * last_axis_sum(ee_push * rx / rl), g * last_axis_sum(ee_push * ry / rl)

    # Intent: away from the pursuers, or through the gap between the two nearest ones.
    ix, iy = fx, fy
    if P >= 2:
        i1 = first_argmin(d, dmin)
        d_rest = d.copy()
        d_rest[i1, np.arange(d.shape[1])] = np.inf
        d2nd = d_rest.min(0)
        i2 = first_argmin(d_rest, d2nd)
        ax, ay = _column_pick(dx, i1), _column_pick(dy, i1)
        bx, by = _column_pick(dx, i2), _column_pick(dy, i2)
        slip = (d2nd < p.slip_range) & (_norm(ax - bx, ay - by) > 2 * capture_range)
        # midpoint (pa + pb) / 2 - pos_e, with pa = pos_e - (ax, ay)
        mx, my = -(ax + bx) / 2, -(ay + by) / 2
        m = np.maximum(_norm(mx, my), 1e-12)
        ix, iy = np.where(slip, mx / m, ix), np.where(slip, my / m, iy)

    # Free running: intent plus repulsion from obstacles, walls and other evaders.
    vx = ix + g * last_axis_sum(ob_push * obs_nx) + ee_x
    vy = iy + g * last_axis_sum(ob_push * obs_ny) + ee_y

    # Wall following: when the intent runs into the nearest obstacle, run along it
    # (keeping the current sense of travel when the intent is square on) and drift
    # off it gently, instead of letting the repulsion turn the evader back.
    k = first_argmin(obs_d, obs_min)
    near_d, nx, ny = _column_pick(obs_d, k), _column_pick(obs_nx, k), _column_pick(obs_ny, k)
    into = ix * nx + iy * ny
    follow = (near_d < p.follow_range) & (into < 0)
    tx, ty = -ny, nx
    along = ix * tx + iy * ty
    head = heading_e.reshape(-1)
    cos_h, sin_h = np.cos(head), np.sin(head)
    sense = np.where(np.abs(along) > 1e-6, np.sign(along), np.where(cos_h * tx + sin_h * ty >= 0, 1.0, -1.0))
    off = p.follow_drift * (p.follow_range - near_d) / p.follow_range
    vx = np.where(follow, sense * tx + off * nx + ee_x, vx)
    vy = np.where(follow, sense * ty + off * ny + ee_y, vy)

    # Inertia: near a balance of pushes keep going rather than flip back and forth.
    vx = vx + p.inertia * cos_h
    vy = vy + p.inertia * sin_h

    still = (np.abs(vx) + np.abs(vy)) < 1e-12
    heading = np.where(still, head, np.arctan2(vy, vx))
    return heading.reshape(B, E), calm.reshape(B, E)


def move_evaders(
    pos_e: np.ndarray, heading: np.ndarray, step: float, active: np.ndarray, geo: Geometry, p: EscapeParams
) -> np.ndarray:
    """Advance active evaders by ``step`` metres along ``heading``; slide or stop at obstacles."""
    delta = (step * active)[..., None] * np.stack([np.cos(heading), np.sin(heading)], -1)
    cand = pos_e + delta
    blocked = (
        obstacle_columns(cand.reshape(-1, 2), geo, normals=False)[0].min(0).reshape(pos_e.shape[:-1]) < p.body_margin
    )
    if not blocked.any():
        return cand
    # Only the blocked evaders need the nearest obstacle's normal: work out theirs alone.
    moved, d = cand[blocked], delta[blocked]
    n = pick_nearest(*signed_distances(moved, geo))[1]
    slid = moved - np.minimum((d * n).sum(-1), 0.0)[..., None] * n
    slid_ok = obstacle_distances(slid, geo).min(-1) >= p.body_margin
    cand[blocked] = np.where(slid_ok[..., None], slid, pos_e[blocked])
    return cand
