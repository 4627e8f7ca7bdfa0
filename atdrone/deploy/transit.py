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

from atdrone.deploy.shield import ellipsoid_distance


class TransitBlocked(RuntimeError):
    """No conflict-free straight-line schedule exists for these starts and targets."""


@dataclass(frozen=True)
class Transit:
    """Straight lines from ``start`` (D, 3) to ``end`` (D, 3) at ``speed``, drone i leaving at ``delay[i]``."""

    start: np.ndarray
    end: np.ndarray
    delay: np.ndarray
    speed: float

    @property
    def duration(self) -> np.ndarray:
        return np.asarray(np.linalg.norm(self.end - self.start, axis=1) / self.speed)

    @property
    def total(self) -> float:
        return float((self.delay + self.duration).max(initial=0.0))

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Reference positions (D, 3) and velocities (D, 3) at ``t`` seconds after the transit began."""
        dur = self.duration
        frac = np.clip((t - self.delay) / np.maximum(dur, 1e-9), 0.0, 1.0)
        pos = self.start + (self.end - self.start) * frac[:, None]
        moving = (t >= self.delay) & (t < self.delay + dur) & (dur > 0)
        direction = (self.end - self.start) / np.maximum(dur, 1e-9)[:, None]
        return pos, np.where(moving[:, None], direction, 0.0)


def _clear(paths: np.ndarray, k: int, others: list[int], radius: float, half_height: float, margin: np.ndarray) -> bool:
    """Whether drone k's sampled path (T, 3) stays ``margin[k, o]`` (scaled) clear of each of ``others``' paths."""
    if not others:
        return True
    scaled = ellipsoid_distance(paths[others] - paths[k], radius, half_height)  # (len(others), T)
    return bool((scaled >= margin[k, others][:, None] - 1e-9).all())


def plan_transit(
    start: np.ndarray,
    end: np.ndarray,
    speed: float,
    radius: float,
    half_height: float,
    margin: float = 1.3,
    delay_step: float = 0.5,
    max_delay: float = 20.0,
    sample: float = 0.1,
    tries: int = 30,
) -> Transit:
    """Start delays for straight-line transits that keep every pair ``margin`` clear (see the module docstring)."""
    start = np.asarray(start, dtype=np.float64).reshape(-1, 3)
    end = np.asarray(end, dtype=np.float64).reshape(-1, 3)
    D = len(start)
    dur = np.linalg.norm(end - start, axis=1) / speed
    horizon = max_delay + float(dur.max(initial=0.0)) + sample
    times = np.arange(0.0, horizon, sample)
    delay = np.full(D, np.nan)

    def path(i: int, d: float) -> np.ndarray:
        frac = np.clip((times - d) / max(dur[i], 1e-9), 0.0, 1.0) if dur[i] > 0 else np.ones_like(times)
        return start[i] + (end[i] - start[i]) * frac[:, None]

    # a pair that starts or ends closer than ``margin`` (drones placed by hand, a hover target) must only not
    # come closer than that
    i, j = np.triu_indices(D, 1)
    pair = np.full((D, D), float(margin))
    at = np.minimum(
        ellipsoid_distance(start[j] - start[i], radius, half_height),
        ellipsoid_distance(end[j] - end[i], radius, half_height),
    )
    pair[i, j] = pair[j, i] = np.minimum(margin, at)
    rng = np.random.default_rng(0)
    orders = [list(range(D)), sorted(range(D), key=lambda i: -dur[i]), sorted(range(D), key=lambda i: dur[i])]
    orders += [list(rng.permutation(D)) for _ in range(tries)]
    for order in orders:
        paths = np.zeros((D, len(times), 3))
        delay = np.full(D, np.nan)
        for n, k in enumerate(order):
            for d in np.arange(0.0, max_delay + 1e-9, delay_step):
                paths[k] = path(k, float(d))
                if _clear(paths, k, order[:n], radius, half_height, pair):
                    delay[k] = d
                    break
            else:
                break
        if np.isfinite(delay).all():
            return Transit(start, end, delay, speed)
    raise TransitBlocked(
        f"no conflict-free straight-line transit in {len(orders)} orders (drones on each other's lines or targets)"
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
