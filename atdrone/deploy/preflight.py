"""The dry run's checks, run before anything arms: does the bridge see what training saw?

- tracking: every rigid body has a fresh pose;
- spawn: every drone stands inside its spawn region of the task (pursuer slot i in
  pursuer box i, evader j in evader box j), within ``spawn_tolerance``;
- heading: every drone faces +y, as every episode starts in training (catches a yaw
  convention or yaw offset that is off);
- battery: every drone at or above ``min_battery_preflight``;
- observation: the observations the loop computes from the live poses equal those of
  a :class:`~atdrone.envs.core.BatchedPursuit` placed at the same poses (with the
  measured yaws): the slot order, the frame and the headings all agree;
- command path: a short hover-and-turn on a private simulated fleet through the same
  command function, bridge and motion-capture code; the drone must end where the
  simulator's turn rule puts it.

A frame transform that is off (an axis swapped, yaw off by 90 degrees) fails the
spawn, heading and observation checks, and nothing arms.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from atdrone.config import TaskConfig, spawn_boxes
from atdrone.deploy.clock import ScaledClock
from atdrone.envs.core import BatchedPursuit
from atdrone.envs.kinematics import advance, turn, wrap_angle
from atdrone.envs.observation import Arena

HEADING_TOLERANCE_DEG = 20.0
OBS_TOLERANCE = 0.35  # about 20 degrees of bearing (2 sin 10 deg) or 1.7 m / 5 of distance
COMMAND_TOLERANCE = 0.1  # metres between the flown and the simulated hover-and-turn


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


def hover_and_turn(
    task: TaskConfig,
    height: float,
    command: Callable[..., tuple[np.ndarray, np.ndarray, np.ndarray]],
    actions: tuple[float, ...] = (1.0, 1.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0),
    rate: float = 4.0,
) -> list[str]:
    """Fly ``actions`` with one simulated drone through the real command path; compare with the turn rule.

    The drone takes off at the arena's centre facing +y, then each tick: measured pose ->
    ``command`` -> cflib position setpoint -> simulated Crazyflie -> simulated mocap. The
    simulator predicts the path from the same start by :func:`turn` and :func:`advance`.
    """
    from atdrone.deploy.bridge import CflibBridge
    from atdrone.deploy.mocap import FrameTransform, SimMocap
    from atdrone.deploy.simfleet import SimFleet

    arena = Arena.from_config(task)
    clock = ScaledClock(rate)
    start = np.array([[arena.geometry.width / 2, arena.geometry.height / 2 - 0.6, 0.0]])
    with SimFleet(["check"], start, clock) as fleet:
        mocap = SimMocap(fleet.truth, FrameTransform(), clock, noise=0.0, latency=0.0)
        bridge = CflibBridge(fleet.uris)
        mocap.start()
        try:
            bridge.open()
            mocap.on_frame(lambda poses: bridge.send_extpos({n: tuple(p.pos) for n, p in poses.items()}))
            bridge.arm(["check"])
            bridge.takeoff(["check"], height, 1.0)
            clock.sleep(1.5)
            pose = mocap.latest()["check"]
            pos, heading = pose.pos[None, :2].copy(), np.array([np.pi / 2])
            predicted = pos.copy()
            t = clock.now()
            for a in actions:
                t += task.dt
                clock.sleep_until(t)
                pos = mocap.latest()["check"].pos[None, :2]
                heading, setpoint, yaw_deg = command(pos, heading, np.array([a]), arena, height)
                bridge.send_position({"check": (*setpoint[0], float(yaw_deg[0]))})
            head_sim = np.array([np.pi / 2])
            for a in actions:
                head_sim = turn(head_sim, np.array([a]))
                predicted = advance(predicted, head_sim, arena.step, arena.geometry.width, arena.geometry.height)
            for _ in range(3):  # hold the last setpoint while the drone catches up (tau)
                t += task.dt
                clock.sleep_until(t)
                bridge.send_position({"check": (*setpoint[0], float(yaw_deg[0]))})
            final = mocap.latest()["check"]
            bridge.notify_stop(["check"])
            bridge.land(["check"], 1.0)
            clock.sleep(1.2)
        finally:
            mocap.stop()
            bridge.close()
    problems = []
    err = float(np.hypot(*(final.pos[:2] - predicted[0])))
    if err > COMMAND_TOLERANCE:
        problems.append(
            f"hover-and-turn ended {err:.2f} m from the simulator's turn rule (tolerance {COMMAND_TOLERANCE})"
        )
    yaw_err = abs(math.degrees(float(wrap_angle(np.array(final.yaw - head_sim[0])))))
    if yaw_err > HEADING_TOLERANCE_DEG:
        problems.append(f"hover-and-turn yaw off the turn rule's heading by {yaw_err:.0f} deg")
    return problems
