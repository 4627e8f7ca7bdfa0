"""Team events as data: a drone swapped, dropped or joined mid-episode, batched over environments.

An :class:`EventPlan` lists the events every episode has (from a protocol document):
``swap`` (a backup takes over the slot's drone in the same pose), ``drop`` (the slot's
drone lands: it leaves the arena, can neither capture nor collide, and every observation
masks it as a teammate beyond range) and ``join`` (a dropped slot is filled again by a
drone spawning in the pursuers' spawn region). Each episode draws its own schedule from
its key (:func:`draw_schedule`): the step of every event and a uniform ``pick`` that
chooses its slot among the eligible ones (:func:`bind_slots`; a join takes the slot of
the drop before it). The simulator holds the schedule in its state (``ev_kind``,
``ev_step``, ``ev_slot``, ``ev_pick``, each (B, K)) and which slots hold a drone
(``present`` (B, P)), and applies the events that fall due in its step as whole-batch
masks (:func:`due`, :func:`apply`).

An event of step t happens at the end of the step that brings the episode to step t, so
the observation of step t already shows it and every action from step t on is the new
drone's. A landed drone is parked outside the arena (:func:`parked`), so it is beyond
every drone's reception range and no evader flees it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import cache
from typing import TYPE_CHECKING, Literal

import numpy as np

from atdrone.envs.geometry import Geometry, nearest_obstacle
from atdrone.envs.streams import EVENT_DRAWS, RowStream, fold

if TYPE_CHECKING:
    from atdrone.config import TaskConfig
    from atdrone.envs.core import PursuitState
    from atdrone.envs.rules import Judgement

NONE, SWAP, DROP, JOIN = 0, 1, 2, 3
EVENT_KINDS = ("none", "swap", "drop", "join")
SLOT_CHOICES = ("partners", "learners", "any")
PARK = -100.0  # a landed drone waits at (PARK - 10 slot, PARK): far beyond every reception range
JOIN_TRIES = 50


@dataclass(frozen=True)
class EventSpec:
    """One event of every episode.

    kind: "swap", "drop" or "join"; steps: (low, high) inclusive range of the step it
    happens at (for a join: of the steps after the event before it); slots: which slots
    it may hit ("partners" by default, "learners", "any"; a join refills the slot the
    event before it emptied).
    """

    kind: Literal["swap", "drop", "join"]
    steps: tuple[int, int]
    slots: Literal["partners", "learners", "any"] = "partners"

    @property
    def code(self) -> int:
        return EVENT_KINDS.index(self.kind)


@dataclass(frozen=True)
class EventPlan:
    """The events of every episode, in order (a join follows the drop whose slot it refills)."""

    events: tuple[EventSpec, ...]

    def __post_init__(self) -> None:
        for i, ev in enumerate(self.events):
            if ev.kind not in EVENT_KINDS[1:]:
                raise ValueError(f"events[{i}].kind must be one of swap, drop, join, got {ev.kind!r}")
            if ev.slots not in SLOT_CHOICES:
                raise ValueError(f"events[{i}].slots must be one of {', '.join(SLOT_CHOICES)}, got {ev.slots!r}")
            lo, hi = ev.steps
            if not 0 <= lo <= hi:
                raise ValueError(f"events[{i}].steps must be 0 <= low <= high, got {ev.steps}")
            if ev.kind == "join" and (i == 0 or self.events[i - 1].kind != "drop"):
                raise ValueError(f"events[{i}]: a join must follow a drop (it refills the dropped slot)")

    def __len__(self) -> int:
        return len(self.events)


def no_schedule(n: int) -> dict[str, np.ndarray]:
    """The schedule fields of n episodes without events (K = 0)."""
    return {
        "ev_kind": np.zeros((n, 0), np.int8),
        "ev_step": np.zeros((n, 0), np.int64),
        "ev_slot": np.zeros((n, 0), np.int64),
        "ev_pick": np.zeros((n, 0)),
    }


def draw_schedule(plan: EventPlan | None, keys: np.ndarray) -> dict[str, np.ndarray]:
    """The schedules (n, K) of episodes with keys ``keys`` (n,): kinds, steps and slot picks, from the keys alone.

    Slots are not chosen yet (-1): :func:`bind_slots` does, once it is known which slots learners fill.
    """
    n = len(keys)
    if plan is None or not len(plan):
        return no_schedule(n)
    K = len(plan)
    draws = RowStream(fold(keys, EVENT_DRAWS))
    pick = draws.random((n, K))  # first: the first event's slot and step are the same under every plan
    step = np.zeros((n, K), np.int64)
    for k, ev in enumerate(plan.events):  # over the plan's few events, each for every episode at once
        offset = step[:, k - 1] if ev.kind == "join" else 0
        step[:, k] = offset + draws.integers(ev.steps[0], ev.steps[1] + 1, size=(n,))
    return {
        "ev_kind": np.tile(np.array([ev.code for ev in plan.events], np.int8), (n, 1)),
        "ev_step": step,
        "ev_slot": np.full((n, K), -1, np.int64),
        "ev_pick": pick,
    }


def bind_slots(plan: EventPlan, pick: np.ndarray, learner: np.ndarray) -> np.ndarray:
    """Slots (n, K) of the events of episodes whose learners fill ``learner`` (n, P) bool; -1: none eligible.

    Event k hits the floor(pick * m)-th of its m eligible slots (in slot order); a join the slot of the drop
    before it. In a team without partner slots (self-play) each drone is the others' partner: "partners"
    events hit any slot.
    """
    n, P = learner.shape
    slots = np.full((n, len(plan)), -1, np.int64)
    anyone = not learner.any()  # no learner slot known (the core alone): every event may hit every slot
    for k, ev in enumerate(plan.events):
        if ev.kind == "join":
            slots[:, k] = slots[:, k - 1]
            continue
        if anyone and ev.slots != "learners":
            slots[:, k] = np.minimum((pick[:, k] * P).astype(np.int64), P - 1)
            continue
        partners = ~learner | ~(~learner).any(1, keepdims=True)  # no partner slot (self-play): any slot
        eligible = {"partners": partners, "learners": learner, "any": np.ones_like(learner)}[ev.slots]
        m = eligible.sum(1)
        nth = np.minimum((pick[:, k] * m).astype(np.int64), np.maximum(m - 1, 0))
        rank = np.cumsum(eligible, 1) - 1  # each eligible slot's place among them
        hit = eligible & (rank == nth[:, None])
        slots[:, k] = np.where(m > 0, hit.argmax(1), -1)
    return slots


def due(state_t: np.ndarray, ev_step: np.ndarray, ev_slot: np.ndarray, running: np.ndarray) -> np.ndarray:
    """(B, K) the events that happen now: their step is the episode's and the episode goes on."""
    return (ev_step == state_t[:, None]) & (ev_slot >= 0) & running[:, None]


@dataclass(frozen=True)
class TeamChange:
    """What the events of one step did, each (B, P) bool: swapped, dropped, joined; ``changed`` their union."""

    swapped: np.ndarray
    dropped: np.ndarray
    joined: np.ndarray

    @property
    def changed(self) -> np.ndarray:
        return self.swapped | self.dropped | self.joined


@cache
def parked(num_p: int) -> np.ndarray:
    """(P, 2) where each slot's landed drone waits: outside the arena, 10 m apart (read-only, shared)."""
    out = np.stack([PARK - 10.0 * np.arange(num_p), np.full(num_p, PARK)], -1)
    out.flags.writeable = False
    return out


def apply(
    fire: np.ndarray,
    kind: np.ndarray,
    slot: np.ndarray,
    present: np.ndarray,
    pos_p: np.ndarray,
    heading_p: np.ndarray,
    keys: np.ndarray,
    t: np.ndarray,
    cfg: TaskConfig,
) -> tuple[np.ndarray, TeamChange]:
    """Apply the events ``fire`` (n, K) of kinds and slots (n, K) to n rows: their new ``present`` (n, P);
    the pursuers' ``pos_p`` (n, P, 2) and ``heading_p`` (n, P) are changed in place (a drop parks its drone,
    a join spawns one).

    A swap or drop hits a slot that holds a drone, a join one that does not. A joining drone spawns as
    at an episode's start (x = U(region.x) + x_step * slot, y = U(region.y), heading +y), redrawn while it
    would start closer than collision_distance to a present pursuer; the draws come from the episode's
    key (``keys`` (n,)) and step ``t`` (n,).
    """
    P = present.shape[1]
    hit = fire[:, :, None] & (slot[:, :, None] == np.arange(P))  # (n, K, P)
    of = lambda code: (hit & (kind == code)[:, :, None]).any(1)
    change = TeamChange(swapped=of(SWAP) & present, dropped=of(DROP) & present, joined=of(JOIN) & ~present)
    now = (present & ~change.dropped) | change.joined
    if change.dropped.any():
        pos_p[:] = np.where(change.dropped[..., None], parked(P), pos_p)
    if change.joined.any():
        pos_p[:] = _spawn_joiners(pos_p, change.joined, now, keys, t, cfg)
        heading_p[:] = np.where(change.joined, np.pi / 2, heading_p)
    return now, change


def _spawn_joiners(
    pos_p: np.ndarray, joined: np.ndarray, present: np.ndarray, keys: np.ndarray, t: np.ndarray, cfg: TaskConfig
) -> np.ndarray:
    """Pursuer positions (n, P, 2) with the ``joined`` (n, P) slots spawned (see :func:`apply`)."""
    pl = cfg.players
    rp = pl.respawn_region.pursuer
    P = pos_p.shape[1]
    out = pos_p.copy()
    draws = RowStream(fold(fold(keys, EVENT_DRAWS + 1), t))
    todo = np.ones(len(out), dtype=bool)
    for _ in range(JOIN_TRIES):  # redraws, each for every row still too close at once
        g = draws if todo.all() else draws.rows(todo)
        m = int(todo.sum())
        x = g.uniform(rp.x[0], rp.x[1], size=(m, P)) + rp.x_step * np.arange(P)
        y = g.uniform(rp.y[0], rp.y[1], size=(m, P))
        if not pl.random_respawn:
            x = np.full((m, P), sum(rp.x) / 2) + rp.x_step * np.arange(P)
            y = np.full((m, P), sum(rp.y) / 2)
        sub = np.where(joined[todo][..., None], np.stack([x, y], -1), out[todo])
        out[todo] = sub
        d = np.hypot(*(sub[:, :, None] - sub[:, None, :]).transpose(3, 0, 1, 2))  # (m, P, P)
        near = (d < cfg.task.collision_distance) & ~np.eye(P, dtype=bool)
        near &= joined[todo][:, :, None] & present[todo][:, None, :]
        again = near.any((1, 2))
        if not again.any() or not pl.random_respawn:
            break
        todo[np.flatnonzero(todo)[~again]] = False
    return out


def happen(
    state: PursuitState, running: np.ndarray, cfg: TaskConfig, distances: Callable[[np.ndarray], np.ndarray]
) -> TeamChange | None:
    """Apply to ``state`` (in place, a step's new state) the events due now in the ``running`` (B,) episodes,
    worked out on their rows only; what they changed (each (B, P)), None when nothing was due. The approach
    reward of a changed team starts from its new distances (``distances``: positions (n, N, 2) ->
    nearest-pursuer distance of each evader (n, E))."""
    s = state
    fire_all = due(s.t, s.ev_step, s.ev_slot, running)
    rows = np.flatnonzero(fire_all.any(1))
    if not len(rows):
        return None
    fire = fire_all[rows]
    P = s.present.shape[1]
    pos_p, heading_p = s.pos[rows, :P], s.heading[rows, :P]
    now, change = apply(
        fire, s.ev_kind[rows], s.ev_slot[rows], s.present[rows], pos_p, heading_p, s.key[rows], s.t[rows], cfg
    )
    s.present = s.present.copy()  # the previous state may share it
    s.present[rows], s.pos[rows, :P], s.heading[rows, :P] = now, pos_p, heading_p
    moved = rows[(change.dropped | change.joined).any(1)]  # a swap moves no drone
    if len(moved):
        s.prev_dist[moved] = np.where(s.captured[moved], 0.0, distances(s.pos[moved]))
    full = np.zeros((3, *s.present.shape), dtype=bool)
    full[:, rows] = (change.swapped, change.dropped, change.joined)
    return TeamChange(*full)


def refresh_obstacles(
    obstacles: tuple[np.ndarray, np.ndarray], joined: np.ndarray, pos_p: np.ndarray, geometry: Geometry
) -> tuple[np.ndarray, np.ndarray]:
    """The nearest-obstacle distance (B, P) and normal (B, P, 2) of the pursuers at ``pos_p`` (B, P, 2), worked
    out anew in the rows where a drone ``joined`` (B, P)."""
    rows = np.flatnonzero(joined.any(1))
    dist, normal = obstacles[0].copy(), obstacles[1].copy()
    dist[rows], normal[rows] = nearest_obstacle(pos_p[rows], geometry)
    return dist, normal


@cache
def _mates(num_p: int) -> np.ndarray:
    """(P, P - 1) the other slots each pursuer sees, in its teammate blocks' order (read-only, shared)."""
    out = np.array([[j for j in range(num_p) if j != i] for i in range(num_p)], dtype=np.intp).reshape(num_p, -1)
    out.flags.writeable = False
    return out


def parking_unseen(num_p: int, reception_range: float) -> bool:
    """Whether every parking spot lies beyond ``reception_range`` of every point of the arena (x, y >= 0), so
    that the observation's range mask already hides a landed drone from its teammates."""
    spots = parked(num_p)
    return bool(np.hypot(np.minimum(spots[:, 0], 0.0), np.minimum(spots[:, 1], 0.0)).min() > reception_range)


def hide_absent(obs: np.ndarray, present: np.ndarray, num_e: int, blocks: bool = True) -> None:
    """Zero in ``obs`` (B, P, D), in place, every landed drone's (not ``present`` (B, P)) own row and, with
    ``blocks``, its teammate block in the others' rows: it is masked as a teammate beyond range is (without
    ``blocks`` when :func:`parking_unseen` says the range mask has done so already)."""
    B, P, _ = obs.shape
    obs[~present] = 0.0
    if blocks:
        mates = obs.reshape(B, P, -1, 4)[:, :, num_e + 1 :]  # (B, P, P - 1, 4) teammate blocks, a view
        mates[~present[:, _mates(P)]] = 0.0


def absent_judgement(judged: Judgement, present: np.ndarray, pairs: np.ndarray) -> Judgement:
    """``judged`` with the landed drones (not ``present`` (B, P)) in no collision: they are out of the arena."""
    hit_pairs = judged.hit_pairs & present[:, pairs[:, 0]] & present[:, pairs[:, 1]]
    return replace(
        judged,
        hit_pairs=hit_pairs,
        hit_obstacle=np.where(present, judged.hit_obstacle, -1),
        collided=judged.collided & present,
    )


def describe(kind: np.ndarray, step: np.ndarray, slot: np.ndarray) -> list[str]:
    """Each episode's schedule (rows of (K,) arrays) as text: "drop@57:s2+join@80:s2" ("" without events)."""
    names = np.array(EVENT_KINDS, dtype=object)
    rows = []
    for kr, sr, lr in zip(kind, step, slot, strict=True):  # one record per finished episode, not per step
        rows.append("+".join(f"{names[k]}@{s}:s{sl}" for k, s, sl in zip(kr, sr, lr, strict=True) if k))
    return rows
