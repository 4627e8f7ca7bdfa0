"""Transits between episodes: straight lines at a constant speed, started at times that keep every pair apart.

:func:`plan_transit` is pure: given where the drones are and where they must go, it
gives each drone a start delay such that, with every drone hovering before its start and
after its arrival, no two drones' separation ellipsoids (with ``margin``) touch at any
time. Drones are scheduled one after another (prioritised planning): each takes the
earliest start that keeps it clear of the drones scheduled before it, over their whole
trajectories, hovering included. Several orders are tried (index order, longest first,
shortest first, then random ones); a plan that cannot be made (drones on each other's
targets) raises :class:`TransitBlocked`, and the flight ends with that reason rather
than fly a conflicting line.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from atdrone.deploy.shield import Obstacles, ellipsoid_distance, obstacle_distance

MARGIN = 1.3  # separation ellipsoids kept between drones on a planned transit
LEASH = 0.15  # m: a reference the loop moves (a policy's, a backup's line) never runs further ahead of its drone


class TransitBlocked(RuntimeError):
    """No conflict-free straight-line schedule exists for these starts and targets."""


@dataclass(frozen=True)
class Transit:
    """Lines at ``speed`` from ``start`` (D, 3) through ``via`` (D, 3; NaN: straight) to ``end`` (D, 3), drone i
    leaving at ``delay[i]``."""

    start: np.ndarray
    end: np.ndarray
    delay: np.ndarray
    speed: float
    via: np.ndarray | None = None

    def _legs(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        via = np.full_like(self.start, np.nan) if self.via is None else self.via
        mid = np.where(np.isfinite(via).all(1)[:, None], via, (self.start + self.end) / 2)
        first = np.linalg.norm(mid - self.start, axis=1) / self.speed
        second = np.linalg.norm(self.end - mid, axis=1) / self.speed
        return mid, first, second

    @property
    def duration(self) -> np.ndarray:
        _, first, second = self._legs()
        return np.asarray(first + second)

    @property
    def total(self) -> float:
        return float((self.delay + self.duration).max(initial=0.0))

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Reference positions (D, 3) and velocities (D, 3) at ``t`` seconds after the transit began."""
        mid, first, second = self._legs()
        tau = np.clip(t - self.delay, 0.0, None)
        on_first = tau < first
        f1 = np.clip(tau / np.maximum(first, 1e-9), 0.0, 1.0)
        f2 = np.clip((tau - first) / np.maximum(second, 1e-9), 0.0, 1.0)
        pos = np.where(
            on_first[:, None], self.start + (mid - self.start) * f1[:, None], mid + (self.end - mid) * f2[:, None]
        )
        d1 = (mid - self.start) / np.maximum(first, 1e-9)[:, None]
        d2 = (self.end - mid) / np.maximum(second, 1e-9)[:, None]
        moving = (t >= self.delay) & (tau < first + second)
        vel = np.where(on_first[:, None], d1, d2)
        return pos, np.where(moving[:, None], vel, 0.0)


def _clear(paths: np.ndarray, k: int, others: list[int], radius: float, half_height: float, margin: np.ndarray) -> bool:
    """Whether drone k's sampled path (T, 3) stays ``margin[k, o]`` (scaled) clear of each of ``others``' paths."""
    if not others:
        return True
    scaled = ellipsoid_distance(paths[others] - paths[k], radius, half_height)  # (len(others), T)
    return bool((scaled >= margin[k, others][:, None] - 1e-9).all())


def _detours(
    start: np.ndarray,
    end: np.ndarray,
    bounds: tuple[np.ndarray, np.ndarray] | None,
    obstacles: Obstacles | None = None,
    clearance: float = 0.15,
) -> list[np.ndarray]:
    """Waypoints: 0.4, 0.8 and 1.2 m either side of the line's middle, then 0.5 m from the start in eight
    directions (a first step out of a crowd), then past each end (``clearance`` + 0.1, 0.4 and 0.7 m out),
    side and corner of every obstacle (``clearance`` + 0.1 m out): the ways around a bar whose middle the
    line crosses, nearest first, inside ``bounds``."""
    mid = (start + end) / 2
    d = end[:2] - start[:2]
    n = np.array([-d[1], d[0]]) / max(float(np.hypot(*d)), 1e-9) if np.hypot(*d) > 1e-9 else np.array([1.0, 0.0])
    points = [mid[:2] + n * off for off in (0.4, -0.4, 0.8, -0.8, 1.2, -1.2)]
    points += [start[:2] + 0.5 * np.array([np.cos(a), np.sin(a)]) for a in np.arange(8) * np.pi / 4]
    if obstacles is not None:
        beyond = clearance + 0.1
        # past each end, and further out: a line from above a bar's middle to below it, bent at one point,
        # clears both corners of an end only from a point well past that end
        around = [
            (cx + sx * (hx + beyond + out), cy)
            for cx, cy, hx, _ in obstacles.boxes
            for sx in (-1, 1)
            for out in (0.0, 0.3, 0.6)
        ]
        around += [(cx, cy + sy * (hy + beyond)) for cx, cy, _, hy in obstacles.boxes for sy in (-1, 1)]
        # and past each corner: a line from beside a bar's middle to the point past its end cuts the corner
        around += [
            (cx + sx * (hx + beyond), cy + sy * (hy + beyond))
            for cx, cy, hx, hy in obstacles.boxes
            for sx in (-1, 1)
            for sy in (-1, 1)
        ]
        around += [
            (cx + (r + beyond) * np.cos(a), cy + (r + beyond) * np.sin(a))
            for cx, cy, r in obstacles.discs
            for a in np.arange(4) * np.pi / 2
        ]
        points += sorted((np.array(p) for p in around), key=lambda p: float(np.hypot(*(p - mid[:2]))))
    out = []
    for p in points:
        w = mid.copy()
        w[:2] = np.clip(p, *bounds) if bounds is not None else p
        out.append(w)
    return out


def plan_transit(
    start: np.ndarray,
    end: np.ndarray,
    speed: float,
    radius: float,
    half_height: float,
    margin: float = MARGIN,
    delay_step: float = 0.5,
    max_delay: float = 20.0,
    sample: float = 0.1,
    tries: int = 20,
    bounds: tuple[np.ndarray, np.ndarray] | None = None,
    obstacles: Obstacles | None = None,
    clearance: float = 0.15,
) -> Transit:
    """Start delays (and detours) for transits that keep every pair ``margin`` clear (see the module docstring)."""
    start = np.asarray(start, dtype=np.float64).reshape(-1, 3)
    end = np.asarray(end, dtype=np.float64).reshape(-1, 3)
    D = len(start)
    straight = np.linalg.norm(end - start, axis=1) / speed
    horizon = max_delay + 2.5 * float(straight.max(initial=0.0)) + 6.0
    times = np.arange(0.0, horizon, sample)

    def path(i: int, d: float, via: np.ndarray | None) -> np.ndarray:
        """Drone i's positions at every sample time (T, 3), leaving at ``d`` through ``via``."""
        mid = (start[i] + end[i]) / 2 if via is None else via
        first = float(np.linalg.norm(mid - start[i])) / speed
        second = float(np.linalg.norm(end[i] - mid)) / speed
        tau = np.clip(times - d, 0.0, None)
        f1 = np.clip(tau / max(first, 1e-9), 0.0, 1.0)[:, None]
        f2 = np.clip((tau - first) / max(second, 1e-9), 0.0, 1.0)[:, None]
        return np.where(tau[:, None] < first, start[i] + (mid - start[i]) * f1, mid + (end[i] - mid) * f2)

    # a pair that starts or ends closer than ``margin`` (drones placed by hand, a hover target) must only not
    # come closer than that
    i, j = np.triu_indices(D, 1)
    pair = np.full((D, D), float(margin))
    at = np.minimum(
        ellipsoid_distance(start[j] - start[i], radius, half_height),
        ellipsoid_distance(end[j] - end[i], radius, half_height),
    )
    pair[i, j] = pair[j, i] = np.minimum(margin, at)
    # a drone that begins nearer an obstacle than ``clearance`` (held there by the shield, with noise) must only
    # not come nearer than that
    if obstacles is not None:
        keep = np.minimum(clearance, obstacle_distance(start[:, :2], obstacles))
    rng = np.random.default_rng(0)
    orders = [list(range(D)), sorted(range(D), key=lambda i: -straight[i]), sorted(range(D), key=lambda i: straight[i])]
    orders += [list(rng.permutation(D)) for _ in range(tries)]
    for use_detours in (False, True):  # detours also lead around obstacles
        for order in orders:
            paths = np.zeros((D, len(times), 3))
            delay = np.full(D, np.nan)
            via = np.full((D, 3), np.nan)
            for n, k in enumerate(order):
                options: list[np.ndarray | None] = [None]
                if use_detours and straight[k] > 0:
                    options += _detours(start[k], end[k], bounds, obstacles, clearance)
                placed = False
                for w in options:
                    if obstacles is not None:  # the route itself must keep clear of the obstacles
                        route = path(k, 0.0, w)[:, :2]
                        if (obstacle_distance(route, obstacles) < keep[k] - 1e-9).any():
                            continue
                    for d in np.arange(0.0, max_delay + 1e-9, delay_step):
                        paths[k] = path(k, float(d), w)
                        if _clear(paths, k, order[:n], radius, half_height, pair):
                            delay[k], placed = d, True
                            if w is not None:
                                via[k] = w
                            break
                    if placed:
                        break
                if not placed:
                    break
            if np.isfinite(delay).all():
                return Transit(start, end, delay, speed, via)
    raise TransitBlocked(
        f"no conflict-free transit in {len(orders)} orders, with detours (drones on each other's lines or targets)"
    )


def separated_spawn(
    draw: Callable[[], tuple[np.ndarray, np.ndarray]],
    radius: float,
    half_height: float,
    margin: float = 1.3,
    tries: int = 200,
) -> tuple[np.ndarray, np.ndarray]:
    """A spawn draw (``draw()`` -> pursuer (P, 2), evader (E, 2)) whose drones are ``margin`` clear of each
    other: the task's spawn distribution, conditioned on a safe start (the first draw that is)."""
    for _ in range(tries):
        pos_p, pos_e = draw()
        xy = np.concatenate([pos_p, pos_e])
        flat = np.c_[xy, np.zeros(len(xy))]
        i, j = np.triu_indices(len(xy), 1)
        if (ellipsoid_distance(flat[i] - flat[j], radius, half_height) >= margin).all():
            return pos_p, pos_e
    raise TransitBlocked(f"no spawn draw with every drone {margin} ellipsoids apart in {tries} tries")
