"""Partner drones dropped alone, and backup drones that take their slots.

A partner drone (never a learner, never an evader drone) whose battery runs low or whose
link is lost is **dropped** (:func:`~atdrone.deploy.reactions.drops`): it lands alone (a
lost one gets the land command every tick and is left to its firmware's watchdog), its
pursuer slot is empty, and the other drones fly the episode on. An empty slot is masked
as the simulator masks a drone its ``drop`` event landed (:mod:`atdrone.envs.events`):
the slot's position is parked outside the arena, every observation hides it as a
teammate beyond range, and it neither captures nor collides.

A backup named for that partner (config ``backups``) waits on the floor. Once no drone in
the air is above its column it takes off, flies to a **pose-safe spawn** for the slot
(:func:`backup_spawn`: inside the slot's part of the pursuers' spawn region, inside the
fence, clear of the obstacles and :data:`~atdrone.deploy.transit.MARGIN` separation
ellipsoids from every drone in the air), streamed through the shield like every other
setpoint, and takes the slot: the slot's partner policy acts through it from the next
tick, its memory of the slot forgotten. A backup that is itself dropped, fails its
takeoff or cannot take the slot within :data:`JOIN_TIMEOUT` of its takeoff lands (one its
firmware locked on the floor never takes off), and the slot stays empty. Between
episodes a waiting backup takes off with the drones that landed, and a backup in the air
takes its slot at once (the transit flies it to the slot's spawn).

:class:`Backups` is the part of :class:`~atdrone.deploy.loop.Flight` that does this; the
team changes are kept in :attr:`Backups.team_changes` for the flight log.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from atdrone.config import TaskConfig
from atdrone.deploy.bridge import Bridge
from atdrone.deploy.clock import Clock
from atdrone.deploy.config import DeployConfig
from atdrone.deploy.hooks import FlightHooks
from atdrone.deploy.landing import cut_by_firmware
from atdrone.deploy.links import LinkView
from atdrone.deploy.sequence import COLUMN_CLEAR
from atdrone.deploy.shield import HOLD_MARGIN, Obstacles, ShieldConfig, ellipsoid_distance, obstacle_distance
from atdrone.deploy.team import PolicyRunner, Team
from atdrone.deploy.transit import LEASH, MARGIN
from atdrone.envs.geometry import Geometry

JOIN_ARRIVED = 0.1  # m: a backup this close to its spawn takes the slot
JOIN_TIMEOUT = 40.0  # s (clock) from its takeoff: a backup that has not taken the slot by then lands
RISEN = 0.5  # of the flight height: a backup lower than this at the end of its takeoff failed it
GRID = 0.1  # m between the spawn points tried


def backup_spawn(
    slot: int,
    task: TaskConfig,
    others: np.ndarray,
    height: float,
    shield_cfg: ShieldConfig,
    fence: tuple[np.ndarray, np.ndarray],
    obstacles: Obstacles,
    margin: float = MARGIN,
) -> np.ndarray | None:
    """A spawn (2,) for a backup taking pursuer ``slot`` at ``height``, or None when there is none.

    The points of a :data:`GRID` over the slot's part of the pursuers' spawn region (x in
    region.x + x_step * slot, y in region.y, as a drone joining in the simulator spawns),
    inside ``fence``, ``obstacle_clearance`` from every obstacle and ``margin`` separation
    ellipsoids from every drone of ``others`` (K, 3); of those, the one farthest from
    them (scaled, up to twice ``margin``), then the one nearest the region's middle.
    """
    rp = task.players.respawn_region.pursuer
    lo, hi = fence
    x0, x1 = max(rp.x[0] + rp.x_step * slot, lo[0]), min(rp.x[1] + rp.x_step * slot, hi[0])
    y0, y1 = max(rp.y[0], lo[1]), min(rp.y[1], hi[1])
    if x0 > x1 or y0 > y1:
        return None
    gx, gy = np.meshgrid(np.arange(x0, x1 + 1e-9, GRID), np.arange(y0, y1 + 1e-9, GRID))
    points = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, height)]
    ok = obstacle_distance(points[:, :2], obstacles) >= shield_cfg.obstacle_clearance
    others = np.asarray(others, dtype=np.float64).reshape(-1, 3)
    others = others[np.isfinite(others).all(1)]
    r, h = shield_cfg.drone_radius, shield_cfg.drone_half_height
    apart = (
        ellipsoid_distance(others[None] - points[:, None], r, h).min(1) if len(others) else np.full(len(points), np.inf)
    )
    ok &= apart >= margin
    if not ok.any():
        return None
    middle = np.array([(x0 + x1) / 2, (y0 + y1) / 2])
    off = np.hypot(*(points[:, :2] - middle).T)
    order = np.lexsort((off, -np.minimum(apart, 2 * margin)))  # farthest first, then nearest the middle
    best = next(k for k in order if ok[k])
    return np.asarray(points[best, :2])


def backup_ground(task: TaskConfig, shield_cfg: ShieldConfig, count: int) -> np.ndarray:
    """Where the simulated fleet's ``count`` backups wait (count, 2): along the fence's +x side from its -y
    corner, :data:`COLUMN_CLEAR` apart, inside the fence and clear of the task's obstacles."""
    width, height = task.site.boundary.width, task.site.boundary.height
    lo, hi = shield_cfg.margin, (width - shield_cfg.margin, height - shield_cfg.margin)
    x = hi[0] - 0.05
    ys = np.arange(lo + 0.1, hi[1], COLUMN_CLEAR)
    points = np.c_[np.full(len(ys), x), ys]
    geometry = Geometry.from_config(task)
    obstacles = Obstacles(
        np.c_[geometry.box_center, geometry.box_half].reshape(-1, 4),
        np.c_[geometry.disc_center, geometry.disc_radius].reshape(-1, 3),
    )
    points = points[obstacle_distance(points, obstacles) >= shield_cfg.obstacle_clearance]
    return points[:count]


@dataclass
class Join:
    """A backup on its way to a dropped slot: ``phase`` waiting (on the floor), takeoff or transit, since when
    (clock), the spawn it flies to, and the team-change record it completes."""

    slot: int
    drone: str
    record: dict[str, Any]
    phase: str = "waiting"
    since: float = 0.0
    rose_at: float = math.inf  # clock time it took off
    target: np.ndarray | None = field(default=None, repr=False)


class Backups(FlightHooks):
    """Dropping partner drones and seating backups (see the module docstring); the flight provides the rest."""

    cfg: DeployConfig
    task: TaskConfig
    team: Team
    policy: PolicyRunner
    bridge: Bridge
    clock: Clock
    shield_cfg: ShieldConfig
    obstacles: Obstacles
    names: list[str]
    pursuers: list[str]
    evader_drones: list[str]
    partner_slots: np.ndarray
    state: dict[str, str]
    notes: dict[str, list[str]]
    hold_at: np.ndarray
    prev_setpoint: np.ndarray
    links: LinkView
    progress: Callable[[str], None]
    episode: int
    t0: float
    tick_t: float
    dt: float

    def _init_backups(self) -> None:
        P = len(self.pursuers)
        self.index = {n: i for i, n in enumerate(self.names)}
        self.slots = np.arange(P)  # the drone (index into names) flying each pursuer slot
        self.present = np.ones(P, dtype=bool)  # the slot holds a drone that acts
        self.evader_index = np.arange(P, P + len(self.evader_drones))
        self.spares = [b.name for b in self.cfg.backups]  # backups still on the floor, unused, in order
        self.retired: set[str] = set()  # drones dropped from the flight
        self.joins: list[Join] = []
        self.team_changes: list[dict[str, Any]] = []
        self.team_changed = False  # a slot emptied or filled since the episode last looked

    # ------------------------------------------------------------ dropping
    def _alone(self) -> np.ndarray:
        """(D,) the drones whose battery or lost link drops them alone: partner slots' drones and backups."""
        out = np.zeros(len(self.names), dtype=bool)
        out[self.slots[self.partner_slots]] = True
        out[[self.index[b.name] for b in self.cfg.backups]] = True
        out[[self.index[n] for n in self.retired]] = True
        return out

    def _drop(self, name: str, why: str) -> None:
        """Drop ``name`` alone for rule ``why`` (``battery``: it lands; ``link_lost``: it is lost): its slot is
        empty and a backup named for it, if any, is called."""
        if name in self.retired:
            return
        self.retired.add(name)
        self.notes.setdefault(name, []).append(f"dropped:{why}")
        if name in self.spares:  # a backup on the floor, not called yet: it will take no slot
            self.spares.remove(name)
            self.progress(f"[deploy] backup {name} dropped ({why}) on the floor: it will take no slot")
        if why == "battery":
            self._land([name])
        join = next((j for j in self.joins if j.drone == name), None)
        if join is not None:  # a backup on its way: it lands, the slot stays empty
            self._give_up(join, f"dropped ({why}) before it took the slot", land=False)
        P = len(self.pursuers)
        slot = next((s for s in range(P) if self.present[s] and self.names[self.slots[s]] == name), None)
        if slot is None:
            return
        self.present[slot] = False
        self.team_changed = True
        now = self.clock.now()
        record: dict[str, Any] = {
            "slot": slot,
            "drone": name,
            "why": why,
            "t": self.tick_t - self.t0,
            "episode": self.episode,
            "backup": "",
            "took_slot_t": None,
            "took_slot_episode": None,
            "memory_reset": False,
            "backup_end": "",
        }
        self.team_changes.append(record)
        backup = next((b.name for b in self.cfg.backups if b.name in self.spares and self._replaces(b.name, slot)), "")
        said = f"[deploy] {name} dropped ({why}): slot {slot} empty, the others fly on"
        if backup:
            self.spares.remove(backup)
            record["backup"] = backup
            self.joins.append(Join(slot, backup, record, since=now))
            said += f"; backup {backup} takes off for it"
        self.progress(said)

    def _replaces(self, backup: str, slot: int) -> bool:
        spec = next(b for b in self.cfg.backups if b.name == backup)
        return not spec.replaces or self.pursuers[slot] in spec.replaces

    def _give_up(self, join: Join, why: str, land: bool = True) -> None:
        """The backup of ``join`` will not take its slot: it lands (``land``), the slot stays empty."""
        self.joins.remove(join)
        self.retired.add(join.drone)
        join.record["backup_end"] = why
        if land:
            self._land([join.drone])
        self.notes.setdefault(join.drone, []).append("backup_gave_up")
        self.progress(f"[deploy] backup {join.drone} {why}: it lands, slot {join.slot} stays empty")

    # ------------------------------------------------------------ seating
    def _take_off_backup(self, join: Join) -> None:
        self.bridge.request_arming([join.drone])  # queued before the takeoff; an armed drone ignores it
        self.bridge.takeoff([join.drone], self.cfg.flight_height, self.cfg.takeoff_duration)
        self._set_state([join.drone], "taking_off")
        join.phase, join.since = "takeoff", self.clock.now()
        join.rose_at = join.since
        self.notes.setdefault(join.drone, []).append("backup_takeoff")

    def _risen(self, join: Join, pos: np.ndarray) -> bool:
        """A backup at the end of its takeoff: flying when it rose to :data:`RISEN` of the flight height (and
        True), else it failed its takeoff and lands."""
        k = self.index[join.drone]
        z = float(pos[k, 2])
        if not z >= RISEN * self.cfg.flight_height:
            self._give_up(join, f"failed its takeoff (at {z:.2f} m)")
            return False
        self._set_state([join.drone], "flying")
        self.hold_at[k], self.prev_setpoint[k] = np.nan, np.nan  # taken over from the planner, through the shield
        join.phase, join.since = "transit", self.clock.now()
        return True

    def _seat(self, join: Join) -> None:
        """The backup takes its slot: the slot's partner policy acts through it, its memory forgotten."""
        self.joins.remove(join)
        self.slots[join.slot] = self.index[join.drone]
        self.present[join.slot] = True
        self.team_changed = True
        self.policy.between_steps(self.team.forget, join.slot)  # after a late step still acting for the old drone
        join.record.update(took_slot_t=self.tick_t - self.t0, took_slot_episode=self.episode, memory_reset=True)
        self.notes.setdefault(join.drone, []).append(f"took_slot:{join.slot}")
        self.progress(f"[deploy] backup {join.drone} took slot {join.slot} (memory reset)")

    def _spawn_for(self, join: Join, pos: np.ndarray) -> np.ndarray | None:
        """A pose-safe spawn for the join's slot, clear of every other drone in the air and other joins' spawns."""
        k = self.index[join.drone]
        air = self._airborne()
        air[k] = False
        others = [pos[air]] + [
            np.r_[j.target, self.cfg.flight_height][None] for j in self.joins if j is not join and j.target is not None
        ]
        return backup_spawn(
            join.slot,
            self.task,
            np.concatenate(others),
            self.cfg.flight_height,
            self.shield_cfg,
            self._fence(),
            self.obstacles,
        )

    def _tend_backups(
        self, pos: np.ndarray, age: np.ndarray, ref: np.ndarray, setpoints: np.ndarray, vel: np.ndarray
    ) -> list[int]:
        """One episode tick of every backup on its way (before the shield): take off once its column is clear,
        fly to its spawn (its ``ref``, ``setpoints`` and ``vel`` rows), take the slot there. The slots taken."""
        now, seated = self.clock.now(), []
        air = self._airborne()
        h, r, hh = self.cfg.flight_height, self.shield_cfg.drone_radius, self.shield_cfg.drone_half_height
        for join in list(self.joins):
            k = self.index[join.drone]
            if now - join.rose_at > JOIN_TIMEOUT:
                self._give_up(join, f"did not take the slot within {JOIN_TIMEOUT:.0f} s of its takeoff")
                continue
            if join.phase == "waiting" and cut_by_firmware(self.bridge.supervisor().get(join.drone, 0)):
                self._give_up(join, "was locked by its firmware before its takeoff", land=False)
            elif join.phase == "waiting":
                others = air & (np.arange(len(self.names)) != k)
                near = np.hypot(*(pos[others, :2] - pos[k, :2]).T) < COLUMN_CLEAR
                heard = self.links.silence[k] <= self.shield_cfg.link_timeout
                if age[k] <= self.shield_cfg.stale_pose and heard and not near.any():
                    self._take_off_backup(join)
            elif join.phase == "takeoff":
                done = self.state[join.drone] == "taking_off" and now - join.since >= self.cfg.takeoff_duration + 0.5
                if done and self._risen(join, pos):
                    ref[k] = pos[k, :2]
            elif join.phase == "transit" and self.state[join.drone] == "flying" and np.isfinite(pos[k]).all():
                others = air & (np.arange(len(self.names)) != k) & np.isfinite(pos).all(1)
                taken = (
                    join.target is not None
                    and (ellipsoid_distance(pos[others] - np.r_[join.target, h], r, hh) < HOLD_MARGIN).any()
                )
                if join.target is None or taken:
                    join.target = self._spawn_for(join, pos)
                if join.target is None:  # nowhere clear yet: it holds where it is
                    continue
                if math.hypot(*(pos[k, :2] - join.target)) < JOIN_ARRIVED:
                    self._seat(join)
                    seated.append(join.slot)
                    continue
                ref[k], setpoints[k], vel[k] = self._toward(ref[k], pos[k], join.target)
        return seated

    def _toward(
        self, ref: np.ndarray, pos: np.ndarray, target: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The next reference (2,), setpoint (3,) and velocity (3,) of a straight line at ``goto_speed`` from
        ``ref`` (kept within a step of the drone) to ``target``."""
        gap = ref - pos[:2]
        if math.hypot(*gap) > LEASH:
            ref = pos[:2] + gap * (LEASH / math.hypot(*gap))
        to = target - ref
        dist = math.hypot(*to)
        step = min(dist, self.cfg.goto_speed * self.dt)
        unit = to / dist if dist > 1e-9 else np.zeros(2)
        new = ref + unit * step
        vel = np.r_[unit * (step / self.dt), 0.0]
        return new, np.r_[(ref + new) / 2, self.cfg.flight_height], vel

    # ------------------------------------------------------------ between episodes
    def _waiting_backups(self) -> list[str]:
        """Backups still on the floor for a slot: they take off with the drones that landed."""
        return [j.drone for j in self.joins if j.phase == "waiting"]

    def _joining(self) -> list[str]:
        """Backups on their way to a slot."""
        return [j.drone for j in self.joins]

    def _backups_up(self, rose: Sequence[str]) -> None:
        """Between episodes, after the takeoffs (``rose``: the waiting backups that took off with the landed drones):
        every backup of a join in the air takes its slot now (the transit flies it to the slot's spawn); one that
        failed its takeoff lands."""
        pos = self.measured()[0]
        for join in list(self.joins):
            if join.drone in rose and join.phase == "waiting" and self.state[join.drone] == "taking_off":
                join.phase, join.rose_at = "takeoff", self.clock.now()
            if join.phase == "takeoff" and self.state[join.drone] == "taking_off" and not self._risen(join, pos):
                continue
            if join.phase == "transit" and self.state[join.drone] == "flying":
                self._seat(join)

    def _slot_targets(self, spawn_p: np.ndarray, spawn_e: np.ndarray, fallback: np.ndarray) -> np.ndarray:
        """(D, 2) where each drone goes for a spawn draw: a slot's drone to its slot's spawn, an evader drone to
        its own, every other drone ``fallback`` (D, 2)."""
        out = np.array(fallback, dtype=np.float64)
        out[self.slots[self.present]] = spawn_p[self.present]
        if self.evader_drones:
            out[self.evader_index] = spawn_e[: len(self.evader_index)]
        return out

    def _idle(self, acting: np.ndarray) -> np.ndarray:
        """(D,) the drones neither a policy (the ``acting`` drones' indices), the evaders' escape step nor a
        backup's flight to its slot moves this tick."""
        idle = np.ones(len(self.names), dtype=bool)
        idle[acting] = False
        idle[self.evader_index] = False
        idle[[self.index[j.drone] for j in self.joins if j.phase == "transit"]] = False
        return idle

    def _gone(self) -> np.ndarray:
        """(D,) the drones dropped from the flight."""
        gone = np.zeros(len(self.names), dtype=bool)
        gone[[self.index[n] for n in self.retired]] = True
        return gone
