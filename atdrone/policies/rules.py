"""Rule-based teammates of the unseen zoo (SPEC section 8): greedy and VICSEK drones.

Both read the simulator state of the drones they steer (own pose, evaders, teammates,
obstacles) and obey the same 45-degree turn limit as every pursuer: they choose a
desired heading and :func:`~atdrone.policies.base.turn_towards` bounds the turn.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from atdrone.envs.geometry import pick_nearest, signed_distances
from atdrone.policies.base import DroneBatch, StatelessPolicy, turn_towards


@dataclass(frozen=True)
class Scene:
    """What a rule-based drone sees of its environment, one row per drone (M rows)."""

    pos: np.ndarray  # (M, 2)
    heading: np.ndarray  # (M,)
    target: np.ndarray  # (M, 2) nearest uncaptured evader (own position when none)
    has_target: np.ndarray  # (M,)
    mate_vec: np.ndarray  # (M, P, 2) from the drone to each teammate (zeros for itself)
    mate_dist: np.ndarray  # (M, P), inf for itself
    mate_heading: np.ndarray  # (M, P)
    obst_dist: np.ndarray  # (M, K) signed distances to walls and obstacles
    obst_normal: np.ndarray  # (M, K, 2) pointing from the obstacle to the drone

    @classmethod
    def of(cls, batch: DroneBatch) -> Scene:
        core, s, P = batch.core, batch.core.state, batch.core.num_p
        pos, rows = batch.pos, np.arange(len(batch))
        ev = s.pos[batch.env, P:]
        ed = np.sqrt(((ev - pos[:, None]) ** 2).sum(-1))
        ed = np.where(s.captured[batch.env], np.inf, ed)
        k = ed.argmin(-1)
        has_target = np.isfinite(ed[rows, k])
        mates = s.pos[batch.env, :P]
        mate_vec = mates - pos[:, None]
        mate_dist = np.sqrt((mate_vec**2).sum(-1))
        mate_dist[rows, batch.slot] = np.inf
        od, on = signed_distances(pos, core.geometry)
        return cls(
            pos=pos,
            heading=batch.heading,
            target=np.where(has_target[:, None], ev[rows, k], pos),
            has_target=has_target,
            mate_vec=mate_vec,
            mate_dist=mate_dist,
            mate_heading=s.heading[batch.env, :P],
            obst_dist=od,
            obst_normal=on,
        )

    def target_heading(self) -> np.ndarray:
        """Heading to the target evader; own heading when every evader is captured."""
        v = self.target - self.pos
        return np.where(self.has_target, np.arctan2(v[:, 1], v[:, 0]), self.heading)


class GreedyPolicy(StatelessPolicy):
    """Heads for the nearest uncaptured evader; turns ~20 degrees away from a close teammate or obstacle.

    When the nearest teammate or obstacle (walls included) is within ``avoid_range``
    and either lies ahead (bearing within 90 degrees) or the chase would turn towards
    it, avoidance takes precedence: the drone turns ``avoid_turn`` away from a threat
    ahead, and holds its course past one beside or behind it. Teammates move, so a
    teammate counts as within range also when it would be after ``lookahead`` more
    steps of both drones on their current headings (0 turns this off); without it two
    drones closing head-on at 0.06 m/step meet before a 20-degree turn helps.
    """

    name = "greedy"

    def __init__(self, avoid_range: float = 0.3, avoid_turn_deg: float = 20.0, lookahead: int = 4) -> None:
        self.avoid_range = avoid_range
        self.avoid_turn = np.deg2rad(avoid_turn_deg)
        self.lookahead = lookahead

    def act(self, batch: DroneBatch) -> np.ndarray:
        sc = Scene.of(batch)
        chase = turn_towards(sc.heading, sc.target_heading())
        rows = np.arange(len(batch))
        mate_dist = sc.mate_dist
        if self.lookahead:
            step = batch.core.cfg.players.velocity_p * batch.core.cfg.dt * self.lookahead
            own = np.stack([np.cos(sc.heading), np.sin(sc.heading)], -1)[:, None]
            theirs = np.stack([np.cos(sc.mate_heading), np.sin(sc.mate_heading)], -1)
            ahead = sc.mate_vec + step * (theirs - own)
            mate_dist = np.minimum(mate_dist, np.where(np.isfinite(mate_dist), np.sqrt((ahead**2).sum(-1)), np.inf))
        m = mate_dist.argmin(-1)
        mate_d, mate_v = mate_dist[rows, m], sc.mate_vec[rows, m]
        obst_d, obst_n = pick_nearest(sc.obst_dist, sc.obst_normal)
        chase_heading = sc.target_heading()
        act = chase
        # The farther threat first, so the nearer one overrides it.
        mate_first = mate_d >= obst_d
        for first in (True, False):
            use_mate = mate_first == first
            d = np.where(use_mate, mate_d, obst_d)
            v = np.where(use_mate[:, None], mate_v, -obst_n)
            act = np.where(d < self.avoid_range, self._avoid(sc.heading, chase_heading, v, use_mate, act), act)
        return act

    def _avoid(
        self, heading: np.ndarray, chase_heading: np.ndarray, v: np.ndarray, is_mate: np.ndarray, otherwise: np.ndarray
    ) -> np.ndarray:
        threat_dir = np.arctan2(v[:, 1], v[:, 0])
        bearing = _wrap(threat_dir - heading)
        ahead = np.abs(bearing) < np.pi / 2
        chase_into = np.abs(_wrap(threat_dir - chase_heading)) < np.pi / 2
        away = -np.where(bearing >= 0, 1.0, -1.0) * self.avoid_turn / (np.pi / 4)
        # Teammates move: always veer off. Obstacles: veer off one ahead; hold course past
        # one beside or behind when the chase would turn back into it.
        hold = np.where(ahead, away, np.where(chase_into, 0.0, otherwise))
        return np.where(is_mate, away, hold)


def _wrap(angle: np.ndarray) -> np.ndarray:
    return np.arctan2(np.sin(angle), np.cos(angle))


class VicsekPolicy(StatelessPolicy):
    """Group chase after Janosov et al. 2017: the direction of a sum of steering terms.

    chase: unit vector to the nearest uncaptured evader; repulsion from teammates
    within ``mate_range`` and from walls/obstacles within ``obstacle_range``, growing
    linearly as the gap closes; long-range cohesion (towards the teammates' centroid)
    and alignment (with their mean heading).
    """

    name = "vicsek"

    def __init__(
        self,
        chase: float = 1.0,
        mate_range: float = 0.25,
        mate_gain: float = 4.0,
        obstacle_range: float = 0.2,
        obstacle_gain: float = 4.0,
        cohesion: float = 0.1,
        alignment: float = 0.1,
    ) -> None:
        self.chase, self.cohesion, self.alignment = chase, cohesion, alignment
        self.mate_range, self.mate_gain = mate_range, mate_gain
        self.obstacle_range, self.obstacle_gain = obstacle_range, obstacle_gain

    def act(self, batch: DroneBatch) -> np.ndarray:
        sc = Scene.of(batch)
        th = sc.target_heading()
        v = self.chase * np.stack([np.cos(th), np.sin(th)], -1)
        finite = np.isfinite(sc.mate_dist)
        safe_d = np.where(finite, np.maximum(sc.mate_dist, 1e-9), 1.0)
        close = finite & (sc.mate_dist < self.mate_range)
        push = np.where(close, (self.mate_range - sc.mate_dist) / self.mate_range, 0.0)
        v -= self.mate_gain * (push[..., None] * sc.mate_vec / safe_d[..., None]).sum(1)
        near = np.clip((self.obstacle_range - sc.obst_dist) / self.obstacle_range, 0.0, None)
        v += self.obstacle_gain * (near[..., None] * sc.obst_normal).sum(1)
        n_mates = finite.sum(-1, keepdims=True)
        centroid = np.where(finite[..., None], sc.mate_vec, 0.0).sum(1) / np.maximum(n_mates, 1)
        norm = np.maximum(np.sqrt((centroid**2).sum(-1, keepdims=True)), 1e-9)
        v += self.cohesion * centroid / norm
        mh = np.where(finite, sc.mate_heading, 0.0)
        align = np.stack([(np.cos(mh) * finite).sum(-1), (np.sin(mh) * finite).sum(-1)], -1)
        v += self.alignment * align / np.maximum(n_mates, 1)
        return turn_towards(sc.heading, np.arctan2(v[:, 1], v[:, 0]))
