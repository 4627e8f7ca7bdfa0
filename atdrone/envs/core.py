"""The batched AT-Drone pursuit simulator: B environments stepped as whole arrays.

Description
    Four pursuers (0.3 m/s) chase evaders (0.6 m/s) in a 3.6 m x 5 m arena with box
    and disc obstacles (SPEC sections 1-6). Evaders run the built-in escape policy of
    :mod:`atdrone.envs.evaders`. One step: pursuers turn and move -> evaders flee and
    move -> capture and collision -> reward -> observe; finished environments reset
    themselves at once.

Action Space
    (num_envs, num_p) floats, clipped to [-1, 1]: heading += a * pi/4, then the drone
    moves velocity_p * dt along its new heading (:mod:`atdrone.envs.kinematics`).

Observation Space
    (num_envs, num_p, obs_dim) float32, egocentric, ``OBS_LAYOUT_VERSION`` 1: the pure
    :func:`atdrone.envs.observation.observe` of the poses record :meth:`BatchedPursuit.poses`. Entities
    are blocks of 4 features ``[mask, distance / 5, sin(bearing), cos(bearing)]``,
    the bearing measured from the pursuer's own heading (counter-clockwise positive):
      - num_e evader blocks (evader index order); mask 0 and zeros when the evader is
        captured or farther than reception_range;
      - 1 block for the nearest obstacle or wall (mask always 1; signed distance);
      - num_p - 1 teammate blocks (the other pursuers in index order); mask 0 and
        zeros beyond reception_range.
    obs_dim = 4 * (num_e + num_p).

Rewards
    Shared by the team, the same value in every pursuer's column: capture per evader
    captured + approach * sum over evaders uncaptured at the start of the step of the
    reduction of their nearest-pursuer distance / approach_scale + collision if any
    collision happened + (optional) proximity band penalties per teammate pair.

Starting State
    Pursuer i at x = U(region.x) + x_step * i, y = U(region.y); evader j at
    x = b + x_step * j with one shared b = U(region.x), y = U(region.y); headings +y.
    With random_respawn false every draw takes the middle of its range.

Episode End
    Captured all evaders (success), a collision (pursuers < collision_distance apart
    or a pursuer < safe_radius from an obstacle or wall) when collision_ends_episode,
    or task_horizon steps (timeout). ``info`` reports how each environment ended, and
    who collided this step: collided (B, P) the pursuers in a collision, hit_pairs
    (B, pairs) the pursuer pairs closer than collision_distance (in ``pairs`` order),
    hit_obstacle (B, P) the index into ``geometry.names`` of the obstacle or wall a
    pursuer hit (-1: none).

Team events
    With an :class:`~atdrone.envs.events.EventPlan` (``events``) each episode draws a
    schedule of swaps, drops and joins from its key, held in the state and applied in
    the step as whole-batch masks; ``info["team_changed"]`` (B, P) names the slots whose
    drone changed, so the policies forget exactly those drones (:mod:`atdrone.envs.events`).

Randomness
    Every episode has a number (its place in the core's sequence of episodes: 0, 1, ...
    from a reset with a seed, continuing through auto-resets in row order) and a key,
    a hash of the seed and that number (``state.key``). Its spawn and its evaders'
    wandering are counter-based draws from its key and step (:mod:`atdrone.envs.streams`),
    so an episode plays the same whichever row it runs in and whatever the other rows do.

Arguments
    task: a TaskConfig, task name or path; num_envs; seed of the episode keys (None:
    fresh entropy).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

import atdrone.envs.events as ev_
from atdrone.config import TaskConfig, load_task
from atdrone.envs.evaders import EscapeParams
from atdrone.envs.geometry import Geometry
from atdrone.envs.kinematics import advance, turn
from atdrone.envs.observation import (
    DIST_SCALE as DIST_SCALE,
)
from atdrone.envs.observation import (
    ENTITY_FEATURES as ENTITY_FEATURES,
)
from atdrone.envs.observation import (
    OBS_BOUND as OBS_BOUND,
)
from atdrone.envs.observation import (
    OBS_LAYOUT_VERSION as OBS_LAYOUT_VERSION,
)
from atdrone.envs.observation import (
    Arena,
    Poses,
    obs_dim,
    observe,
)
from atdrone.envs.rules import evader_distances, evader_step, judge, pursuer_pairs, spawn
from atdrone.envs.streams import SPAWN_DRAWS, RowStream, episode_keys, fold, root_key

RUNNING, CAPTURED, COLLISION, TIMEOUT = 0, 1, 2, 3
DONE_REASONS = ("running", "captured", "collision", "timeout")


@dataclass
class PursuitState:
    """Mutable state of B environments; agents are pursuers first, then evaders.

    pos (B, N, 2) metres; heading (B, N) radians; captured (B, E); t (B,) steps;
    ep_return (B,); ep_collided (B,); wander_heading (B, E); wander_left (B, E) steps;
    prev_dist (B, E) nearest-pursuer distance of each evader after the last step;
    episode (B,) the number of each row's episode and key (B,) uint64 its random key;
    present (B, P) which pursuer slots hold a drone; ev_kind, ev_step, ev_slot, ev_pick
    (B, K) each episode's team events (:mod:`atdrone.envs.events`; K = 0 without).
    """

    pos: np.ndarray
    heading: np.ndarray
    captured: np.ndarray
    t: np.ndarray
    ep_return: np.ndarray
    ep_collided: np.ndarray
    wander_heading: np.ndarray
    wander_left: np.ndarray
    prev_dist: np.ndarray = field(default_factory=lambda: np.zeros(0))
    episode: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    key: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.uint64))
    present: np.ndarray = field(default_factory=lambda: np.ones((0, 0), dtype=bool))
    ev_kind: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int8))
    ev_step: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int64))
    ev_slot: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=np.int64))
    ev_pick: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def copy(self) -> PursuitState:
        return PursuitState(**{k: v.copy() for k, v in self.__dict__.items()})


class BatchedPursuit:
    """B AT-Drone pursuit environments stepped together (see the module docstring)."""

    def __init__(
        self, task: TaskConfig | str, num_envs: int = 1, seed: int | None = None, events: ev_.EventPlan | None = None
    ) -> None:
        if not isinstance(num_envs, int | np.integer) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        self.cfg = load_task(task)
        self.num_envs = int(num_envs)
        self.num_p = self.cfg.players.num_p
        self.num_e = self.cfg.players.num_e
        self.obs_dim = obs_dim(self.num_p, self.num_e)
        self.arena = Arena.from_config(self.cfg)
        self.geometry: Geometry = self.arena.geometry
        self.escape = EscapeParams()
        self.root = root_key(seed)  # the episode keys' root
        self.next_episode = 0  # the number of the next episode a reset or an auto-reset starts
        self.pairs = pursuer_pairs(self.num_p).copy()  # (pairs, 2): the pursuer pairs of info["hit_pairs"]
        self.events = events if events is not None and len(events) else None  # the team events of every episode
        self._parking_seen = not ev_.parking_unseen(self.num_p, self.cfg.players.reception_range)
        self.state = self._fresh_state(np.arange(self.num_envs))  # what reset() starts
        self._obs: np.ndarray | None = None
        # the whole batch just before the last auto-reset (to show how episodes ended)
        self.final_state: PursuitState | None = None

    # ------------------------------------------------------------------ state
    def _fresh_state(self, episodes: np.ndarray) -> PursuitState:
        """The start of episodes numbered ``episodes`` (n,): spawn and wander clocks from their keys."""
        n = len(episodes)
        keys = episode_keys(self.root, episodes)
        draws = RowStream(fold(keys, SPAWN_DRAWS))
        pos, heading = spawn(self.cfg, draws, n)
        e = self.num_e
        lo, hi = self.escape.wander_steps
        state = PursuitState(
            pos=pos,
            heading=heading,
            captured=np.zeros((n, e), dtype=bool),
            t=np.zeros(n, dtype=np.int64),
            ep_return=np.zeros(n),
            ep_collided=np.zeros(n, dtype=bool),
            wander_heading=heading[:, self.num_p :].copy(),
            wander_left=draws.integers(lo, hi + 1, size=(n, e)),
            episode=np.asarray(episodes, dtype=np.int64),
            key=keys,
            present=np.ones((n, self.num_p), dtype=bool),
            **ev_.draw_schedule(self.events, keys),
        )
        if self.events is not None:  # every slot eligible until a Match says which are the learners'
            state.ev_slot = ev_.bind_slots(self.events, state.ev_pick, np.zeros((n, self.num_p), dtype=bool))
        state.prev_dist = self._evader_distances(state.pos)
        return state

    def _take(self, n: int) -> np.ndarray:
        """The numbers of the next n episodes."""
        episodes = np.arange(self.next_episode, self.next_episode + n)
        self.next_episode += n
        return episodes

    def step_keys(self) -> np.ndarray:
        """(B,) keys of each row's current step: its episode key folded with the step number."""
        return fold(self.state.key, self.state.t)

    def _evader_distances(self, pos: np.ndarray) -> np.ndarray:
        """Nearest-pursuer distance of each evader, (B, E)."""
        return evader_distances(pos, self.num_p)

    @property
    def pursuer_pos(self) -> np.ndarray:
        return self.state.pos[:, : self.num_p]

    @property
    def evader_pos(self) -> np.ndarray:
        return self.state.pos[:, self.num_p :]

    def reset(self, seed: int | None = None, episodes: np.ndarray | None = None) -> np.ndarray:
        """Reset every environment to the next episodes; with ``seed``, reseed and start from episode 0.

        ``episodes`` (B,): play these episode numbers instead (later auto-resets go on
        after the highest).
        """
        if seed is not None:
            self.root, self.next_episode = root_key(seed), 0
        if episodes is None:
            episodes = self._take(self.num_envs)
        else:
            episodes = np.asarray(episodes, dtype=np.int64)
            if episodes.shape != (self.num_envs,):
                raise ValueError(f"episodes must have shape {(self.num_envs,)}, got {episodes.shape}")
            self.next_episode = int(episodes.max()) + 1
        self.state = self._fresh_state(episodes)
        self._obs = self.observe()
        return self._obs

    def keep(self, rows: np.ndarray) -> None:
        """Drop every environment but ``rows`` (indices, in the order kept): the batch shrinks to them."""
        rows = np.asarray(rows, dtype=np.intp)
        self.state = PursuitState(**{k: v[rows] for k, v in self.state.__dict__.items()})
        self.num_envs = len(rows)
        if self._obs is not None:
            self._obs = self._obs[rows]
        self.final_state = None

    # ------------------------------------------------------------ observation
    def poses(self, state: PursuitState | None = None) -> Poses:
        """The poses record of ``state`` (default: current): views of its arrays, no copy."""
        s = self.state if state is None else state
        return Poses(pos=s.pos, heading=s.heading, captured=s.captured, arena=self.arena)

    def observe(
        self, state: PursuitState | None = None, obstacles: tuple[np.ndarray, np.ndarray] | None = None
    ) -> np.ndarray:
        """Observations (B, num_p, obs_dim) float32 of ``state`` (default: current): :func:`observe` of its poses.

        ``obstacles``: the distance and normal of each pursuer's nearest obstacle, when already known.
        A landed drone (not ``present``) sees nothing and no one sees it.
        """
        obs = observe(self.poses(state), obstacles)
        if self.events is not None:
            present = (self.state if state is None else state).present
            if not present.all():
                ev_.hide_absent(obs, present, self.num_e, blocks=self._parking_seen)
        return obs

    def bind_events(self, rows: np.ndarray, learner: np.ndarray) -> None:
        """Choose the slots of the team events of the episodes in ``rows`` whose learners fill ``learner``
        (len(rows), P) bool (a Match calls this once it has drawn their teams)."""
        if self.events is not None and len(rows):
            self.state.ev_slot[rows] = ev_.bind_slots(self.events, self.state.ev_pick[rows], learner)

    # ------------------------------------------------------------------- step
    def step(self, actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Advance every environment one step; see the module docstring."""
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        actions = np.asarray(actions, dtype=np.float64)
        if actions.shape != (self.num_envs, self.num_p):
            raise ValueError(f"actions must have shape {(self.num_envs, self.num_p)}, got {actions.shape}")
        cfg, s, P = self.cfg, self.state, self.num_p
        task, rw = cfg.task, cfg.task.reward

        # Pursuers: turn at most 45 degrees, then move at constant speed.
        head_p = turn(s.heading[:, :P], actions)
        pos_p = advance(s.pos[:, :P], head_p, self.arena.step, self.geometry.width, self.geometry.height)
        absent = self.events is not None and not s.present.all()
        if absent:  # landed drones wait at their parking spots, outside the arena
            pos_p = np.where(s.present[..., None], pos_p, ev_.parked(P))

        # Evaders: escape policy, wandering when calm.
        ev = evader_step(
            s.pos[:, P:],
            s.heading[:, P:],
            pos_p,
            s.captured,
            s.wander_heading,
            s.wander_left,
            self.cfg,
            self.escape,
            RowStream(self.step_keys()),
            self.geometry,
        )
        active = ~s.captured
        pos = np.concatenate([pos_p, ev.pos], 1)
        heading = np.concatenate([head_p, ev.heading], 1)
        wander_heading, wander_left = ev.wander_heading, ev.wander_left

        # Capture and collision.
        judged = judge(pos, s.captured, self.cfg, self.geometry)
        if absent:
            judged = ev_.absent_judgement(judged, s.present, self.pairs)
        newly, captured, dist_pe = judged.captured_now, judged.captured, judged.evader_distance
        pair_d, pair_hit, hit_obstacle, collided = (
            judged.pair_distance,
            judged.hit_pairs,
            judged.hit_obstacle,
            judged.collided,
        )
        p_obst = judged.obstacles
        any_collision = collided.any(-1)

        # Shared reward.
        approach = ((s.prev_dist - dist_pe) * active).sum(-1) / rw.approach_scale
        reward = rw.capture * newly.sum(-1) + rw.approach * approach + rw.collision * any_collision
        if rw.proximity.enabled:
            for lo_b, hi_b, pen in rw.proximity.bands:
                reward = reward + pen * ((pair_d >= lo_b) & (pair_d < hi_b)).sum(-1)

        t = s.t + 1
        ep_return = s.ep_return + reward
        ep_collided = s.ep_collided | any_collision
        success = captured.all(-1)
        reason = np.full(self.num_envs, RUNNING, dtype=np.int8)
        reason[t >= task.task_horizon] = TIMEOUT
        reason[success] = CAPTURED
        if task.collision_ends_episode:
            reason[any_collision] = COLLISION
        done = reason != RUNNING

        self.state = PursuitState(
            pos=pos,
            heading=heading,
            captured=captured,
            t=t,
            ep_return=ep_return,
            ep_collided=ep_collided,
            wander_heading=wander_heading,
            wander_left=wander_left,
            prev_dist=np.where(captured, 0.0, dist_pe),
            episode=s.episode.copy(),
            key=s.key.copy(),
            present=s.present,
            ev_kind=s.ev_kind,
            ev_step=s.ev_step,
            ev_slot=s.ev_slot,
            ev_pick=s.ev_pick,
        )
        change = ev_.happen(self.state, ~done, self.cfg, self._evader_distances) if self.events else None
        if change is not None and change.joined.any():  # a joined drone's nearest obstacle is worked out anew
            p_obst = ev_.refresh_obstacles(p_obst, change.joined, self.state.pos[:, :P], self.geometry)
        obs = self.observe(obstacles=p_obst)
        info: dict[str, Any] = {
            "done_reason": reason,
            "episode_length": t.copy(),
            "episode_return": ep_return.copy(),
            "episode_collided": ep_collided.copy(),
            "episode_captured": captured.sum(-1),
            "collided": collided,
            "hit_pairs": pair_hit,
            "hit_obstacle": hit_obstacle,
            "captured_now": newly,
            "final_obs": obs.copy(),
        }
        if self.events is not None:  # (B, P) the slots whose drone was swapped, dropped or joined this step
            info["team_changed"] = change.changed if change is not None else np.zeros((self.num_envs, P), dtype=bool)
        if done.any():
            self.final_state = self.state.copy()
            obs[done] = self.observe(self._reset_envs(np.flatnonzero(done)))
        self._obs = obs
        rewards = np.repeat(reward[:, None], P, axis=1).astype(np.float32)
        return obs, rewards, done, info

    def _reset_envs(self, idx: np.ndarray) -> PursuitState:
        """Start the next episodes in rows ``idx``; returns their fresh state (the rows in ``idx`` order)."""
        fresh = self._fresh_state(self._take(len(idx)))
        for k, v in fresh.__dict__.items():
            getattr(self.state, k)[idx] = v
        return fresh
