"""The safety shield: pure functions from one tick's measurements and proposed setpoints to what may be sent.

Per drone the shield decides an :class:`Action`, the most severe rule that fires:

    TRACK < HOLD < LAND < STOP < LOST

- TRACK: send the (clamped) setpoint. HOLD: send a setpoint at the measured position
  (the previous setpoint when the pose is unknown). LAND: the loop lands the drone with
  the high-level commander. STOP: emergency stop (motors off). LOST: the link is gone;
  nothing can be sent (the firmware's watchdog takes over), the loop reports it.

Rules (``rule`` names as they appear in the flight log):

- ``geofence``: a setpoint outside the fence (the arena shrunk by ``margin``) is pulled
  inside. ``outside``: a drone measured beyond the fence by more than
  ``outside_tolerance`` lands.
- ``step``: a setpoint at most ``max_step`` (horizontal) from the measured position;
  ``speed``: at most ``max_speed * dt`` from the previous setpoint; ``altitude``: z
  within ``z_limits``; ``nan_setpoint``: a proposed setpoint with NaN holds.
- ``separation``: physical drones whose clamped setpoints, or whose positions predicted
  ``horizon`` seconds ahead, come closer than ``min_separation`` while converging (or
  that already are that close) hold. Holding sends the measured position, so a held
  pair's setpoints are where the drones are.
- ``stale_pose``: a drone without a fresh pose for ``stale_pose`` seconds, or with NaN
  in its pose, lands. ``all_stale``: every physical drone stale -> all land;
  ``mocap_lost``: the freshest pose older than ``stop_after`` -> all STOP.
- ``policy_stall``: the policy step took longer than ``policy_stall`` -> all land.
- ``link_lost``: no packet from a drone for ``link_timeout`` -> that drone is LOST and
  every other drone lands.
- ``battery``: below ``min_battery`` -> that drone lands.
- ``signal``: SIGINT/SIGTERM -> all land.

Virtual drones (``physical`` False, e.g. simulated evaders) are ignored by the fence,
separation and pose rules. Inputs are never modified.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np

from atdrone.config import _check, _non_negative, _positive


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
    min_separation: float = field(default=0.15, metadata=_check(_positive))  # between physical drones
    horizon: float = field(default=0.2, metadata=_check(_non_negative))  # s of look-ahead for separation
    max_speed: float = field(default=0.8, metadata=_check(_positive))  # m/s between consecutive setpoints
    max_step: float = field(default=0.3, metadata=_check(_positive))  # m from the measured position
    z_limits: tuple[float, float] = field(default=(0.2, 1.5), metadata=_check(_limits))
    stale_pose: float = field(default=0.3, metadata=_check(_positive))  # s without a fresh pose -> land
    stop_after: float = field(default=1.0, metadata=_check(_positive))  # s with every pose stale -> STOP
    policy_stall: float = field(default=0.5, metadata=_check(_positive))  # s a policy step may take
    link_timeout: float = field(default=0.5, metadata=_check(_positive))  # s without a packet -> lost
    min_battery: float = field(default=3.4, metadata=_check(_positive))  # V


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
    policy_latency: float  # s
    stop_requested: bool


@dataclass(frozen=True)
class ShieldEvent:
    """A rule that fired for a drone ("" for a rule about every drone is never used: each drone gets one)."""

    drone: str
    rule: str
    detail: str


@dataclass(frozen=True)
class ShieldDecision:
    """Per drone: the action, the setpoint to send (TRACK/HOLD; NaN otherwise) and the events."""

    action: np.ndarray  # (D,) int
    setpoint: np.ndarray  # (D, 3)
    events: tuple[ShieldEvent, ...]
    names: tuple[str, ...] = ()

    def lost(self) -> list[str]:
        """The drones whose link is lost."""
        return [n for n, a in zip(self.names, self.action, strict=True) if a == Action.LOST]


def geofence(arena: tuple[float, float], margin: float) -> tuple[np.ndarray, np.ndarray]:
    """The fence rectangle: lower and upper (x, y) corners of the arena shrunk by ``margin``."""
    return np.array([margin, margin]), np.array([arena[0] - margin, arena[1] - margin])


def _pairs_closer(points: np.ndarray, ok: np.ndarray, limit: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Index pairs (i < j) of rows with ``ok`` whose horizontal distance is below ``limit``; and those distances."""
    i, j = np.triu_indices(len(points), 1)
    keep = ok[i] & ok[j]
    i, j = i[keep], j[keep]
    d = np.hypot(points[i, 0] - points[j, 0], points[i, 1] - points[j, 1])
    close = d < limit
    return i[close], j[close], d[close]


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
            events.append(ShieldEvent(names[k], rule, detail))

    everyone = np.ones(D, dtype=bool)
    # --- whole-flight rules
    if inp.stop_requested:
        fire(everyone, Action.LAND, "signal", "stop requested (SIGINT/SIGTERM)")
    if inp.policy_latency > cfg.policy_stall:
        fire(everyone, Action.LAND, "policy_stall", f"policy step took {inp.policy_latency:.2f} s")
    lost = np.asarray(inp.link_age) > cfg.link_timeout
    if lost.any():
        fire(lost, Action.LOST, "link_lost", f"no packet for more than {cfg.link_timeout} s")
        fire(
            ~lost, Action.LAND, "link_lost", f"link lost: {', '.join(n for n, x in zip(names, lost, strict=True) if x)}"
        )
    # --- poses
    known = np.asarray(np.isfinite(pos).all(1))
    age = np.asarray(inp.pose_age, dtype=np.float64)
    stale = phys & (~known | ~(age <= cfg.stale_pose))
    if phys.any() and stale[phys].all():
        freshest = float(np.min(np.where(known, age, np.inf)[phys]))
        if freshest > cfg.stop_after:
            fire(phys, Action.STOP, "mocap_lost", f"no fresh pose of any drone for {freshest:.2f} s")
        else:
            fire(everyone, Action.LAND, "all_stale", "no fresh pose of any drone")
    else:
        fire(stale, Action.LAND, "stale_pose", f"no fresh pose for {cfg.stale_pose} s")
    lo, hi = geofence(inp.arena, cfg.margin)
    outside = (
        phys & known & (((pos[:, :2] < lo - cfg.outside_tolerance) | (pos[:, :2] > hi + cfg.outside_tolerance)).any(1))
    )
    fire(outside, Action.LAND, "outside", "measured outside the geofence")
    battery = np.asarray(inp.battery, dtype=np.float64)
    fire(battery < cfg.min_battery, Action.LAND, "battery", f"battery below {cfg.min_battery} V")

    # --- setpoints: NaN -> hold; clamps; fence
    sp = np.array(inp.setpoint, dtype=np.float64)
    bad = np.asarray(~np.isfinite(sp).all(1))
    fire(bad & (action == Action.TRACK), Action.HOLD, "nan_setpoint", "the proposed setpoint has NaN")
    sp = np.where(bad[:, None], np.where(known[:, None], pos, inp.prev_setpoint), sp)
    step = sp[:, :2] - pos[:, :2]
    dist = np.hypot(step[:, 0], step[:, 1])
    over = known & (dist > cfg.max_step)
    sp[over, :2] = pos[over, :2] + step[over] * (cfg.max_step / dist[over])[:, None]
    fire(over & phys, Action.TRACK, "step", f"setpoint more than {cfg.max_step} m from the drone")
    prev = np.asarray(inp.prev_setpoint, dtype=np.float64)
    has_prev = np.isfinite(prev).all(1)
    move = sp[:, :2] - prev[:, :2]
    moved = np.hypot(move[:, 0], move[:, 1])
    limit = cfg.max_speed * inp.dt
    fast = has_prev & (moved > limit)
    sp[fast, :2] = prev[fast, :2] + move[fast] * (limit / moved[fast])[:, None]
    fire(fast & phys, Action.TRACK, "speed", f"setpoint faster than {cfg.max_speed} m/s")
    z_lo, z_hi = cfg.z_limits
    high = (sp[:, 2] < z_lo) | (sp[:, 2] > z_hi)
    sp[:, 2] = np.clip(sp[:, 2], z_lo, z_hi)
    fire(high & phys, Action.TRACK, "altitude", f"setpoint z outside {list(cfg.z_limits)}")
    fenced = phys & ((sp[:, :2] < lo) | (sp[:, :2] > hi)).any(1)
    sp[phys, :2] = np.clip(sp[phys, :2], lo, hi)
    fire(fenced, Action.TRACK, "geofence", "setpoint pulled inside the geofence")

    # --- separation between physical drones with known poses (setpoints and predicted positions)
    hold_pos = np.where(known[:, None], pos, prev)
    vel = np.nan_to_num(np.asarray(inp.vel, dtype=np.float64))
    ahead = pos + vel * cfg.horizon
    sep_ok = phys & known
    conflict = np.zeros(D, dtype=bool)
    for points in (sp, ahead, pos):
        i, j, _ = _pairs_closer(points, sep_ok, cfg.min_separation)
        rel_p = pos[j, :2] - pos[i, :2]
        rel_s = sp[j, :2] - sp[i, :2]
        converging = (rel_s * rel_s).sum(1) <= (rel_p * rel_p).sum(1) + 1e-12
        now_close = np.hypot(rel_p[:, 0], rel_p[:, 1]) < cfg.min_separation
        hit = converging | now_close
        conflict[i[hit]] = True
        conflict[j[hit]] = True
    fire(conflict & (action <= Action.HOLD), Action.HOLD, "separation", f"predicted closer than {cfg.min_separation} m")

    # --- the setpoint to send: TRACK the clamped one, HOLD the measured position
    action_arr = action
    out = np.full((D, 3), np.nan)
    track = action_arr == Action.TRACK
    hold = action_arr == Action.HOLD
    out[track] = sp[track]
    out[hold] = hold_pos[hold]
    out[hold, 2] = np.clip(np.where(np.isfinite(out[hold, 2]), out[hold, 2], sp[hold, 2]), z_lo, z_hi)
    held = hold & phys
    out[held, :2] = np.clip(out[held, :2], lo, hi)  # a hold never leaves the fence either
    return ShieldDecision(action=action_arr, setpoint=out, events=tuple(events), names=tuple(names))
