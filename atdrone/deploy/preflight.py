"""The dry run's checks, run before anything arms: does the bridge see what training saw?

- tracking: every rigid body has a fresh pose;
- spawn: every drone stands inside its spawn region of the task (pursuer slot i in
  pursuer box i, evader j in evader box j), within ``spawn_tolerance``; a backup drone
  (waiting on the floor to take a partner's slot) inside the fence;
- heading: every drone faces +y, as every episode starts in training (catches a yaw
  convention or yaw offset that is off);
- battery: every drone at or above ``min_battery_preflight``;
- observation: the observations the loop computes from the live poses equal those of
  a :class:`~atdrone.envs.core.BatchedPursuit` placed at the same poses (with the
  measured yaws): the slot order, the frame and the headings all agree;
- estimate: each drone's onboard state estimate (logged ``stateEstimate`` x, y, z, yaw)
  agrees with motion capture within 0.1 m and 10 degrees: an estimator whose yaw was
  left at 0 (position-only extpos, never reset) fails here, before it can flip a drone;
- frame: the reference marker (``frame_reference``, fixed at a known arena pose) is seen
  there within 0.1 m and 10 degrees: an origin error of 0.3 m, a swapped axis or a yaw
  offset of 90 degrees fails here (the drones alone cannot show it: they fly consistently
  in whatever frame they are given).

Nothing arms unless every check passes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from atdrone.config import TaskConfig, spawn_boxes
from atdrone.envs.core import BatchedPursuit
from atdrone.envs.kinematics import wrap_angle

if TYPE_CHECKING:
    from atdrone.deploy.config import DeployConfig
    from atdrone.deploy.loop import Flight

HEADING_TOLERANCE_DEG = 20.0
OBS_TOLERANCE = 0.35  # about 20 degrees of bearing (2 sin 10 deg) or 1.7 m / 5 of distance
ESTIMATE_POS_TOLERANCE = 0.1  # m between the onboard estimate (or the reference marker) and motion capture
ESTIMATE_YAW_TOLERANCE_DEG = 10.0


@dataclass(frozen=True)
class Check:
    """One preflight check and what it found."""

    name: str
    ok: bool
    detail: str


@dataclass
class Preflight:
    """The checks of a dry run; ``ok`` only when every one passed."""

    checks: list[Check] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return bool(self.checks) and all(c.ok for c in self.checks)

    def add(self, name: str, problems: list[str], fine: str) -> None:
        self.checks.append(Check(name, not problems, "; ".join(problems) if problems else fine))

    def text(self) -> str:
        return "\n".join(f"  [{'ok' if c.ok else 'FAIL'}] {c.name}: {c.detail}" for c in self.checks)


def spawn_regions(task: TaskConfig) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Boxes [[x0, x1], [y0, y1]] of each pursuer slot and each evader."""
    rp, re = task.players.respawn_region.pursuer, task.players.respawn_region.evader
    return (
        [np.array(b) for b in spawn_boxes(rp, task.players.num_p)],
        [np.array(b) for b in spawn_boxes(re, task.players.num_e)],
    )


def check_spawn(names: list[str], pos: np.ndarray, boxes: list[np.ndarray], tolerance: float) -> list[str]:
    """Problems with drones (pos (D, 3), NaN unknown) outside their boxes by more than ``tolerance``."""
    problems = []
    for name, p, box in zip(names, pos, boxes, strict=True):
        if not np.isfinite(p).all():
            continue  # reported by the tracking check
        lo, hi = box[:, 0] - tolerance, box[:, 1] + tolerance
        if (p[:2] < lo).any() or (p[:2] > hi).any():
            problems.append(
                f"{name} at ({p[0]:.2f}, {p[1]:.2f}) is outside its spawn region "
                f"x {box[0, 0]:.2f}-{box[0, 1]:.2f}, y {box[1, 0]:.2f}-{box[1, 1]:.2f}"
            )
    return problems


def check_heading(names: list[str], yaw: np.ndarray, tolerance_deg: float = HEADING_TOLERANCE_DEG) -> list[str]:
    """Problems with drones not facing +y (the heading every episode starts with)."""
    off = np.degrees(np.abs(wrap_angle(yaw - np.pi / 2)))
    return [
        f"{n} faces {math.degrees(y):.0f} deg, not +y (90 deg): off by {o:.0f} deg"
        for n, y, o in zip(names, yaw, off, strict=True)
        if np.isfinite(y) and o > tolerance_deg
    ]


def check_observation(
    task: TaskConfig,
    pos_p: np.ndarray,
    yaw_p: np.ndarray,
    pos_e: np.ndarray,
    loop_obs: Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray],
) -> list[str]:
    """The loop's observations vs a BatchedPursuit placed at the same poses with the measured yaws."""
    core = BatchedPursuit(task, 1, seed=0)
    core.reset()
    core.state.pos[0] = np.concatenate([pos_p, pos_e])
    core.state.heading[0, : len(pos_p)] = yaw_p
    expected = core.observe()[0]
    got = loop_obs(pos_p, np.full(len(pos_p), np.pi / 2), pos_e, np.zeros(len(pos_e), dtype=bool))[0]
    diff = np.abs(expected - got).max(-1)
    return [
        f"pursuer slot {i}: observation differs from the simulator's by {d:.2f} (tolerance {OBS_TOLERANCE})"
        for i, d in enumerate(diff)
        if not d <= OBS_TOLERANCE
    ]


def check_estimates(
    names: list[str],
    pos: np.ndarray,
    yaw: np.ndarray,
    estimates: dict[str, tuple[float, float, float, float]],
    pos_tolerance: float = ESTIMATE_POS_TOLERANCE,
    yaw_tolerance_deg: float = ESTIMATE_YAW_TOLERANCE_DEG,
) -> list[str]:
    """Problems with drones whose onboard state estimate (x, y, z, yaw radians) disagrees with motion capture
    (pos (D, 3), yaw (D,) in the arena frame): an estimator left at yaw 0, one not reset, one fed another frame."""
    problems = []
    for name, p, y in zip(names, pos, yaw, strict=True):
        est = np.asarray(estimates.get(name, (math.nan,) * 4), dtype=np.float64)
        if not np.isfinite(est).all():
            problems.append(f"{name}: no onboard state estimate logged")
            continue
        if not np.isfinite(p).all():
            continue  # reported by the tracking check
        err = float(np.linalg.norm(est[:3] - p))
        yaw_err = abs(math.degrees(float(wrap_angle(np.array(est[3] - y)))))
        if err > pos_tolerance:
            problems.append(f"{name}: onboard estimate {err:.2f} m from motion capture (tolerance {pos_tolerance} m)")
        if yaw_err > yaw_tolerance_deg:
            problems.append(
                f"{name}: onboard yaw {math.degrees(est[3]):.0f} deg, motion capture {math.degrees(y):.0f} deg "
                f"(off by {yaw_err:.0f}, tolerance {yaw_tolerance_deg:g})"
            )
    return problems


def check_reference(
    body: str,
    seen: tuple[np.ndarray, float] | None,
    pos: tuple[float, float, float],
    yaw_deg: float,
    pos_tolerance: float = ESTIMATE_POS_TOLERANCE,
    yaw_tolerance_deg: float = ESTIMATE_YAW_TOLERANCE_DEG,
) -> list[str]:
    """Problems with the frame: the reference marker, seen through ``frame`` at ``seen`` (arena position, yaw
    radians; None: not tracked), is not at its stated pose (an origin, axis or yaw-offset error)."""
    if seen is None:
        return [f"reference body {body!r} not tracked: the frame cannot be checked"]
    at, yaw = seen
    err = float(np.linalg.norm(np.asarray(at) - np.asarray(pos)))
    yaw_err = abs(math.degrees(float(wrap_angle(np.array(yaw - math.radians(yaw_deg))))))
    problems = []
    if err > pos_tolerance:
        problems.append(
            f"reference body {body!r} at ({at[0]:.2f}, {at[1]:.2f}, {at[2]:.2f}), stated "
            f"({pos[0]:.2f}, {pos[1]:.2f}, {pos[2]:.2f}): the frame is off by {err:.2f} m"
        )
    if yaw_err > yaw_tolerance_deg:
        problems.append(f"reference body {body!r} yaw off its stated {yaw_deg:g} deg by {yaw_err:.0f} deg")
    return problems


# ------------------------------------------------------------------ on the live backend
def run_preflight(flight: Flight, cfg: DeployConfig, task: TaskConfig, wait: float = 3.0) -> Preflight:
    """Every check of the dry run on the live backend (see :mod:`atdrone.deploy.preflight`)."""
    clock, pre = flight.clock, Preflight()
    deadline = clock.now() + wait * clock.rate
    while clock.now() < deadline:
        pos, yaw, age = flight.measured()
        if (age < cfg.shield.stale_pose).all() and all(np.isfinite(v) for v in flight.bridge.battery().values()):
            break
        clock.sleep(0.05)
    pos, yaw, age = flight.measured()
    stale = [
        f"{n} ({'never seen' if not np.isfinite(a) else f'{a:.2f} s old'})"
        for n, a in zip(flight.names, age, strict=True)
        if not a < cfg.shield.stale_pose
    ]
    pre.add(
        "tracking",
        [f"no fresh pose of {', '.join(stale)}"] if stale else [],
        f"{len(flight.names)} rigid bodies tracked",
    )
    ref = cfg.frame_reference
    if ref is None:
        pre.add("frame", ["no frame_reference marker configured: the frame cannot be checked"], "")
    else:
        marker = flight.mocap.latest().get(ref.body)
        seen = None if marker is None else (marker.pos, marker.yaw)
        pre.add("frame", check_reference(ref.body, seen, ref.pos, ref.yaw_deg), "the reference marker is where stated")
    p_boxes, e_boxes = spawn_regions(task)
    boxes = p_boxes[: len(flight.pursuers)] + e_boxes[: len(flight.evader_drones)]
    F = len(flight.flyers)
    fence = np.array([[cfg.shield.margin, task.site.boundary.width - cfg.shield.margin]])
    fence = np.r_[fence, [[cfg.shield.margin, task.site.boundary.height - cfg.shield.margin]]]
    spawn = check_spawn(flight.flyers, pos[:F], boxes, cfg.spawn_tolerance)
    spawn += check_spawn(flight.names[F:], pos[F:], [fence] * (len(flight.names) - F), 0.0)  # backups
    pre.add(
        "spawn",
        spawn,
        "every drone inside its spawn region" + (", every backup inside the fence" if len(flight.names) > F else ""),
    )
    pre.add("heading", check_heading(flight.names, yaw), "every drone faces +y")
    pre.add(
        "estimate",
        check_estimates(flight.names, pos, yaw, flight.bridge.estimates()),
        "every onboard state estimate agrees with motion capture (0.1 m, 10 deg)",
    )
    battery = flight.bridge.battery()
    low = [
        f"{n} at {battery.get(n, math.nan):.2f} V"
        for n in flight.names
        if not battery.get(n, math.nan) >= cfg.min_battery_preflight
    ]
    pre.add("battery", [f"below {cfg.min_battery_preflight} V: {', '.join(low)}"] if low else [], "every battery fine")
    P = len(flight.pursuers)
    if np.isfinite(pos[:F]).all() and np.isfinite(yaw[:F]).all():
        pos_e = pos[P:F, :2] if flight.evader_drones else np.array([b.mean(1) for b in e_boxes])
        obs_problems = check_observation(
            task, pos[:P, :2], yaw[:P], pos_e, lambda a, h, e, c: flight.observations(a, h, e, c)[0]
        )
    else:
        obs_problems = ["poses missing: cannot compare observations"]
    pre.add("observation", obs_problems, "the loop's observations equal the simulator's at the live poses")
    return pre


def plan_text(cfg: DeployConfig, member: str, task: TaskConfig) -> str:
    """What an armed run would do."""
    drones = ", ".join(f"{d.name} ({d.role}{', ' + d.uri if d.uri else ''})" for d in cfg.fleet())
    partners = f"zoo {cfg.partners.zoo}" if cfg.partners.zoo else ", ".join(cfg.partners.members)
    return (
        f"plan: fly member {member} on {task.name} ({cfg.backend} backend), {cfg.episodes} episode(s) of at most "
        f"{task.task.task_horizon} steps at {cfg.flight_height} m; partners {partners}; evaders {cfg.evaders}\n"
        f"      drones: {drones}\n"
        f"      shield: fence margin {cfg.shield.margin} m, separation ellipsoid {cfg.shield.drone_radius} / "
        f"{cfg.shield.drone_half_height} m per drone, "
        f"stale pose {cfg.shield.stale_pose} s, battery {cfg.shield.min_battery} V"
    )
