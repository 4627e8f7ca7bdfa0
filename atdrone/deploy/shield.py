"""The safety shield: pure functions from one tick's measurements and proposed setpoints to what may be sent.

Per drone the shield decides an :class:`Action`, the most severe rule that fires:

    TRACK < HOLD < LAND < STOP < LOST

- TRACK: send the (clamped) full-state setpoint. HOLD: send a setpoint at the drone's
  hold point, zero velocity: the point is latched at the measured position of the first
  held tick (``hold_at`` carries it from tick to tick) and, for a separation conflict,
  pushed apart from the other drone. LAND: the loop lands the drone. STOP: emergency
  stop (motors off). LOST: the link is gone; nothing can be sent (the firmware's
  watchdogs take over), the loop reports it.

Rules (``rule`` names as they appear in the flight log):

- ``geofence``: a setpoint outside the fence (the arena shrunk by ``margin``) is pulled
  inside, and its velocity feed-forward limited so that setpoint + 0.5 s x velocity stays
  inside (where Mellinger settles when a setpoint stops being renewed). ``outside``: a
  drone measured beyond the fence by more than ``outside_tolerance`` lands.
- ``speed``: a setpoint at most ``max_speed * dt`` from the previous setpoint; then
  ``step``: at most ``max_step`` (horizontal) from the measured position (applied last,
  so it always holds); ``altitude``: z within ``z_limits``; ``nan_setpoint``: a
  proposed setpoint with NaN holds.
- ``obstacle``: a setpoint closer than ``obstacle_clearance`` to an obstacle of the
  task (boxes and discs; the walls are the fence's) is pushed out to that clearance.
- ``separation`` (also while the onboard planner takes off or lands them): every drone
  is an ellipsoid of radius ``drone_radius`` and half-height ``drone_half_height``
  (Crazyswarm's 0.125 / 0.375 m); two physical drones conflict when their ellipsoids
  touch now or on their measured straight-line motion within ``lookahead`` seconds (1
  s: the tick, the radio and the stopping time), or when their proposed setpoints, or
  their positions, carried along the velocity feed-forward for ``lookahead`` seconds,
  converge until they touch; a 10 % margin leaves room to brake; both hold, pushed
  apart to 1.2 ellipsoids. A drone that holds is checked at its hold point with no
  feed-forward, not along its proposed setpoint: were the host to pause, every drone
  flies on to what it was sent last, and those targets are kept apart. A drone without
  a valid pose (unknown or stale) or with a lost link is an obstacle at its last valid
  pose, its ellipsoid grown by ``grow``, how far it may have flown since.
- ``stale_pose``: a drone without a fresh pose for ``stale_pose`` seconds, or with NaN
  in its pose, lands. ``all_stale``: every drone stale (a landed drone with a fresh
  pose shows the system alive) -> all land; ``mocap_lost``: the freshest pose older than
  ``stop_after`` -> all STOP.
- ``policy_stall``: the policy has been late for ``policy_stall`` s -> all land.
- ``link_lost``: no packet from a drone for ``link_timeout`` (host pauses excluded:
  :mod:`atdrone.deploy.links`) -> that drone is LOST (the loop sends it the land command
  every tick) and every other drone lands, unless the lost drone is one the flight drops
  ``alone`` (a partner drone: the others fly on). ``links_silent``: every link silent together
  (the ground station stalled, not N radios) -> every drone holds; still silent
  ``link_stall`` s later -> all land; nobody is marked lost. ``locked``: a drone's supervisor reports it locked (its
  emergency stop fired) -> it is STOPPED and every other drone lands.
- ``estimate_off``: a drone's onboard state estimate more than ``estimate_tolerance`` from its
  motion-capture pose for ``estimate_hold`` s (the second opinion: its poses no longer reach
  its estimator, or the estimator diverged; it flies on a belief) -> that drone lands. The flight judges only
  estimates of drones whose link is heard, and counts the time from its last resume after a host pause.
- ``battery``: below ``min_battery`` -> that drone lands.
- ``signal``: SIGINT/SIGTERM -> all land.

Virtual drones (``physical`` False, e.g. simulated evaders) are ignored by the fence,
separation, obstacle and pose rules. Inputs are never modified.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from atdrone.config import _check, _non_negative, _positive

FF_REACH = 0.5  # s: Mellinger's kd_xy / kp_xy (0.2 / 0.4): how far past a stale setpoint its feed-forward carries
HOLD_MARGIN = 1.1  # a pair holds when its ellipsoids would come this close (scaled): room to brake
PUSH_MARGIN = 1.2  # a held pair is pushed apart until their scaled distance reaches this


class Action(IntEnum):
    """What the loop does with a drone this tick; larger is more severe."""

    TRACK = 0
    HOLD = 1
    LAND = 2
    STOP = 3
    LOST = 4


def _limits(value: tuple[float, float]) -> str | None:
    lo, hi = value
    return None if 0 <= lo < hi else f"must be [low, high] with 0 <= low < high, got {list(value)!r}"


@dataclass(frozen=True)
class ShieldConfig:
    """The ``shield`` section of a deploy config (metres, seconds, volts)."""

    margin: float = field(default=0.25, metadata=_check(_non_negative))  # the fence: the arena shrunk by this
    outside_tolerance: float = field(default=0.15, metadata=_check(_non_negative))  # beyond the fence -> land
    drone_radius: float = field(default=0.125, metadata=_check(_positive))  # the separation ellipsoid, per drone
    drone_half_height: float = field(default=0.375, metadata=_check(_positive))
    lookahead: float = field(default=1.0, metadata=_check(_non_negative))  # s: tick + radio + stopping time
    obstacle_clearance: float = field(default=0.15, metadata=_check(_non_negative))  # m from an obstacle's edge
    max_speed: float = field(default=0.8, metadata=_check(_positive))  # m/s between consecutive setpoints
    max_step: float = field(default=0.3, metadata=_check(_positive))  # m from the measured position
    z_limits: tuple[float, float] = field(default=(0.2, 1.5), metadata=_check(_limits))
    stale_pose: float = field(default=0.3, metadata=_check(_positive))  # s without a fresh pose -> land
    stop_after: float = field(default=1.0, metadata=_check(_positive))  # s with every pose stale -> STOP
    policy_late: float = field(default=0.3, metadata=_check(_positive))  # s a policy step may take: then hold
    policy_stall: float = field(default=1.0, metadata=_check(_positive))  # s of a late policy: then land
    link_timeout: float = field(default=0.5, metadata=_check(_positive))  # s without a packet -> lost
    link_stall: float = field(default=0.5, metadata=_check(_positive))  # s of every link silent, held: then land
    min_battery: float = field(default=3.4, metadata=_check(_positive))  # V
    estimate_tolerance: float = field(default=0.25, metadata=_check(_positive))  # m onboard estimate vs pose
    estimate_hold: float = field(default=0.5, metadata=_check(_positive))  # s that far apart -> land


@dataclass(frozen=True)
class Obstacles:
    """The task's obstacles: boxes (K, 4) centre x, y and half sizes; discs (M, 3) centre x, y and radius."""

    boxes: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    discs: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


@dataclass(frozen=True)
class ShieldInput:
    """One tick of D drones (see the module docstring); NaN marks what is unknown."""

    dt: float
    arena: tuple[float, float]  # width, height
    names: tuple[str, ...]
    physical: np.ndarray  # (D,) bool
    pos: np.ndarray  # (D, 3) measured
    vel: np.ndarray  # (D, 3) measured velocity (NaN: 0)
    pose_age: np.ndarray  # (D,) s since the last fresh pose (inf: never)
    setpoint: np.ndarray  # (D, 3) proposed
    prev_setpoint: np.ndarray  # (D, 3) sent last tick
    battery: np.ndarray  # (D,) V
    link_age: np.ndarray  # (D,) s since the last packet
    policy_latency: float  # s the policy has been late (0: on time)
    stop_requested: bool
    setpoint_vel: np.ndarray | None = None  # (D, 3) proposed velocity feed-forward (None: zeros)
    hold_at: np.ndarray | None = None  # (D, 3) latched hold points of drones held last tick (NaN: not held)
    locked: np.ndarray | None = None  # (D,) bool: the supervisor reports the drone locked
    obstacles: Obstacles = field(default_factory=Obstacles)
    links_silent: float = 0.0  # s every link has been silent together (0: some link is heard)
    last_pos: np.ndarray | None = None  # (D, 3) each drone's last valid position (NaN: never)
    grow: np.ndarray | None = None  # (D,) m a drone without a valid pose may have flown since (0: it has one)
    estimate_off: np.ndarray | None = None  # (D,) s the onboard estimate has been off its pose (0: it agrees)
    alone: np.ndarray | None = None  # (D,) bool: a lost link lands this drone alone (the flight drops it)


@dataclass(frozen=True)
class ShieldEvent:
    """A rule that fired for a drone, and the action it asked for."""

    drone: str
    rule: str
    detail: str
    action: int = 0


@dataclass(frozen=True)
class ShieldDecision:
    """Per drone: the action, the setpoint and velocity to send (TRACK/HOLD; NaN otherwise), the events and
    the latched hold points to pass to the next tick (NaN where a drone is not held); the pairs held for
    separation."""

    action: np.ndarray  # (D,) int
    setpoint: np.ndarray  # (D, 3)
    events: tuple[ShieldEvent, ...]
    names: tuple[str, ...] = ()
    velocity: np.ndarray | None = None  # (D, 3)
    hold_at: np.ndarray | None = None  # (D, 3)
    pairs: np.ndarray | None = None  # (K, 2) drone indices of the pairs the separation rule held

    def lost(self) -> list[str]:
        """The drones whose link is lost."""
        return [n for n, a in zip(self.names, self.action, strict=True) if a == Action.LOST]


def geofence(arena: tuple[float, float], margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The fence rectangle: lower and upper (x, y) corners of the arena shrunk by ``margin``."""
    return np.array([margin, margin]), np.array([arena[0] - margin, arena[1] - margin])


def _scale(radius: float | np.ndarray, half_height: float | np.ndarray) -> np.ndarray:
    """The pair's semi-axes: twice the per-drone ones, (3,) or (..., 3) for per-pair arrays."""
    r, h = np.broadcast_arrays(np.asarray(radius, dtype=np.float64), np.asarray(half_height, dtype=np.float64))
    return np.stack([2 * r, 2 * r, 2 * h], -1)


def ellipsoid_distance(delta: np.ndarray, radius: float | np.ndarray, half_height: float | np.ndarray) -> np.ndarray:
    """Scaled distance (...) between two drones' centres ``delta`` (..., 3) apart: below 1 their ellipsoids
    (``radius``, ``half_height`` each; per pair when arrays) touch; the pair's Minkowski sum has twice the
    semi-axes."""
    scale = _scale(radius, half_height)
    return np.asarray(np.sqrt(((delta / scale) ** 2).sum(-1)))


def closest_approach(
    rel_pos: np.ndarray,
    rel_vel: np.ndarray,
    horizon: float,
    radius: float | np.ndarray,
    half_height: float | np.ndarray,
) -> np.ndarray:
    """The smallest scaled distance (...) over t in [0, horizon] of a pair moving ``rel_pos + rel_vel t``."""
    scale = _scale(radius, half_height)
    p, v = rel_pos / scale, rel_vel / scale
    vv = (v * v).sum(-1)
    t = np.clip(np.where(vv > 1e-12, -(p * v).sum(-1) / np.maximum(vv, 1e-12), 0.0), 0.0, horizon)
    closest = p + v * t[..., None]
    return np.asarray(np.sqrt((closest * closest).sum(-1)))


def obstacle_distance(points: np.ndarray, obstacles: Obstacles) -> np.ndarray:
    """Distance (N,) from each point (N, 2) to the nearest obstacle's edge (negative inside; inf: none)."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    best = np.full(len(points), np.inf)
    for cx, cy, hx, hy in obstacles.boxes:
        q = np.abs(points - np.array([cx, cy])) - np.array([hx, hy])
        outside = np.maximum(q, 0.0)
        best = np.minimum(best, np.hypot(outside[:, 0], outside[:, 1]) + np.minimum(q.max(1), 0.0))
    for cx, cy, radius in obstacles.discs:
        best = np.minimum(best, np.hypot(points[:, 0] - cx, points[:, 1] - cy) - radius)
    return best


def push_out_of_obstacles(points: np.ndarray, obstacles: Obstacles, clearance: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (D, 2) moved to ``clearance`` outside every obstacle they are closer to; and which moved (D,)."""
    out = np.array(points, dtype=np.float64)
    moved = np.zeros(len(out), dtype=bool)
    for _ in range(3):  # an obstacle's push may bring a point near another: a few rounds settle it
        for cx, cy, hx, hy in obstacles.boxes:
            r = out - np.array([cx, cy])
            q = np.abs(r) - np.array([hx, hy])
            outside = np.maximum(q, 0.0)
            dist = np.hypot(outside[:, 0], outside[:, 1]) + np.minimum(q.max(1), 0.0)
            near = dist < clearance
            for k in np.flatnonzero(near):
                if (q[k] > 0).any():  # outside the box: along the normal of its nearest point
                    n = np.sign(r[k]) * outside[k]
                    n = n / np.linalg.norm(n)
                else:  # inside: out through the nearest side
                    axis = int(np.argmax(q[k]))
                    n = np.zeros(2)
                    n[axis] = np.sign(r[k, axis]) or 1.0
                out[k] += n * (clearance - dist[k])
                moved[k] = True
        for cx, cy, radius in obstacles.discs:
            r = out - np.array([cx, cy])
            length = np.hypot(r[:, 0], r[:, 1])
            near = length - radius < clearance
            for k in np.flatnonzero(near):
                n = r[k] / length[k] if length[k] > 1e-9 else np.array([1.0, 0.0])
                out[k] = np.array([cx, cy]) + n * (radius + clearance)
                moved[k] = True
    return out, moved


def shield(inp: ShieldInput, cfg: ShieldConfig) -> ShieldDecision:
    """The shield's decision for one tick (see the module docstring)."""
    names, D = inp.names, len(inp.names)
    phys = np.asarray(inp.physical, dtype=bool)
    pos = np.asarray(inp.pos, dtype=np.float64)
    action = np.full(D, int(Action.TRACK))
    events: list[ShieldEvent] = []

    def fire(mask: np.ndarray, act: Action, rule: str, detail: str) -> None:
        for k in np.flatnonzero(mask):
            action[k] = max(action[k], int(act))
            events.append(ShieldEvent(names[k], rule, detail, int(act)))

    everyone = np.ones(D, dtype=bool)
    # --- whole-flight rules
    if inp.stop_requested:
        fire(everyone, Action.LAND, "signal", "stop requested (SIGINT/SIGTERM)")
    if inp.policy_latency > cfg.policy_stall:
        fire(everyone, Action.LAND, "policy_stall", f"policy late for {inp.policy_latency:.2f} s")
    silent_all = inp.links_silent > 0
    lost = (np.asarray(inp.link_age) > cfg.link_timeout) & (not silent_all)
    if silent_all:
        stalled = inp.links_silent > cfg.link_timeout + cfg.link_stall
        why = f"every link silent for {inp.links_silent:.2f} s (the ground station stalled)"
        fire(everyone, Action.LAND if stalled else Action.HOLD, "links_silent", why)
    if lost.any():
        fire(lost, Action.LOST, "link_lost", f"no packet for more than {cfg.link_timeout} s")
        alone = np.zeros(D, dtype=bool) if inp.alone is None else np.asarray(inp.alone, dtype=bool)
        landing_all = lost & ~alone  # a drone dropped alone leaves the others flying
        if landing_all.any():
            who = ", ".join(n for n, x in zip(names, landing_all, strict=True) if x)
            fire(~lost, Action.LAND, "link_lost", f"link lost: {who}")
    locked = np.zeros(D, dtype=bool) if inp.locked is None else np.asarray(inp.locked, dtype=bool)
    if locked.any():
        fire(locked, Action.STOP, "locked", "the supervisor reports the drone locked (emergency stop)")
        fire(~locked, Action.LAND, "locked", f"locked: {', '.join(n for n, x in zip(names, locked, strict=True) if x)}")
    # --- poses
    known = np.asarray(np.isfinite(pos).all(1))
    age = np.asarray(inp.pose_age, dtype=np.float64)
    stale = phys & (~known | ~(age <= cfg.stale_pose))
    tracked = phys | np.isfinite(age)  # a landed drone still tracked shows the system is alive
    if phys.any() and (~known | ~(age <= cfg.stale_pose))[tracked].all():
        freshest = float(np.min(np.where(known, age, np.inf)[tracked]))
        if freshest > cfg.stop_after:
            fire(phys, Action.STOP, "mocap_lost", f"no fresh pose of any drone for {freshest:.2f} s")
        else:
            fire(everyone, Action.LAND, "all_stale", "no fresh pose of any drone")
    else:
        fire(stale, Action.LAND, "stale_pose", f"no fresh pose for {cfg.stale_pose} s")
    if inp.estimate_off is not None:
        off = phys & known & (np.asarray(inp.estimate_off, dtype=np.float64) >= cfg.estimate_hold)
        why = f"its onboard estimate is more than {cfg.estimate_tolerance} m from its pose"
        fire(off, Action.LAND, "estimate_off", why)
    lo, hi = geofence(inp.arena, cfg.margin)
    outside = (
        phys & known & (((pos[:, :2] < lo - cfg.outside_tolerance) | (pos[:, :2] > hi + cfg.outside_tolerance)).any(1))
    )
    fire(outside, Action.LAND, "outside", "measured outside the geofence")
    battery = np.asarray(inp.battery, dtype=np.float64)
    fire(battery < cfg.min_battery, Action.LAND, "battery", f"battery below {cfg.min_battery} V")

    # --- setpoints: NaN -> hold; clamps (speed, then step, so the step limit always holds); fence; obstacles
    sp = np.array(inp.setpoint, dtype=np.float64)
    vel_ff = np.zeros((D, 3)) if inp.setpoint_vel is None else np.nan_to_num(np.array(inp.setpoint_vel, dtype=float))
    clamped = np.zeros(D, dtype=bool)
    bad = np.asarray(~np.isfinite(sp).all(1))
    fire(bad & (action == Action.TRACK), Action.HOLD, "nan_setpoint", "the proposed setpoint has NaN")
    sp = np.where(bad[:, None], np.where(known[:, None], pos, inp.prev_setpoint), sp)
    prev = np.asarray(inp.prev_setpoint, dtype=np.float64)
    has_prev = np.isfinite(prev).all(1)
    move = sp[:, :2] - prev[:, :2]
    moved = np.hypot(move[:, 0], move[:, 1])
    limit = cfg.max_speed * inp.dt
    fast = has_prev & (moved > limit)
    sp[fast, :2] = prev[fast, :2] + move[fast] * (limit / moved[fast])[:, None]
    fire(fast & phys, Action.TRACK, "speed", f"setpoint faster than {cfg.max_speed} m/s")
    step = sp[:, :2] - pos[:, :2]
    dist = np.hypot(step[:, 0], step[:, 1])
    over = known & (dist > cfg.max_step)
    sp[over, :2] = pos[over, :2] + step[over] * (cfg.max_step / dist[over])[:, None]
    fire(over & phys, Action.TRACK, "step", f"setpoint more than {cfg.max_step} m from the drone")
    z_lo, z_hi = cfg.z_limits
    high = (sp[:, 2] < z_lo) | (sp[:, 2] > z_hi)
    sp[:, 2] = np.clip(sp[:, 2], z_lo, z_hi)
    fire(high & phys, Action.TRACK, "altitude", f"setpoint z outside {list(cfg.z_limits)}")
    fenced = phys & ((sp[:, :2] < lo) | (sp[:, :2] > hi)).any(1)
    sp[phys, :2] = np.clip(sp[phys, :2], lo, hi)
    fire(fenced, Action.TRACK, "geofence", "setpoint pulled inside the geofence")
    pushed_xy, near_obstacle = push_out_of_obstacles(sp[:, :2], inp.obstacles, cfg.obstacle_clearance)
    near_obstacle &= phys
    sp[near_obstacle, :2] = np.clip(pushed_xy[near_obstacle], lo, hi)
    fire(near_obstacle, Action.TRACK, "obstacle", f"setpoint kept {cfg.obstacle_clearance} m from obstacles")
    clamped |= fast | over | high | fenced | near_obstacle

    # --- separation between physical drones with known poses: now, at the setpoints, and ahead. A drone that
    # holds (for another rule, or for a pair found before) is checked where it will hold, not where its policy
    # wanted to go: a paused host leaves every drone flying to what was sent last, so what is sent must be apart
    prev_hold = np.full((D, 3), np.nan) if inp.hold_at is None else np.asarray(inp.hold_at, dtype=np.float64)
    here = np.where(known[:, None], pos, prev)
    latch = np.where(np.isfinite(prev_hold).all(1)[:, None], prev_hold, here)
    latch[:, 2] = np.clip(np.where(np.isfinite(latch[:, 2]), latch[:, 2], sp[:, 2]), z_lo, z_hi)
    vel = np.nan_to_num(np.asarray(inp.vel, dtype=np.float64))
    # a drone with no valid pose (or a lost one) is an obstacle at its last pose, grown by how far it may have flown
    grow = np.zeros(D) if inp.grow is None else np.nan_to_num(np.asarray(inp.grow, dtype=np.float64))
    last = np.full((D, 3), np.nan) if inp.last_pos is None else np.asarray(inp.last_pos, dtype=np.float64)
    ghost = phys & (grow > 0) & np.isfinite(last).all(1)
    pos = np.where(ghost[:, None], last, pos)
    vel[ghost] = 0.0
    ok = phys & (known | ghost)
    i, j = np.triu_indices(D, 1)
    keep = ok[i] & ok[j]
    i, j = i[keep], j[keep]
    r = (2 * cfg.drone_radius + grow[i] + grow[j]) / 2
    h = (2 * cfg.drone_half_height + grow[i] + grow[j]) / 2
    now_d = ellipsoid_distance(pos[j] - pos[i], r, h)
    ahead = closest_approach(pos[j] - pos[i], vel[j] - vel[i], cfg.lookahead, r, h)
    tracking = action == Action.TRACK
    conflict_pair = np.zeros(len(i), dtype=bool)
    while True:  # holds only grow (at most D rounds); a pair found in a round stays found
        goal = np.where(tracking[:, None], sp, np.where((action <= Action.HOLD)[:, None], latch, pos))
        ff = np.where(tracking[:, None], vel_ff, 0.0)
        proposed = closest_approach(goal[j] - goal[i], ff[j] - ff[i], cfg.lookahead, r, h)
        commanded = closest_approach(pos[j] - pos[i], ff[j] - ff[i], cfg.lookahead, r, h)  # ff from here
        closing = (np.minimum(proposed, commanded) < HOLD_MARGIN) & (np.minimum(proposed, commanded) < now_d - 1e-12)
        conflict_pair |= (now_d < HOLD_MARGIN) | (ahead < HOLD_MARGIN) | closing
        conflict = np.zeros(D, dtype=bool)
        conflict[i[conflict_pair]] = True
        conflict[j[conflict_pair]] = True
        if not (conflict & tracking).any():
            break
        tracking &= ~conflict
    fire(conflict & (action <= Action.HOLD), Action.HOLD, "separation", "separation ellipsoids would touch")

    # --- the setpoint to send: TRACK the clamped one, HOLD the latched hold point (pushed apart)
    hold = action == Action.HOLD
    track = action == Action.TRACK
    push = np.zeros((D, 3))
    for a, b, d, rr in zip(i[conflict_pair], j[conflict_pair], now_d[conflict_pair], r[conflict_pair], strict=True):
        delta = pos[a, :2] - pos[b, :2]
        norm = float(np.hypot(*delta))
        unit = delta / norm if norm > 1e-9 else np.array([1.0, 0.0])
        shift = max(0.0, PUSH_MARGIN - float(d)) * float(rr)
        push[a, :2] += unit * shift
        push[b, :2] -= unit * shift
    out = np.full((D, 3), np.nan)
    out_vel = np.full((D, 3), np.nan)
    out[track] = sp[track]
    out_vel[track] = np.where(clamped[track, None], 0.0, vel_ff[track])
    # a held full-state setpoint leaves Mellinger at rest FF_REACH * v past its position (kd / kp): a setpoint
    # that stops being renewed must not carry the drone through the fence
    out_vel[track, :2] = np.clip(out_vel[track, :2], (lo - sp[track, :2]) / FF_REACH, (hi - sp[track, :2]) / FF_REACH)
    pushed = latch + push
    # a push must not carry a drone toward a third one: where it would, the drone holds at its latch
    where = np.where(hold[:, None], pushed, np.where(track[:, None], sp, pos))
    for k in np.flatnonzero(hold & ok & (np.abs(push).sum(1) > 0)):
        others = np.flatnonzero(ok & (np.arange(D) != k))
        rk = (2 * cfg.drone_radius + grow[others] + grow[k]) / 2
        hk = (2 * cfg.drone_half_height + grow[others] + grow[k]) / 2
        before = ellipsoid_distance(pos[others] - pos[k], rk, hk)
        after = ellipsoid_distance(where[others] - pushed[k], rk, hk)
        if (after < np.minimum(before, PUSH_MARGIN) - 1e-9).any():
            pushed[k] = latch[k]
    out[hold] = pushed[hold]
    out_vel[hold] = 0.0
    held = hold & phys
    out[held, :2] = np.clip(out[held, :2], lo, hi)  # a hold never leaves the fence either
    hold_at = np.full((D, 3), np.nan)
    hold_at[hold] = out[hold]  # the push accumulates: a held pair keeps moving apart until clear
    return ShieldDecision(
        action=action,
        setpoint=out,
        events=tuple(events),
        names=tuple(names),
        velocity=out_vel,
        hold_at=hold_at,
        pairs=np.stack([i[conflict_pair], j[conflict_pair]], 1),
    )
