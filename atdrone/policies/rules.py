"""Rule-based teammates of the unseen zoo (SPEC section 8): greedy and VICSEK drones.

Both read a poses record (``batch.poses``: own pose, evaders, teammates, and the
arena's obstacles), as a motion-capture frame gives it, and obey the same 45-degree
turn limit as every pursuer: they choose a desired heading and
:func:`~atdrone.envs.kinematics.turn_towards` bounds the turn. :func:`chase_nearest`,
the demo's default, reads the observation alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from atdrone.envs.geometry import pick_nearest, signed_distances
from atdrone.envs.kinematics import MAX_TURN, turn_towards, wrap_angle
from atdrone.envs.observation import DIST_SCALE, ENTITY_FEATURES
from atdrone.envs.streams import fold, unit
from atdrone.policies.base import DroneBatch, StatelessPolicy

NOISE_DRAW = 7  # the counter a noisy VICSEK drone folds into its key (a neural drone's draws use 0 and 1)


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
    def of(cls, batch: DroneBatch, who: str = "a rule-based policy") -> Scene:
        """The scene of every drone of ``batch``, from ``batch.poses`` (ValueError without)."""
        s = batch.need_poses(who)
        P = s.arena.num_p
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
        od, on = signed_distances(pos, s.arena.geometry)
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
        sc = Scene.of(batch, self.name)
        chase = turn_towards(sc.heading, sc.target_heading())
        rows = np.arange(len(batch))
        mate_dist = sc.mate_dist
        if self.lookahead:
            step = batch.need_poses(self.name).arena.step * self.lookahead
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
        bearing = wrap_angle(threat_dir - heading)
        ahead = np.abs(bearing) < np.pi / 2
        chase_into = np.abs(wrap_angle(threat_dir - chase_heading)) < np.pi / 2
        away = -np.where(bearing >= 0, 1.0, -1.0) * self.avoid_turn / MAX_TURN
        # Teammates move: always veer off. Obstacles: veer off one ahead; hold course past
        # one beside or behind when the chase would turn back into it.
        hold = np.where(ahead, away, np.where(chase_into, 0.0, otherwise))
        return np.where(is_mate, away, hold)


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
        noise: float = 0.0,
    ) -> None:
        if not 0.0 <= noise <= 2 * np.pi:
            raise ValueError(f"vicsek noise must be an angle in [0, 2 pi] radians, got {noise}")
        self.chase, self.cohesion, self.alignment, self.noise = chase, cohesion, alignment, noise
        self.generator = np.random.default_rng(0)
        self.mate_range, self.mate_gain = mate_range, mate_gain
        self.obstacle_range, self.obstacle_gain = obstacle_range, obstacle_gain

    def act(self, batch: DroneBatch) -> np.ndarray:
        sc = Scene.of(batch, self.name)
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
        want = np.arctan2(v[:, 1], v[:, 0])
        if self.noise > 0.0:
            u = self.generator.random(len(want)) if batch.keys is None else unit(fold(batch.keys, NOISE_DRAW))
            want = want + self.noise * (u - 0.5)
        return turn_towards(sc.heading, want)


_TURNS = np.linspace(-1.0, 1.0, 17)  # candidate actions of chase_nearest's safety filter


def chase_nearest(obs: np.ndarray, num_e: int, clearance: float = 0.35) -> np.ndarray:
    """The default demo policy: steer each pursuer at its nearest visible evader.

    Read from the observation alone (layout of :mod:`atdrone.envs.observation`): the
    wanted turn is clip(bearing / 45 degrees, -1, 1) towards the nearest unmasked
    evader block, straight ahead when none is visible. A safety filter then picks,
    among 17 turns in [-1, 1], the one that best turns the nose away from every
    obstacle, wall or teammate nearer than ``clearance`` metres (ties: closest to the
    wanted turn), so demo episodes do not end at the first wall.
    obs (B, P, obs_dim) of the task's num_e evaders -> actions (B, P), for every
    pursuer or any P of them.
    """
    B, P, _ = obs.shape  # P: the drones steered, every pursuer or some of them
    E = num_e
    blocks = obs.reshape(B, P, -1, ENTITY_FEATURES)
    mask, dist = blocks[..., 0] > 0.5, blocks[..., 1] * DIST_SCALE
    bearing = np.arctan2(blocks[..., 2], blocks[..., 3])

    ev_dist = np.where(mask[..., :E], dist[..., :E], np.inf)
    nearest = ev_dist.argmin(-1)[..., None]
    seen = np.isfinite(np.take_along_axis(ev_dist, nearest, -1)[..., 0])
    aim = np.take_along_axis(bearing[..., :E], nearest, -1)[..., 0]
    want = np.where(seen, np.clip(aim / MAX_TURN, -1.0, 1.0), 0.0)

    # The obstacle block (slot E) and the teammate blocks: after turning by a, an entity at
    # bearing b sits at b - a * MAX_TURN; a near one should end up abeam or behind (cos <= 0).
    near = mask[..., E:] & (dist[..., E:] < clearance)  # (B, P, M)
    after = bearing[..., E:, None] - _TURNS * MAX_TURN  # (B, P, M, K)
    unsafe = (near[..., None] * np.maximum(np.cos(after), 0.0)).sum(-2)  # (B, P, K)
    cost = unsafe * 10.0 + np.abs(_TURNS - want[..., None])
    return _TURNS[cost.argmin(-1)] if near.any() else want
