"""One episode of a flight: spawn, the 10 Hz policy loop, capture and collision judged on the measured poses.

:class:`Episodes` is the part of :class:`~atdrone.deploy.loop.Flight` that flies an
episode (see the loop's module docstring for a tick's stages): the references the
policies move (:func:`advance_reference`), the evader drones' escape step, capture at
:func:`capture_reach`, the reward as in training, and the shield's decision applied.
"""

from __future__ import annotations

import math
import time

import numpy as np

from atdrone.config import TaskConfig
from atdrone.deploy.backup import Backups
from atdrone.deploy.clock import Ticker
from atdrone.deploy.flightlog import FlightLog
from atdrone.deploy.landing import Landing
from atdrone.deploy.sequence import Sequencing
from atdrone.deploy.shield import HOLD_MARGIN, Action, ShieldConfig, ShieldDecision, geofence
from atdrone.deploy.team import PolicyRunner, Team
from atdrone.deploy.transit import LEASH
from atdrone.envs.core import CAPTURED, COLLISION, TIMEOUT
from atdrone.envs.evaders import EscapeParams
from atdrone.envs.events import absent_judgement, hide_absent, parked
from atdrone.envs.kinematics import advance, turn
from atdrone.envs.observation import Arena, Poses
from atdrone.envs.rules import EvaderMove, evader_step, judge

OUTCOMES = {CAPTURED: "captured", COLLISION: "collision", TIMEOUT: "timeout"}
CAPTURE_SLACK = 0.05  # m: evader drones count as captured this far beyond the separation ellipsoids


def capture_reach(capture_range: float, shield_cfg: ShieldConfig) -> float:
    """The distance (m) at which a pursuer captures an evader drone: the task's capture range, but at least
    :data:`CAPTURE_SLACK` beyond the separation ellipsoids (the shield keeps drones ``2 * drone_radius``
    apart). It lies beyond the distance at which the shield holds a pair (``HOLD_MARGIN`` ellipsoids), so
    a pair the separation rule holds was predicted within the reach: the loop counts that as a capture
    (docs/deploy.md, "Capturing an evader drone")."""
    reach = max(capture_range, 2 * shield_cfg.drone_radius + CAPTURE_SLACK)
    assert reach > HOLD_MARGIN * 2 * shield_cfg.drone_radius, "the capture reach must lie beyond the hold"
    return reach


def advance_reference(
    ref: np.ndarray, measured: np.ndarray, heading: np.ndarray, action: np.ndarray, arena: Arena, dt: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The simulator's turn rule and step applied to the reference, not to the measured position.

    ref, measured (D, 2), heading (D,) radians, action (D,) in [-1, 1] -> new headings (D,),
    new references (D, 2), the setpoint (D, 2) halfway along this tick's step, and the
    reference velocity (D, 2) (the trained speed along the heading; 0 where a wall stops it).
    A reference more than :data:`LEASH` ahead of its drone is first pulled back to it.
    """
    gap = ref - measured
    dist = np.hypot(gap[:, 0], gap[:, 1])
    far = dist > LEASH
    ref = np.where(far[:, None], measured + gap * (LEASH / np.maximum(dist, 1e-12))[:, None], ref)
    new_heading = turn(heading, action)
    new_ref = advance(ref, new_heading, arena.step, arena.geometry.width, arena.geometry.height)
    vel = (new_ref - ref) / dt
    return new_heading, new_ref, (ref + new_ref) / 2, vel


class Episodes(Backups, Landing, Sequencing):
    """Flying one episode (see the module docstring); the flight provides the ticks and the state."""

    team: Team
    policy: PolicyRunner
    log: FlightLog
    ticks: Ticker
    arena: Arena
    escape: EscapeParams
    judged_task: TaskConfig
    learner_slots: np.ndarray
    partner_slots: np.ndarray
    dt: float
    horizon: int
    episode: int
    episode_done: bool
    pairs: np.ndarray

    def observations(
        self, pos_p: np.ndarray, heading: np.ndarray, pos_e: np.ndarray, captured: np.ndarray
    ) -> tuple[np.ndarray, Poses]:
        raise NotImplementedError

    def _fly_episode(self) -> None:
        self.episode_done = False
        reached = self._go_to_spawn(*self._spawn())
        if reached is None or self.aborted:
            return
        spawn_p, spawn_e = reached
        P, E = len(self.pursuers), self.task.players.num_e
        heading = np.full(P, np.pi / 2)
        pos0, _, _ = self.measured()
        ref = np.where(
            np.isfinite(pos0[:, :2]), pos0[:, :2], self._slot_targets(spawn_p, spawn_e, np.zeros_like(pos0[:, :2]))
        )
        ev = self.evader_index
        ref_e = spawn_e.copy()  # the evaders' references (virtual evaders: their positions)
        head_e = np.full(E, np.pi / 2)
        lo, hi = self.escape.wander_steps
        wander_heading, wander_left = head_e.copy(), self.rng.integers(lo, hi + 1, size=E)
        captured = np.zeros(E, dtype=bool)
        ret, steps, outcome = 0.0, 0, ""
        self.policy.between_steps(self.team.start, self.team.draw(self.rng))  # after a late step of the last
        self.team_changed = False
        prev_dist: np.ndarray | None = None
        held_for = np.zeros(E, dtype=bool)  # evader drones the shield held with a pursuer last tick
        while not outcome:
            tick = self._begin_tick(steps)
            lat: dict[str, float] = {}
            c0 = time.perf_counter()
            pos, yaw, age = self.measured()
            lat["mocap_age"] = (
                float(np.nanmax(np.where(np.isfinite(age), age, np.nan))) if np.isfinite(age).any() else math.inf
            )
            c1 = time.perf_counter()
            present = self.present.copy()
            slot_pos = _fill(pos[self.slots, :2], ref[self.slots])
            # an empty slot waits outside the arena, beyond every range, as a drone its drop event landed in training
            pos_p = np.where(present[:, None], slot_pos, parked(P))
            pos_e = ref_e if not self.evader_drones else _fill(pos[ev, :2], ref[ev])
            # the episode so far: capture and collision at the measured poses
            judged = judge(np.concatenate([pos_p, pos_e])[None], captured[None], self.judged_task, self.geometry)
            if not present.all():  # an empty slot neither captures nor collides
                judged = absent_judgement(judged, present[None], self.pairs)
            dist = judged.evader_distance[0]
            if self.team_changed and prev_dist is not None:  # a changed team's approach starts from here
                prev_dist = np.where(captured, 0.0, dist)
            self.team_changed = False
            newly = (judged.captured[0] | held_for) & ~captured  # within the reach now, or held for it
            if prev_dist is not None:
                ret += self._reward(prev_dist, dist, captured, newly, judged.collided[0])
            captured = captured | newly
            prev_dist = np.where(captured, 0.0, dist)
            if self.evader_drones and newly.any():
                self._land([self.evader_drones[j] for j in np.flatnonzero(newly)])
            if captured.all():
                outcome = OUTCOMES[CAPTURED]
            elif judged.collided[0].any() and self.task.task.collision_ends_episode:
                outcome = OUTCOMES[COLLISION]
            elif steps >= self.horizon:
                outcome = OUTCOMES[TIMEOUT]
            obs, poses = self.observations(pos_p, heading, pos_e, captured)
            if not present.all():  # every observation masks an empty slot as a teammate beyond range
                hide_absent(obs, present[None], E)
            c2 = time.perf_counter()
            actions = self.policy.act(self.shield_cfg.policy_late, obs, poses, self.learner_slots, self.partner_slots)
            c3 = time.perf_counter()
            vel = np.zeros((len(self.names), 3))
            acting = self.slots[present]
            idle = self._idle(acting)  # a dropped drone, a backup not yet flying to its slot: where it is
            ref[idle] = np.where(np.isfinite(pos[idle, :2]), pos[idle, :2], ref[idle])
            setpoints = np.c_[ref, np.full(len(self.names), self.cfg.flight_height)]
            if actions is not None:
                heading, ref_p, mid_p, vel_p = advance_reference(
                    ref[self.slots], slot_pos, heading, actions, self.arena, self.dt
                )
                move = self._evaders(ref_e, head_e, pos_p, captured, wander_heading, wander_left)
                head_e, wander_heading, wander_left = move.heading, move.wander_heading, move.wander_left
                mid_e, vel_e = (ref_e + move.pos) / 2, (move.pos - ref_e) / self.dt
                ref_e = move.pos
                ref[acting] = ref_p[present]
                setpoints[acting, :2], vel[acting, :2] = mid_p[present], vel_p[present]
                if self.evader_drones:
                    ref[ev] = ref_e
                    setpoints[ev, :2], vel[ev, :2] = mid_e, vel_e
                    vel[ev[captured]] = 0.0
            for slot in self._tend_backups(pos, age, ref, setpoints, vel):  # a new drone faces +y, as it spawns
                heading[slot] = np.pi / 2
            decision = self._shield(pos, age, setpoints, vel, self.policy.late_for())
            if actions is None and not (decision.action >= Action.LAND).any():
                fence = geofence((self.geometry.width, self.geometry.height), self.shield_cfg.margin)
                decision = _hold_all(decision, self.hold_at, pos, self._airborne() & np.isfinite(pos).all(1), fence)
                self.notes.setdefault("", []).append("policy_late")
            held_for = self._held_with_a_pursuer(decision, captured, pos)
            c4 = time.perf_counter()
            if not outcome and self._apply(decision):
                outcome = "shield"
            # a held drone's reference restarts where it is held
            held = decision.action == Action.HOLD
            ref[held] = decision.setpoint[held, :2]
            self._touchdown(pos)
            c5 = time.perf_counter()
            lat.update(observe=c2 - c1, policy=c3 - c2, shield=c4 - c3, send=c5 - c4, tick=c5 - c0)
            self._log_tick(tick, steps, pos, yaw, decision, lat, ref_e if not self.evader_drones else None)
            steps += 1
        self.episode_done = outcome != "shield"
        if self.episode_done and not self.aborted:
            # the last tick's setpoints were not sent (the outcome came first) and those before carry the
            # policy's velocity: the firmware settles kd / kp * v past a stale setpoint (0.11 m at 0.22 m/s),
            # so the drones are held here, at zero velocity, before the log is written and the next leg planned
            self._hold_tick()
        self.log.episode(
            self.episode,
            outcome,
            steps,
            int(captured.sum()),
            float(ret),
            virtual_evaders=not self.evader_drones,
        )
        self.progress(
            f"[deploy] episode {self.episode + 1}/{self.cfg.episodes}: {outcome} after {steps} steps, "
            f"{int(captured.sum())}/{E} captured, {self.ticks.overruns} tick overruns so far"
        )

    def _reward(
        self, prev: np.ndarray, dist: np.ndarray, captured: np.ndarray, newly: np.ndarray, collided: np.ndarray
    ) -> float:
        rw = self.task.task.reward
        approach = float(((prev - dist) * ~captured).sum()) / rw.approach_scale
        return float(rw.capture * newly.sum() + rw.approach * approach + rw.collision * collided.any())

    def _held_with_a_pursuer(self, decision: ShieldDecision, captured: np.ndarray, pos: np.ndarray) -> np.ndarray:
        """Evader drones (E,) not yet captured that the separation rule held together with a pursuer no
        further away than the capture reach plus what the pursuer flies at the trained speed within the
        shield's look-ahead: the pursuer's own approach was about to bring it within the reach
        (:func:`capture_reach`). An evader running at a pursuer from further away is not captured."""
        out = np.zeros(len(captured), dtype=bool)
        if not self.evader_drones or decision.pairs is None:
            return out
        near = self.judged_task.task.capture_range + self.task.players.velocity_p * self.shield_cfg.lookahead
        pursuer = np.zeros(len(self.names), dtype=bool)
        pursuer[self.slots[self.present]] = True
        evader = {int(k): j for j, k in enumerate(self.evader_index)}
        for a, b in decision.pairs:
            for p, e in ((int(a), int(b)), (int(b), int(a))):
                if pursuer[p] and e in evader and np.hypot(*(pos[p, :2] - pos[e, :2])) <= near:
                    out[evader[e]] = True
        return out & ~captured

    def _evaders(
        self,
        pos_e: np.ndarray,
        head_e: np.ndarray,
        pos_p: np.ndarray,
        captured: np.ndarray,
        wander_heading: np.ndarray,
        wander_left: np.ndarray,
    ) -> EvaderMove:
        move = evader_step(
            pos_e[None],
            head_e[None],
            pos_p[None],
            captured[None],
            wander_heading[None],
            wander_left[None],
            self.task,
            self.escape,
            self.rng,
            self.geometry,
        )
        return EvaderMove(move.pos[0], move.heading[0], move.wander_heading[0], move.wander_left[0])


def _hold_all(
    decision: ShieldDecision,
    prev_hold: np.ndarray,
    pos: np.ndarray,
    airborne: np.ndarray,
    fence: tuple[np.ndarray, np.ndarray],
) -> ShieldDecision:
    """A late policy: every airborne drone the shield let track is held too, at its latched hold point (where
    it was held last tick, else where it is), zero velocity."""
    action = decision.action.copy()
    newly = airborne & (action == Action.TRACK)
    action[newly] = Action.HOLD
    latch = np.where(np.isfinite(prev_hold).all(1)[:, None], prev_hold, pos)
    latch[:, :2] = np.clip(latch[:, :2], *fence)
    setpoint = decision.setpoint.copy()
    setpoint[newly] = latch[newly]
    velocity = np.zeros_like(setpoint) if decision.velocity is None else decision.velocity.copy()
    velocity[newly] = 0.0
    hold_at = np.full_like(setpoint, np.nan) if decision.hold_at is None else decision.hold_at.copy()
    hold_at[newly] = latch[newly]
    return ShieldDecision(action, setpoint, decision.events, decision.names, velocity, hold_at, decision.pairs)


def _fill(measured: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Measured positions, the fallback where a pose is unknown (the shield lands such drones anyway)."""
    out = np.where(np.isfinite(measured), measured, fallback)
    return np.nan_to_num(out, nan=0.0)
