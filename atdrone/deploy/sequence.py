"""Episode sequencing: spawn draws, takeoffs of landed drones, and the planned transits between episodes.

:class:`Sequencing` is the part of :class:`~atdrone.deploy.loop.Flight` that moves the
drones between episodes: a spawn draw whose drones are clear of each other, the
columns landed drones take off through cleared of drones in the air, and straight-line
transits scheduled by :func:`~atdrone.deploy.transit.plan_transit`, streamed through the
same shield as the episodes (the loop ticks, and the heartbeat is fed, while a transit is
planned in a worker thread).
"""

from __future__ import annotations

import concurrent.futures
import math
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import numpy as np

from atdrone.config import TaskConfig
from atdrone.deploy.bridge import Bridge
from atdrone.deploy.clock import Clock
from atdrone.deploy.config import DeployConfig
from atdrone.deploy.hooks import FlightHooks
from atdrone.deploy.landing import LANDED_CONFIRM
from atdrone.deploy.shield import (
    Obstacles,
    ShieldConfig,
    ellipsoid_distance,
    geofence,
    obstacle_distance,
    push_out_of_obstacles,
)
from atdrone.deploy.transit import MARGIN, Transit, TransitBlocked, plan_transit, separated_spawn
from atdrone.envs.geometry import Geometry
from atdrone.envs.rules import spawn

ARRIVED = 0.05  # m: a transit is over when every drone is this close to its target
SPAWN_DRAWS = 5  # spawn draws tried before a blocked transit ends the flight
COLUMN_CLEAR = 0.45  # m: no drone in the air this near (in x, y) a landed one that takes off


class Sequencing(FlightHooks):
    """Between episodes (see the module docstring); the flight provides the state and the ticks."""

    cfg: DeployConfig
    task: TaskConfig
    bridge: Bridge
    clock: Clock
    geometry: Geometry
    obstacles: Obstacles
    shield_cfg: ShieldConfig
    rng: np.random.Generator
    names: list[str]
    pursuers: list[str]
    evader_drones: list[str]
    state: dict[str, str]
    notes: dict[str, list[str]]
    hold_at: np.ndarray
    prev_setpoint: np.ndarray
    aborted: str
    _worker: concurrent.futures.ThreadPoolExecutor
    _drawn: tuple[np.ndarray, np.ndarray]

    if TYPE_CHECKING:  # the backups' part of the flight (no runtime stubs: they would shadow it)

        def _waiting_backups(self) -> list[str]: ...

        def _joining(self) -> list[str]: ...

        def _backups_up(self, rising: Sequence[str]) -> None: ...

        def _slot_targets(self, spawn_p: np.ndarray, spawn_e: np.ndarray, fallback: np.ndarray) -> np.ndarray: ...

        def _gone(self) -> np.ndarray: ...

    def _spawn(self) -> tuple[np.ndarray, np.ndarray]:
        P = len(self.pursuers)
        physical_e = bool(self.evader_drones)

        def draw() -> tuple[np.ndarray, np.ndarray]:
            pos, _ = spawn(self.task, self.rng, 1)
            return pos[0, :P], pos[0, P:]

        def draw_physical() -> tuple[np.ndarray, np.ndarray]:
            pos_p, pos_e = draw()
            self._drawn = (pos_p, pos_e)
            return pos_p, pos_e if physical_e else np.zeros((0, 2))

        separated_spawn(draw_physical, self.shield_cfg.drone_radius, self.shield_cfg.drone_half_height)
        return self._drawn

    def _go_to_spawn(self, spawn_p: np.ndarray, spawn_e: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """Take off landed drones, then fly every drone to its spawn position on a planned transit; the spawn
        flown to (another draw where no transit reaches the first), or None when the flight was aborted."""
        # a drone captured on the episode's last tick is still landing: down first, then up again with the rest
        down_by = self.clock.now() + self._landing_time() + LANDED_CONFIRM
        while any(self.state[n] == "landing" for n in self.names) and self.clock.now() < down_by:
            if not self._hold_tick():
                return None
        # landed drones take off again (a dropped one stays down), and so do backups still waiting for a slot
        gone = self._gone()
        waiting = self._waiting_backups()
        landed = [n for i, n in enumerate(self.names) if self.state[n] == "landed" and not gone[i]] + waiting
        rising = [n for n in self.names if self.state[n] == "taking_off"]  # a backup that took off in the episode
        if landed or rising:
            if landed and not self._clear_columns(landed):
                return None
            if landed:
                # a drone that needs arming disarms 3 s after it landed (the supervisor's landing timeout): arm again
                self.bridge.request_arming(landed)
                self.bridge.takeoff(landed, self.cfg.flight_height, self.cfg.takeoff_duration)
                self._set_state(landed, "taking_off")
            # the drones in the air keep their setpoint stream (held where they are): without it the firmware
            # levels them out after 0.5 s and stops their motors after 2 s
            end = self.clock.now() + self.cfg.takeoff_duration + 0.5
            while self.clock.now() < end:
                if not self._hold_tick():
                    return None
            joining = self._joining()
            up = [n for n in landed + rising if self.state[n] == "taking_off" and n not in joining]
            self._set_state(up, "flying")
            k = [self.names.index(n) for n in up]
            self.hold_at[k], self.prev_setpoint[k] = np.nan, np.nan  # taken over from the planner
        # a backup in the air takes its slot now (one that did not rise lands), in a tick of its own: its took_slot
        # note and its record's took_slot_t name that tick (between ticks the note would go on the next tick's row)
        if self._joining() and not self._hold_tick(first=lambda: self._backups_up(waiting)):
            return None
        if self.aborted:
            return None
        start = self._at_height()
        flying = self._airborne()
        lo_hi = self._fence()
        blocked: TransitBlocked | None = None
        for draw in range(SPAWN_DRAWS):
            if not self._hold_tick():  # every try ticks: the heartbeat and the shield's watch go on
                return None
            if draw:  # no transit to that draw: the task's spawn distribution, conditioned on a reachable one
                spawn_p, spawn_e = self._spawn()
                self.notes.setdefault("", []).append("spawn_redrawn")
            targets = self._slot_targets(spawn_p, spawn_e, start[:, :2])
            end = np.c_[targets, np.full(len(targets), self.cfg.flight_height)]
            # the task's spawn regions reach into the fence margin: a target the shield would clip is never reached
            end[:, :2], _ = push_out_of_obstacles(
                np.clip(end[:, :2], *lo_hi), self.obstacles, self.shield_cfg.obstacle_clearance
            )
            end[:, :2] = np.clip(end[:, :2], *lo_hi)
            end[~flying] = start[~flying]
            try:
                plan = self._plan(start, end)
                break
            except TransitBlocked as exc:
                blocked = exc
        else:
            self.aborted = f"transit blocked: {blocked} ({SPAWN_DRAWS} spawn draws)"
            return None
        if plan is None or not self._fly_transit(plan, end, flying):
            return None
        return spawn_p, spawn_e

    def _fence(self) -> tuple[np.ndarray, np.ndarray]:
        """The geofence's lower and upper (x, y) corners."""
        return geofence((self.geometry.width, self.geometry.height), self.shield_cfg.margin)

    def _at_height(self) -> np.ndarray:
        """Every drone's measured position (D, 3) at the flight height (the origin where it is not tracked)."""
        pos, _, _ = self.measured()
        start = np.where(np.isfinite(pos), pos, np.r_[0.0, 0.0, self.cfg.flight_height])
        start[:, 2] = self.cfg.flight_height
        return start

    def _plan(self, start: np.ndarray, end: np.ndarray) -> Transit | None:
        """A transit from ``start`` to ``end`` (raises :class:`TransitBlocked`), planned in the worker thread
        while the loop keeps ticking (and the heartbeat fed); None when the flight was aborted meanwhile."""
        planning = self._worker.submit(
            plan_transit,
            start,
            end,
            self.cfg.goto_speed,
            self.shield_cfg.drone_radius,
            self.shield_cfg.drone_half_height,
            bounds=self._fence(),
            obstacles=self.obstacles,
            clearance=self.shield_cfg.obstacle_clearance,
        )
        while not planning.done():
            if not self._hold_tick():
                return None
        return planning.result()

    def _holding_while(self, work: Callable[[], None]) -> None:
        """Run ``work`` (writing the log so far: 0.2-0.4 s) in the worker thread while the loop holds every
        streaming drone where it is, so the setpoint stream, the heartbeat and the shield's watch go on; after an
        abort it simply runs."""
        if self.aborted:
            work()
            return
        running = self._worker.submit(work)
        while not running.done():
            if not self._hold_tick():
                break
        running.result()

    def _fly_transit(self, plan: Transit, end: np.ndarray, moving: np.ndarray) -> bool:
        """Stream ``plan`` through the shield until the ``moving`` drones are at ``end``; False if aborted."""
        began = self.clock.now()
        deadline = began + plan.total + 5.0
        while self.clock.now() < deadline and not self.aborted:
            tick = self._begin_tick()
            ref, vel = plan.at(tick - began)
            pos, yaw, age = self.measured()
            decision = self._shield(pos, age, ref, vel)
            self._apply(decision)
            self._touchdown(pos)
            self._log_tick(tick, -1, pos, yaw, decision, {}, None)
            done = np.hypot(*(pos[:, :2] - end[:, :2]).T) < ARRIVED
            if tick - began >= plan.total and done[moving & ~self._gone()].all():  # a dropped drone went down
                return True
        if not self.aborted:
            self.aborted = "transit did not arrive in time"
        return False

    def _clear_columns(self, landed: list[str]) -> bool:
        """Fly the drones in the air off the columns the ``landed`` ones will take off through (a pursuer that
        caught an evader drone hovers beside where it landed, or above it) on a planned transit; False (and the
        flight ends) when that cannot be done."""
        start = self._at_height()
        flying = self._airborne()
        ground = np.array([self.names.index(n) for n in landed])
        r, h = self.shield_cfg.drone_radius, self.shield_cfg.drone_half_height
        lo, hi = self._fence()
        end = start.copy()
        for i in np.flatnonzero(flying):
            near = ground[np.hypot(*(start[ground, :2] - start[i, :2]).T) < COLUMN_CLEAR]
            if not len(near):
                continue
            away = start[i, :2] - start[near, :2].mean(0)
            heading = math.atan2(away[1], away[0]) if np.hypot(*away) > 1e-6 else 0.0
            for k in (0, 1, -1, 2, -2, 3, -3, 4, -4, 5, -5, 6, -6, 7, -7, 8):  # straight away first
                a = heading + k * np.pi / 8
                target = start[near, :2].mean(0) + 1.1 * COLUMN_CLEAR * np.array([math.cos(a), math.sin(a)])
                others = np.delete(end, i, axis=0)
                clear = (
                    (target >= lo).all()
                    and (target <= hi).all()
                    and (np.hypot(*(start[ground, :2] - target).T) >= COLUMN_CLEAR).all()
                    and obstacle_distance(target[None], self.obstacles)[0] >= self.shield_cfg.obstacle_clearance
                    and (ellipsoid_distance(others - np.r_[target, start[i, 2]], r, h) >= MARGIN).all()
                )
                if clear:
                    end[i, :2] = target
                    break
            else:
                self.aborted = f"no room to take {self.names[int(near[0])]} off: {self.names[i]} hovers over it"
                return False
        if np.array_equal(end, start):
            return True
        try:
            plan = self._plan(start, end)
        except TransitBlocked as exc:
            self.aborted = f"transit blocked clearing a takeoff: {exc}"
            return False
        return plan is not None and self._fly_transit(plan, end, flying)
