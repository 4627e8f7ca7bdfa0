"""The 10 Hz deploy loop: poses -> observations -> policies -> turn rule -> setpoints -> shield -> bridge.

Every tick (0.1 s of the flight's clock):

1. the latest motion-capture pose of every drone (arena frame, timed on arrival);
2. observations through the project's one observation function
   (:func:`~atdrone.envs.observation.observe`), from the measured positions and the
   headings the loop commanded (the policies' own headings, as in training);
3. the learner policy in the learner slots and the partner policies in theirs;
4. the simulator's turn rule and a position setpoint one step ahead along the new
   heading at the flight height (:func:`command`); the evaders (virtual ones, or
   setpoints for evader drones) move by the simulator's escape step;
5. the shield (:mod:`atdrone.deploy.shield`), then the bridge.

Episodes end as in simulation (every evader captured, a collision by the task's
distances, the horizon: :func:`~atdrone.envs.core.judge` on the measured poses) or
by the shield, which also ends the flight. Between episodes the drones fly back to
spawn positions with the high-level commander. Tick overruns are counted; every
stage's latency is logged per tick.
"""

from __future__ import annotations

import math
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from atdrone.config import TaskConfig
from atdrone.deploy.bridge import Bridge
from atdrone.deploy.clock import Clock, Ticker
from atdrone.deploy.config import DeployConfig
from atdrone.deploy.flightlog import FlightLog
from atdrone.deploy.mocap import MocapSource, Pose
from atdrone.deploy.shield import Action, ShieldConfig, ShieldDecision, ShieldInput, shield
from atdrone.envs.core import CAPTURED, COLLISION, TIMEOUT, EvaderMove, evader_step, judge, spawn
from atdrone.envs.evaders import EscapeParams
from atdrone.envs.geometry import Geometry
from atdrone.envs.kinematics import advance, turn
from atdrone.envs.observation import Arena, Poses, observe
from atdrone.policies.base import DroneBatch, Policy

OUTCOMES = {CAPTURED: "captured", COLLISION: "collision", TIMEOUT: "timeout"}


def command(
    pos: np.ndarray, heading: np.ndarray, action: np.ndarray, arena: Arena, height: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The simulator's turn rule, then a setpoint one step ahead along the new heading.

    pos (D, 2) measured, heading (D,) radians, action (D,) in [-1, 1] -> new headings (D,),
    setpoints (D, 3) at ``height``, yaw setpoints (D,) in DEGREES (cflib's position
    setpoint takes degrees; the high-level commander takes radians).
    """
    new_heading = turn(heading, action)
    xy = advance(pos, new_heading, arena.step, arena.geometry.width, arena.geometry.height)
    setpoint = np.concatenate([xy, np.full((len(xy), 1), height)], 1)
    return new_heading, setpoint, np.degrees(new_heading)


@dataclass
class Team:
    """The policies of one flight: the learner, and the partner policy of each partner slot this episode."""

    learner: Policy
    partners: list[Policy]
    draw_partners: Callable[[np.random.Generator], list[Policy]] | None = None  # per episode (a zoo)

    def new_episode(self, rng: np.random.Generator) -> None:
        if self.draw_partners is not None:
            self.partners = self.draw_partners(rng)
        for p in [self.learner, *self.partners]:
            p.reset(np.ones(1, dtype=bool))

    def act(self, obs: np.ndarray, poses: Poses, learner_slots: np.ndarray, partner_slots: np.ndarray) -> np.ndarray:
        """Actions (num_p,) of every pursuer slot from observations (1, num_p, obs_dim)."""
        actions = np.zeros(obs.shape[1])
        env = np.zeros(len(learner_slots), dtype=np.intp)
        actions[learner_slots] = self.learner.act(DroneBatch(obs[0, learner_slots], env, learner_slots, poses))
        for slot, policy in zip(partner_slots, self.partners, strict=True):
            s = np.array([slot])
            actions[slot] = policy.act(DroneBatch(obs[0, s], np.zeros(1, dtype=np.intp), s, poses))[0]
        return actions


@dataclass
class FaultClock:
    """Faults of the sim backend fired once their time comes (callables taking nothing)."""

    pending: list[tuple[float, str, str, Callable[[], None]]] = field(default_factory=list)  # at, drone, kind, fire
    stall: float = 0.0  # seconds the policy step is stalled by a policy_stall fault (consumed once)

    def add(self, at: float, drone: str, kind: str, fire: Callable[[], None]) -> None:
        self.pending.append((at, drone, kind, fire))

    def fire(self, t: float) -> list[tuple[str, str]]:
        """Fire the faults due at flight time ``t``; their (drone, "fault:kind"), drone "" for all."""
        due = [f for f in self.pending if f[0] <= t]
        self.pending = [f for f in self.pending if f[0] > t]
        for *_, fn in due:
            fn()
        return [(drone, f"fault:{kind}") for _, drone, kind, _ in due]


class StopRequest:
    """Set by SIGINT/SIGTERM (or :meth:`set`): every drone lands."""

    def __init__(self) -> None:
        self.event = threading.Event()
        self.signal: str = ""

    def set(self, why: str = "request") -> None:
        self.signal = why
        self.event.set()

    def __bool__(self) -> bool:
        return self.event.is_set()

    @contextmanager
    def handling_signals(self) -> Iterator[None]:
        """Install SIGINT/SIGTERM handlers for the block (main thread only; elsewhere no-op)."""
        if threading.current_thread() is not threading.main_thread():
            yield
            return
        old = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
        for s in old:
            signal.signal(s, lambda num, _frame: self.set(signal.Signals(num).name))
        try:
            yield
        finally:
            for s, h in old.items():
                signal.signal(s, h)


class Flight:
    """One flight: the drones, their policies and the loop that flies them (see the module docstring)."""

    def __init__(
        self,
        cfg: DeployConfig,
        task: TaskConfig,
        team: Team,
        bridge: Bridge,
        mocap: MocapSource,
        clock: Clock,
        log: FlightLog,
        faults: FaultClock | None = None,
        stop: StopRequest | None = None,
        progress: Callable[[str], None] | None = None,
    ) -> None:
        self.cfg, self.task, self.team = cfg, task, team
        self.progress = progress or (lambda _message: None)
        self.bridge, self.mocap, self.clock, self.log = bridge, mocap, clock, log
        self.faults = faults or FaultClock()
        self.stop = StopRequest() if stop is None else stop
        self.arena = Arena.from_config(task)
        self.geometry: Geometry = self.arena.geometry
        self.dt = task.dt
        self.shield_cfg: ShieldConfig = cfg.shield
        learners, partners = cfg.role_names("learner"), cfg.role_names("partner")
        self.pursuers = learners + partners  # pursuer slot order: learners, then partners
        self.evader_drones = cfg.role_names("evader")
        self.names = self.pursuers + self.evader_drones  # every physical drone
        self.learner_slots = np.arange(len(learners))
        self.partner_slots = np.arange(len(learners), len(self.pursuers))
        self.roles = {d.name: d.role for d in cfg.drones}
        self.bodies = {d.name: d.rigid_body for d in cfg.drones}
        self.rng = np.random.default_rng(cfg.seed)
        self.escape = EscapeParams()
        self.horizon = cfg.horizon or task.task.task_horizon
        self.state = dict.fromkeys(self.names, "idle")
        self.ticks = Ticker(clock, self.dt)
        self.t0 = clock.now()
        self.prev_setpoint = np.full((len(self.names), 3), np.nan)
        self._last_pose: tuple[float, np.ndarray] | None = None  # (clock time, positions) for the velocity estimate
        self.episode = -1
        self.aborted = ""
        self.notes: dict[str, list[str]] = {}  # fault notes for the next logged tick, per drone

    # ------------------------------------------------------------------ poses
    def measured(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (D, 3) (NaN unknown), yaws (D,) and pose ages (D,) of every physical drone."""
        latest: dict[str, Pose] = self.mocap.latest()
        now = self.clock.now()
        pos = np.full((len(self.names), 3), np.nan)
        yaw = np.full(len(self.names), np.nan)
        age = np.full(len(self.names), np.inf)
        for i, name in enumerate(self.names):
            pose = latest.get(self.bodies[name])
            if pose is not None:
                pos[i], yaw[i], age[i] = pose.pos, pose.yaw, max(0.0, now - pose.t)
        return pos, yaw, age

    def observations(
        self, pos_p: np.ndarray, heading: np.ndarray, pos_e: np.ndarray, captured: np.ndarray
    ) -> tuple[np.ndarray, Poses]:
        """Observations (1, num_p, obs_dim) and the poses record of one live frame (pursuers in slot order)."""
        poses = Poses(
            pos=np.concatenate([pos_p, pos_e], 0)[None],
            heading=np.concatenate([heading, np.full(len(pos_e), np.pi / 2)])[None],
            captured=captured[None],
            arena=self.arena,
        )
        return observe(poses), poses

    # ------------------------------------------------------------- the flight
    def run(self) -> None:
        """Take off, fly ``cfg.episodes`` episodes (or until the shield ends the flight), land."""
        try:
            self._takeoff()
            for episode in range(self.cfg.episodes):
                if self.aborted:
                    break
                self.episode = episode
                self._fly_episode()
        finally:
            self._land_all()
            pos, yaw, age = self.measured()  # the last row: where every drone ended, in its final state
            self._log_tick(self.clock.now(), -1, pos, yaw, self._shield(pos, age, pos, 0.0), {}, None)

    def _physical(self) -> np.ndarray:
        return np.ones(len(self.names), dtype=bool)

    def _takeoff(self) -> None:
        self.bridge.arm(self.names)
        self.bridge.takeoff(self.names, self.cfg.flight_height, self.cfg.takeoff_duration)
        self._set_state(self.names, "taking_off")
        self._transit(self.cfg.takeoff_duration + 0.5)
        self._set_state([n for n in self.names if self.state[n] == "taking_off"], "flying")

    def _spawn(self) -> tuple[np.ndarray, np.ndarray]:
        pos, _ = spawn(self.task, self.rng, 1)
        return pos[0, : len(self.pursuers)], pos[0, len(self.pursuers) :]

    def _go_to_spawn(self, spawn_p: np.ndarray, spawn_e: np.ndarray) -> None:
        """Fly every drone to its spawn position in three high-level legs on separate altitude layers.

        Drone i climbs (or descends) to its own layer ``flight_height + i * transit_layer``,
        flies there to above its spawn position, then descends to the flight height: the
        straight legs of two drones never meet, because no two drones share a layer while
        they move across the arena (the shield does not steer the high-level commander).
        """
        targets = {n: spawn_p[i] for i, n in enumerate(self.pursuers)}
        targets.update({n: spawn_e[j] for j, n in enumerate(self.evader_drones)})
        flying = [n for n in self.names if self.state[n] == "flying"]
        self.bridge.notify_stop(flying)
        pos, _, _ = self.measured()
        h, gap = self.cfg.flight_height, self.cfg.transit_layer
        layer = {n: h + gap * i for i, n in enumerate(self.names)}
        here = {n: pos[i, :2] if np.isfinite(pos[i, :2]).all() else targets[n] for i, n in enumerate(self.names)}
        climb = max(1.0, gap * (len(self.names) - 1) / 0.3)
        dist = max((float(np.hypot(*(here[n] - targets[n]))) for n in flying), default=0.0)
        legs = (
            ({n: (*here[n], layer[n]) for n in flying}, climb),
            ({n: (*targets[n], layer[n]) for n in flying}, max(1.0, dist / self.cfg.goto_speed)),
            ({n: (*targets[n], h) for n in flying}, climb),
        )
        for goals, duration in legs:
            for n, goal in goals.items():
                self.bridge.go_to(n, np.array(goal), math.pi / 2, duration)
            self._transit(duration + 0.3)
            if self.aborted:
                return

    def _fly_episode(self) -> None:
        spawn_p, spawn_e = self._spawn()
        self._go_to_spawn(spawn_p, spawn_e)
        if self.aborted:
            return
        P, E = len(self.pursuers), self.task.players.num_e
        heading = np.full(P, np.pi / 2)
        virtual_e = spawn_e.copy()
        head_e = np.full(E, np.pi / 2)
        lo, hi = self.escape.wander_steps
        wander_heading, wander_left = head_e.copy(), self.rng.integers(lo, hi + 1, size=E)
        captured = np.zeros(E, dtype=bool)
        ret, steps, outcome = 0.0, 0, ""
        self.team.new_episode(self.rng)
        prev_dist: np.ndarray | None = None
        while not outcome:
            tick = self.ticks.wait()
            lat: dict[str, float] = {}
            c0 = time.perf_counter()
            self._faults(tick)
            pos, yaw, age = self.measured()
            lat["mocap_age"] = (
                float(np.nanmax(np.where(np.isfinite(age), age, np.nan))) if np.isfinite(age).any() else math.inf
            )
            c1 = time.perf_counter()
            pos_p = _fill(pos[:P, :2], self.prev_setpoint[:P, :2])
            pos_e = virtual_e if not self.evader_drones else _fill(pos[P:, :2], self.prev_setpoint[P:, :2])
            # the episode so far: capture and collision at the measured poses
            judged = judge(np.concatenate([pos_p, pos_e])[None], captured[None], self.task, self.geometry)
            dist = judged.evader_distance[0]
            if prev_dist is not None:
                ret += self._reward(prev_dist, dist, captured, judged)
            prev_dist = np.where(judged.captured[0], 0.0, dist)
            captured = judged.captured[0]
            if captured.all():
                outcome = OUTCOMES[CAPTURED]
            elif judged.collided[0].any() and self.task.task.collision_ends_episode:
                outcome = OUTCOMES[COLLISION]
            elif steps >= self.horizon:
                outcome = OUTCOMES[TIMEOUT]
            obs, poses = self.observations(pos_p, heading, pos_e, captured)
            c2 = time.perf_counter()
            stall = self.faults.stall
            if stall:
                self.faults.stall = 0.0
                self.clock.sleep(stall)
            actions = self.team.act(obs, poses, self.learner_slots, self.partner_slots)
            c3 = time.perf_counter()
            policy_latency = (c3 - c2) * self.clock.rate
            heading, setpoint_p, _ = command(pos_p, heading, actions, self.arena, self.cfg.flight_height)
            move = self._evaders(pos_e, head_e, pos_p, captured, wander_heading, wander_left)
            head_e, wander_heading, wander_left = move.heading, move.wander_heading, move.wander_left
            if not self.evader_drones:
                virtual_e = move.pos
            setpoints = setpoint_p
            yaws = np.degrees(heading)
            if self.evader_drones:
                setpoints = np.concatenate([setpoint_p, np.c_[move.pos, np.full(E, self.cfg.flight_height)]])
                yaws = np.concatenate([yaws, np.degrees(move.heading)])
            decision = self._shield(pos, age, setpoints, policy_latency)
            c4 = time.perf_counter()
            if not outcome:
                outcome = self._apply(decision, yaws)
            c5 = time.perf_counter()
            lat.update(observe=c2 - c1, policy=c3 - c2, shield=c4 - c3, send=c5 - c4, tick=c5 - c0)
            self._log_tick(tick, steps, pos, yaw, decision, lat, virtual_e if not self.evader_drones else None)
            steps += 1
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

    def _reward(self, prev: np.ndarray, dist: np.ndarray, captured: np.ndarray, judged: Any) -> float:
        rw = self.task.task.reward
        approach = float(((prev - dist) * ~captured).sum()) / rw.approach_scale
        return float(
            rw.capture * judged.captured_now[0].sum() + rw.approach * approach + rw.collision * judged.collided[0].any()
        )

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

    # ----------------------------------------------------------------- safety
    def _shield(self, pos: np.ndarray, age: np.ndarray, setpoints: np.ndarray, policy_latency: float) -> ShieldDecision:
        battery, link = self.bridge.battery(), self.bridge.link_age()
        inp = ShieldInput(
            dt=self.dt,
            arena=(self.geometry.width, self.geometry.height),
            names=tuple(self.names),
            physical=self._physical(),
            pos=pos,
            vel=self._velocity(pos),
            pose_age=age,
            setpoint=setpoints,
            prev_setpoint=self.prev_setpoint,
            battery=np.array([battery.get(n, np.nan) for n in self.names]),
            link_age=np.array([link.get(n, np.inf) * self.clock.rate for n in self.names]),
            policy_latency=policy_latency,
            stop_requested=bool(self.stop),
        )
        return shield(inp, self.shield_cfg)

    def _velocity(self, pos: np.ndarray) -> np.ndarray:
        """Velocities (D, 3) from the last two ticks' poses (NaN where unknown), for the shield's look-ahead."""
        now, last = self.clock.now(), self._last_pose
        self._last_pose = (now, pos.copy())
        if last is None or now - last[0] <= 1e-6:
            return np.full_like(pos, np.nan)
        return (pos - last[1]) / (now - last[0])

    def _apply(self, decision: ShieldDecision, yaws: np.ndarray) -> str:
        """Send what the shield allows; return "shield" when it ends the episode (and the flight)."""
        act = decision.action
        stream = {
            n: (*decision.setpoint[i], float(yaws[i]))
            for i, n in enumerate(self.names)
            if act[i] in (Action.TRACK, Action.HOLD) and self.state[n] == "flying"
        }
        self.bridge.send_position(stream)
        for n, sp in stream.items():
            self.prev_setpoint[self.names.index(n)] = sp[:3]
        if (act >= Action.LAND).any():
            self.aborted = ",".join(sorted({e.rule for e in decision.events if e.rule != "speed"})) or "shield"
            self._escalate(decision)
            return "shield"
        return ""

    def _escalate(self, decision: ShieldDecision) -> None:
        """Drones the shield stops get an emergency stop; lost links are left alone; every other drone lands."""
        lost = set(decision.lost())
        stop = [n for i, n in enumerate(self.names) if decision.action[i] == Action.STOP and n not in lost]
        if stop:
            self.bridge.emergency_stop(stop)
            self._set_state(stop, "stopped")
        for n in lost:
            self._set_state([n], "lost")

    def _land_all(self) -> None:
        """Land every drone still in the air (high-level commander), watching the shield until they are down."""
        airborne = [n for n in self.names if self.state[n] in ("taking_off", "flying")]
        if airborne:
            duration = max(1.0, self.cfg.flight_height / 0.5)
            self.bridge.notify_stop(airborne)
            self.bridge.land(airborne, duration)
            self._set_state(airborne, "landing")
            self._transit(duration + 0.5, landing=True)
            self._set_state([n for n in airborne if self.state[n] == "landing"], "landed")

    def _transit(self, seconds: float, landing: bool = False) -> None:
        """Let the high-level commander fly for ``seconds``, logging each tick and watching the shield.

        The shield's rules on poses, links, batteries and signals still apply while the
        high-level commander flies (we stream no setpoints then): a LAND during takeoff or
        transit ends the flight (everything lands), a STOP stops; a landing ends early
        once every drone still flying is down.
        """
        self.prev_setpoint[:] = np.nan
        end = self.clock.now() + seconds
        while self.clock.now() < end:
            tick = self.ticks.wait()
            self._faults(tick)
            pos, yaw, age = self.measured()
            decision = self._shield(pos, age, pos, 0.0)  # no setpoints of ours: the high-level commander flies
            self._log_tick(tick, -1, pos, yaw, decision, {}, None)
            if decision.lost() or (decision.action == Action.STOP).any():
                self._escalate(decision)
            if not landing and (decision.action >= Action.LAND).any():
                self.aborted = self.aborted or ",".join(sorted({e.rule for e in decision.events})) or "shield"
                self._escalate(decision)
                return
            down = np.nan_to_num(pos[:, 2], nan=0.0) < 0.05
            if landing and all(down[i] for i, n in enumerate(self.names) if self.state[n] == "landing"):
                return

    # ---------------------------------------------------------------- logging
    def _faults(self, tick: float) -> None:
        for drone, note in self.faults.fire(tick - self.t0):
            for n in [drone] if drone else self.names:
                self.notes.setdefault(n, []).append(note)

    def _set_state(self, names: Sequence[str], state: str) -> None:
        for n in names:
            if self.state[n] not in ("stopped", "lost") or state in ("stopped", "lost"):
                self.state[n] = state

    def _log_tick(
        self,
        t: float,
        step: int,
        pos: np.ndarray,
        yaw: np.ndarray,
        decision: ShieldDecision,
        latency: dict[str, float],
        virtual_e: np.ndarray | None,
    ) -> None:
        events, self.notes = self.notes, {}
        for e in decision.events:
            events.setdefault(e.drone, []).append(e.rule)
        for i, n in enumerate(self.names):
            self.log.tick(
                t=t - self.t0,
                episode=self.episode,
                step=step,
                drone=n,
                role=self.roles[n],
                pos=pos[i],
                yaw=float(yaw[i]),
                setpoint=self.prev_setpoint[i],
                state=self.state[n],
                events=events.get(n, []),
                battery=float(self.bridge.battery().get(n, np.nan)),
                latency=latency,
            )
        if virtual_e is not None:
            for j, p in enumerate(virtual_e):
                self.log.tick(
                    t=t - self.t0,
                    episode=self.episode,
                    step=step,
                    drone=f"virtual_e{j}",
                    role="evader",
                    pos=np.array([p[0], p[1], self.cfg.flight_height]),
                    yaw=float("nan"),
                    setpoint=np.full(3, np.nan),
                    state="virtual",
                    events=[],
                    battery=float("nan"),
                    latency={},
                )


def _fill(measured: np.ndarray, fallback: np.ndarray) -> np.ndarray:
    """Measured positions, the fallback where a pose is unknown (the shield lands such drones anyway)."""
    out = np.where(np.isfinite(measured), measured, fallback)
    return np.nan_to_num(out, nan=0.0)
