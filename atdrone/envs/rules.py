"""The rules of one pursuit step, on whole arrays of environments: where an episode starts
(:func:`spawn`), how the evaders move (:func:`evader_step`, the escape policy of
:mod:`atdrone.envs.evaders`) and who is caught or collides (:func:`judge`).

The simulator (:class:`atdrone.envs.core.BatchedPursuit`) and the deploy loop (virtual evaders,
setpoints for evader drones, the judgement of measured poses) both call these.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache

import numpy as np

from atdrone.config import TaskConfig
from atdrone.envs.evaders import EscapeParams, escape_directions, move_evaders
from atdrone.envs.geometry import Geometry, nearest_obstacles, offsets
from atdrone.envs.streams import RowStream


def spawn(
    cfg: TaskConfig, rng: np.random.Generator | RowStream, n: int, max_tries: int = 100
) -> tuple[np.ndarray, np.ndarray]:
    """Start positions (n, N, 2) and headings (n, N) of n environments.

    The pursuers' x ranges overlap (U(0.2, 1.2) + 0.6 i), so an environment whose
    pursuers would start closer than collision_distance redraws its pursuers (from a
    stream of its own when ``rng`` is a RowStream, so each row's spawn is its key's).
    """
    pl = cfg.players
    rp, re = pl.respawn_region.pursuer, pl.respawn_region.evader

    def draw(g: np.random.Generator | RowStream, lo_hi: tuple[float, float], shape: tuple[int, int]) -> np.ndarray:
        if pl.random_respawn:
            return g.uniform(lo_hi[0], lo_hi[1], size=shape)
        return np.full(shape, (lo_hi[0] + lo_hi[1]) / 2)

    def pursuers(g: np.random.Generator | RowStream, m: int) -> tuple[np.ndarray, np.ndarray]:
        return draw(g, rp.x, (m, pl.num_p)) + rp.x_step * np.arange(pl.num_p), draw(g, rp.y, (m, pl.num_p))

    px, py = pursuers(rng, n)
    i, j = pursuer_pairs(pl.num_p).T
    for _ in range(max_tries):
        close = (np.hypot(px[:, i] - px[:, j], py[:, i] - py[:, j]) < cfg.task.collision_distance).any(-1)
        if not close.any():
            break
        px[close], py[close] = pursuers(rng.rows(close) if isinstance(rng, RowStream) else rng, int(close.sum()))
    ex = draw(rng, re.x, (n, 1)) + re.x_step * np.arange(pl.num_e)
    ey = draw(rng, re.y, (n, pl.num_e))
    pos = np.stack([np.concatenate([px, ex], 1), np.concatenate([py, ey], 1)], -1)
    return pos, np.full((n, pl.num_p + pl.num_e), np.pi / 2)


@cache
def pursuer_pairs(num_p: int) -> np.ndarray:
    """(pairs, 2) the pursuer pairs i < j in ``np.triu_indices`` order (read-only, shared)."""
    pairs = np.stack(np.triu_indices(num_p, 1), 1)
    pairs.flags.writeable = False
    return pairs


@cache
def _incidence(num_p: int) -> np.ndarray:
    """(pairs, P) int64: 1 where a pursuer is one of a pair of :func:`pursuer_pairs` (read-only, shared)."""
    member = (pursuer_pairs(num_p)[:, :, None] == np.arange(num_p)).any(1).astype(np.int64)
    member.flags.writeable = False
    return member


def evader_distances(pos: np.ndarray, num_p: int) -> np.ndarray:
    """Nearest-pursuer distance of each evader, (B, E), from positions (B, N, 2) pursuers first.

    Worked out as (P, B * E) arrays, the evaders innermost (a short trailing pursuer axis is slow in numpy).
    """
    dx, dy = offsets(pos[:, num_p:], pos[:, :num_p])
    return np.sqrt(dx * dx + dy * dy).min(0).reshape(pos.shape[0], -1)


@dataclass(frozen=True)
class EvaderMove:
    """The evaders after one step: positions (B, E, 2), headings (B, E), wander state (B, E)."""

    pos: np.ndarray
    heading: np.ndarray
    wander_heading: np.ndarray
    wander_left: np.ndarray


def evader_step(
    pos_e: np.ndarray,
    head_e: np.ndarray,
    pos_p: np.ndarray,
    captured: np.ndarray,
    wander_heading: np.ndarray,
    wander_left: np.ndarray,
    cfg: TaskConfig,
    escape: EscapeParams,
    rng: np.random.Generator | RowStream,
    geometry: Geometry | None = None,
) -> EvaderMove:
    """One step of the escape policy (SPEC section 3) for evaders at ``pos_e`` fleeing pursuers at ``pos_p``.

    Calm evaders wander, holding a heading drawn from ``rng`` (a Generator, or one
    RowStream row per environment) for 10-15 steps; the
    others flee. Captured evaders stay put. The simulator and the deploy loop (virtual
    evaders, or setpoints for evader drones) both call this.
    """
    geo = Geometry.from_config(cfg) if geometry is None else geometry
    active = ~captured
    flee, calm = escape_directions(
        pos_e, head_e, pos_p, active, geo, cfg.players.reception_range, cfg.task.capture_range, escape
    )
    lo, hi = escape.wander_steps
    redraw = calm & (wander_left <= 0)
    veer = rng.uniform(-escape.wander_turn, escape.wander_turn, size=head_e.shape)
    span = rng.integers(lo, hi + 1, size=head_e.shape)
    new_wander = np.where(redraw, head_e + veer, wander_heading)
    left = np.where(calm, np.where(redraw, span, wander_left) - 1, 0)
    heading = np.where(active, np.where(calm, new_wander, flee), head_e)
    pos = move_evaders(pos_e, heading, cfg.players.velocity_e * cfg.dt, active, geo, escape)
    return EvaderMove(pos=pos, heading=heading, wander_heading=new_wander, wander_left=left)


@dataclass(frozen=True)
class Judgement:
    """Capture and collision at some positions (B environments; SPEC section 4).

    captured_now (B, E) caught by this judgement; captured (B, E) after it;
    evader_distance (B, E) nearest-pursuer distance; pair_distance and hit_pairs (B, pairs)
    in ``pairs`` order; hit_obstacle (B, P) index into ``geometry.names`` (-1 none);
    collided (B, P) pursuers in a collision; obstacles: the distance (B, P) and normal
    (B, P, 2) of each pursuer's nearest obstacle or wall (for the observation).
    """

    captured_now: np.ndarray
    captured: np.ndarray
    evader_distance: np.ndarray
    pair_distance: np.ndarray
    hit_pairs: np.ndarray
    hit_obstacle: np.ndarray
    collided: np.ndarray
    obstacles: tuple[np.ndarray, np.ndarray]


def judge(pos: np.ndarray, captured: np.ndarray, cfg: TaskConfig, geometry: Geometry) -> Judgement:
    """Which evaders are caught and which pursuers collide at positions ``pos`` (B, N, 2), pursuers first
    (pairs in :attr:`BatchedPursuit.pairs` order)."""
    P, task = cfg.players.num_p, cfg.task
    pairs = pursuer_pairs(P)
    dist_pe = evader_distances(pos, P)
    newly = ~captured & (dist_pe < task.capture_range)
    pos_p = pos[:, :P]
    i, j = pairs.T
    pair_d = np.sqrt((pos_p[:, i, 0] - pos_p[:, j, 0]) ** 2 + (pos_p[:, i, 1] - pos_p[:, j, 1]) ** 2)
    pair_hit = pair_d < task.collision_distance
    nearest, o_d, o_n = nearest_obstacles(pos_p, geometry)
    hit = o_d < task.safe_radius
    in_pair = (pair_hit.astype(np.int64) @ _incidence(P)) > 0
    return Judgement(
        captured_now=newly,
        captured=captured | newly,
        evader_distance=dist_pe,
        pair_distance=pair_d,
        hit_pairs=pair_hit,
        hit_obstacle=np.where(hit, nearest, -1),
        collided=hit | in_pair,
        obstacles=(o_d, o_n),
    )
