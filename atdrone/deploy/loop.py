"""The 10 Hz deploy loop: poses -> observations -> policies -> reference -> shield -> bridge.

Every tick (0.1 s of the flight's clock):

1. the loop beats the bridge's dead-man heartbeat (a hung loop stops every drone);
2. the latest motion-capture pose of every drone (arena frame, timed on arrival);
3. observations through the project's one observation function
   (:func:`~atdrone.envs.observation.observe`), from the measured positions and the
   policies' own headings, as in training;
4. the policies, run in a worker thread: a step later than ``shield.policy_late`` holds
   every drone from outside the policy call, one late for ``shield.policy_stall`` lands
   them all;
5. the simulator's turn rule moves each pursuer's **reference**, a virtual unicycle at
   the trained speed (:func:`advance_reference`); evader drones' references move by the
   simulator's escape step; the drones get full-state setpoints on the reference with
   its velocity as feed-forward, at one constant physical yaw;
6. the shield (:mod:`atdrone.deploy.shield`), then the bridge's mailboxes.

Episodes end as in simulation (every evader captured, a collision by the task's
distances, the horizon: :func:`~atdrone.envs.rules.judge` on the measured poses) or
by the shield, which also ends the flight (``aborted`` holds the reason). A captured
evader drone lands. Between episodes the drones fly to a spawn draw whose drones are
clear of each other on straight lines scheduled by :func:`~atdrone.deploy.transit.plan_transit`,
streamed through the same shield. Tick overruns are counted; every stage's latency is
logged per tick.

:class:`Flight` holds the state and the tick's machinery (poses, links, the shield, the
setpoints, the log); its parts live beside it: :mod:`~atdrone.deploy.episode` (one
episode), :mod:`~atdrone.deploy.sequence` (between episodes) and
:mod:`~atdrone.deploy.landing` (landing, reactions, how each drone ended).
"""

from __future__ import annotations

import concurrent.futures
import math
import sys
from collections import deque
from collections.abc import Callable
from dataclasses import replace
from dataclasses import replace as dc_replace

import numpy as np

from atdrone.config import TaskConfig
from atdrone.deploy.bridge import Bridge
from atdrone.deploy.clock import Clock, Ticker
from atdrone.deploy.config import DeployConfig
from atdrone.deploy.episode import Episodes, advance_reference, capture_reach
from atdrone.deploy.faults import FaultClock, InjectedFault, StopRequest
from atdrone.deploy.flightlog import PAIR, FlightLog
from atdrone.deploy.landing import AIRBORNE, CLAMPS, cut_by_firmware
from atdrone.deploy.links import LinkHealth, LinkView
from atdrone.deploy.mocap import FROZEN_FRAMES, MocapSource, Pose
from atdrone.deploy.reactions import Reaction, Verdict
from atdrone.deploy.sequence import COLUMN_CLEAR
from atdrone.deploy.shield import (
    Action,
    Obstacles,
    ShieldConfig,
    ShieldDecision,
    ShieldInput,
    shield,
)
from atdrone.deploy.team import PolicyRunner, Team
from atdrone.envs.evaders import EscapeParams
from atdrone.envs.geometry import Geometry
from atdrone.envs.observation import Arena, Poses, observe
from atdrone.envs.rules import pursuer_pairs

__all__ = ["COLUMN_CLEAR", "FaultClock", "Flight", "InjectedFault", "StopRequest", "Team", "advance_reference"]

GROW_CAP = 1.0  # m: the most a drone without a valid pose is grown by (it lands or is stopped long before)
# s a thread holds the interpreter before another gets it: 1 ms (Python's 5 ms) in flight, so that the heartbeat
# and the loop wait less behind cflib's, the motion capture's and the sender's threads on a busy host
SWITCH = 0.001


class Flight(Episodes):
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
        on_episode: Callable[[], None] | None = None,
    ) -> None:
        self.cfg, self.task, self.team = cfg, task, team
        self.progress = progress or (lambda _message: None)
        self.on_episode = on_episode or (lambda: None)
        self.bridge, self.mocap, self.clock, self.log = bridge, mocap, clock, log
        self.faults = faults or FaultClock()
        self.stop = StopRequest() if stop is None else stop
        self.arena = Arena.from_config(task)
        self.geometry: Geometry = self.arena.geometry
        self.obstacles = Obstacles(
            np.c_[self.geometry.box_center, self.geometry.box_half].reshape(-1, 4),
            np.c_[self.geometry.disc_center, self.geometry.disc_radius].reshape(-1, 3),
        )
        self.dt = task.dt
        self.shield_cfg: ShieldConfig = cfg.shield
        learners, partners = cfg.role_names("learner"), cfg.role_names("partner")
        self.pursuers = learners + partners  # pursuer slot order: learners, then partners
        self.evader_drones = cfg.role_names("evader")
        self.flyers = self.pursuers + self.evader_drones  # the drones that take off at the start
        self.names = self.flyers + [b.name for b in cfg.backups]  # every physical drone, backups last
        self.learner_slots = np.arange(len(learners))
        self.partner_slots = np.arange(len(learners), len(self.pursuers))
        self.roles = {d.name: d.role for d in cfg.fleet()}
        self.bodies = {d.name: d.rigid_body for d in cfg.fleet()}
        self.pairs = pursuer_pairs(len(self.pursuers))  # the pursuer pairs a judgement's hit_pairs are of
        self.rng = np.random.default_rng(cfg.seed)
        self.escape = EscapeParams()
        self.horizon = cfg.horizon or task.task.task_horizon
        # the task as judged: with evader drones a capture counts at ``capture_reach`` (see capture_reach)
        self.judged_task = task
        if self.evader_drones:
            reach = capture_reach(task.task.capture_range, cfg.shield)
            self.judged_task = dc_replace(task, task=dc_replace(task.task, capture_range=reach))
        self.state = dict.fromkeys(self.names, "idle")
        self.ticks = Ticker(clock, self.dt)
        self.t0 = clock.now()
        D = len(self.names)
        self.prev_setpoint = np.full((D, 3), np.nan)
        self.hold_at = np.full((D, 3), np.nan)
        self._last_pose: tuple[float, np.ndarray] | None = None  # (clock time, positions) for the velocity estimate
        self.episode = -1
        self.episodes_flown = 0
        self.aborted = ""  # why the flight ended early ("" while it has not)
        self.error: BaseException | None = None
        self.notes: dict[str, list[str]] = {}  # fault notes for the next logged tick, per drone
        self.policy = PolicyRunner(team, clock, self.faults)
        self._worker = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="transit")
        self.link_health = LinkHealth(self.names, clock.rate, cfg.shield.link_timeout)
        self.links = LinkView(np.zeros(D), 0.0)
        self.speed = np.full(D, np.nan)  # measured speed (m/s) per drone, NaN unknown
        self.reaction = Verdict(Reaction.NONE, (), ())  # the most severe reaction so far
        self.landing_from: dict[str, np.ndarray] = {}  # where each landing began (its landing column)
        self.cut: dict[str, tuple[float, str]] = {}  # drones whose motors were cut: height, state then
        self.last_seen: dict[str, float] = {}  # last measured height per drone
        self.recent: dict[str, deque[tuple[float, str, int]]] = {}  # per drone, its last ticks: height, state, pauses
        self.aloft: dict[str, float] = {}  # per drone taking off or flying, the top of that stretch in the air
        self.ended: dict[str, str] = {}  # how each drone ended (after run)
        self.valid_pos = np.full((D, 3), np.nan)  # each drone's last valid (known, fresh) position
        self.valid_t = np.full(D, -np.inf)  # and when it was measured (clock)
        self.off_since = np.full(D, np.inf)  # clock time each drone's onboard estimate left its pose (inf: it agrees)
        self.grow = np.zeros(D)  # m each drone's separation ellipsoid was grown by last tick (no valid pose)
        self.tick_t = self.t0
        self._pause_caught = -math.inf  # the tick whose host pause was last counted
        self._init_backups()

    # ------------------------------------------------------------------ poses
    def measured(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (D, 3) (NaN unknown), yaws (D,) and pose ages (D,) of every physical drone."""
        latest: dict[str, Pose] = self.mocap.latest()
        now = self.clock.now()
        pos = np.full((len(self.names), 3), np.nan)
        yaw = np.full(len(self.names), np.nan)
        age = np.full(len(self.names), np.inf)
        grace = self._grace()
        for i, name in enumerate(self.names):
            pose = latest.get(self.bodies[name])
            if pose is None:
                continue
            pos[i], yaw[i], age[i] = pose.pos, pose.yaw, max(0.0, now - pose.t)
            # in the air a body never holds its pose to NOISE_FLOOR for FROZEN_FRAMES frames, hovering included (the
            # drone sways by millimetres, the cameras' noise is tenths of one): frames arrive, the pose is as old
            if pose.still >= FROZEN_FRAMES and self.state[name] in AIRBORNE:
                age[i] = max(age[i], now - pose.moved_t)
            age[i] = min(age[i], grace)
        return pos, yaw, age

    def _grace(self) -> float:
        """Clock seconds since the loop last resumed from a host pause: no pose or link is older than that."""
        return max((self.link_health.wall() - self.link_health.resumed) * self.clock.rate, 0.0)

    def _catch_pause(self) -> None:
        """A host pause inside this tick (after its wake-up, before its shield: the tick is now more than a period
        past its time) counts as one, as a late wake-up does: ages count again from now. Once per tick."""
        late = self.clock.now() - self.tick_t
        if self._pause_caught != self.tick_t and self.link_health.host_paused(late, self.dt):
            self._pause_caught = self.tick_t
            self.notes.setdefault("", []).append("host_pause")

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
        """Take off, fly ``cfg.episodes`` episodes (until the shield or an error ends the flight), land.

        Never raises for what happens in flight: an exception is kept in :attr:`error`, its
        one-line reason in :attr:`aborted`, and every drone lands first.
        """
        # no collection in flight: the job made its one full collection before the links opened and froze the
        # heap (atdrone.deploy.job.collector_paused)
        switch = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH)
        # fresh poses before the first tick (the preflight's checks held the interpreter a while)
        fresh_by = self.clock.now() + 2.0
        while self.clock.now() < fresh_by and not np.all(self.measured()[2] < self.shield_cfg.stale_pose / 2):
            self.clock.sleep(0.02)
        try:
            self.bridge.start_heartbeat(lambda: self.stop.urgent)
            self._takeoff()
            for episode in range(self.cfg.episodes):
                if self.aborted:
                    break
                self.episode = episode
                self._fly_episode()
                if not self.aborted or self.episode_done:
                    self.episodes_flown += 1
                self._holding_while(self.on_episode)
        except BaseException as exc:
            self.error = exc
            self.aborted = self.aborted or f"{type(exc).__name__}: {exc}"
        finally:
            try:
                self._land_all()
                self._settle()  # heartbeat and land commands until every drone is confirmed down (or the limit)
            except Exception as exc:  # the loop itself is broken: land through the bridge alone
                airborne = [n for n in self.names if self.state[n] in (*AIRBORNE, "lost")]
                self.bridge.land(airborne, 2.0)
                self.bridge.notify_stop(airborne)
                end = self.clock.now() + 2.0 + 2.5
                while self.clock.now() < end:  # the heartbeat goes on while they land
                    self.bridge.beat()
                    self.clock.sleep(self.dt)
                self.aborted = self.aborted or f"{type(exc).__name__}: {exc}"
            pos, yaw, age = self.measured()  # the last row: where every drone ended, in its final state
            self._log_tick(self.clock.now(), -1, pos, yaw, self._shield(pos, age, pos, in_tick=False), {}, None)
            self.ended = self.endings()
            self.bridge.stop_heartbeat()
            self.policy.close()
            self._worker.shutdown(wait=False, cancel_futures=True)
            sys.setswitchinterval(switch)
        if self.stop and not self.aborted:
            self.aborted = f"stop requested ({self.stop.signal})"
        down = {n: e for n, e in self.ended.items() if e != "landed"}
        if down:  # the exit line names every drone that did not land
            what = "; ".join(f"{n} {e}" for n, e in down.items())
            self.aborted = f"{self.aborted}; not landed: {what}" if self.aborted else f"not landed: {what}"

    episode_done = False  # the current episode reached its own outcome (set per episode)

    def _takeoff(self) -> None:
        self.bridge.arm(self.flyers)  # backups wait on the floor, disarmed
        self.landing_from.clear()
        self.bridge.takeoff(self.flyers, self.cfg.flight_height, self.cfg.takeoff_duration)
        self._set_state(self.flyers, "taking_off")
        self._watch(self.cfg.takeoff_duration + 0.5)
        self._set_state([n for n in self.names if self.state[n] == "taking_off"], "flying")
        self.prev_setpoint[:] = np.nan  # the first transit tick takes over from the planner, through the shield

    # ----------------------------------------------------------------- ticks
    def _begin_tick(self, step: int = -1) -> float:
        """Wait for the next tick (one flying ``step`` of the episode; -1: none), beat the heartbeat, fire due
        faults; the tick's clock time."""
        tick = self.ticks.wait()
        self.tick_t = tick  # the tick's clock time, for what happens in it (the log's rows carry it)
        self.bridge.beat()
        if self.link_health.host_paused(self.ticks.late_by, self.dt):
            self._pause_caught = tick
            self.notes.setdefault("", []).append("host_pause")
        for drone, note in self.faults.fire(tick - self.t0, self.episode, step):
            for n in [drone] if drone else self.names:
                self.notes.setdefault(n, []).append(note)
        if self.faults.hang:
            hang, self.faults.hang = self.faults.hang, 0.0
            self.clock.sleep(hang)  # the loop hangs: no beat, no setpoint (the dead-man heartbeat stops)
        if self.faults.raise_now:
            self.faults.raise_now = False
            raise InjectedFault("an exception injected into the loop (fault 'exception')")
        return tick

    # ----------------------------------------------------------------- safety
    def _shield(
        self,
        pos: np.ndarray,
        age: np.ndarray,
        setpoints: np.ndarray,
        vel: np.ndarray | None = None,
        policy_late: float = 0.0,
        in_tick: bool = True,
    ) -> ShieldDecision:
        if in_tick:  # a pause since the poses were measured must not read as stale poses or silent links
            self._catch_pause()
            age = np.minimum(age, self._grace())
        battery = self.bridge.battery()
        self.links = self.link_health.update(self.bridge.link_age(), self.bridge.sender_age())
        bits = self.bridge.supervisor()
        airborne = self._airborne()
        physical = airborne | np.array([self.state[n] == "lost" for n in self.names])
        now = self.clock.now()
        valid = np.isfinite(pos).all(1) & (age <= self.shield_cfg.stale_pose)
        self.valid_pos[valid], self.valid_t[valid] = pos[valid], now
        grow = np.where(valid, 0.0, np.minimum(self.shield_cfg.max_speed * (now - self.valid_t), GROW_CAP))
        inp = ShieldInput(
            dt=self.dt,
            arena=(self.geometry.width, self.geometry.height),
            names=tuple(self.names),
            physical=physical,
            pos=pos,
            vel=self._velocity(pos, age),
            pose_age=age,
            setpoint=setpoints,
            prev_setpoint=self.prev_setpoint,
            battery=np.array([battery.get(n, np.nan) if airborne[i] else np.inf for i, n in enumerate(self.names)]),
            link_age=self.links.silence,
            links_silent=self.links.all_silent,
            policy_latency=policy_late,
            stop_requested=bool(self.stop),
            setpoint_vel=vel,
            hold_at=self.hold_at,
            locked=np.array([cut_by_firmware(bits.get(n, 0)) and self.state[n] in AIRBORNE for n in self.names]),
            obstacles=self.obstacles,
            last_pos=self.valid_pos,
            grow=np.where(physical, grow, 0.0),
            estimate_off=self._estimate_off(pos, valid & airborne, now),
            alone=self._alone(),
        )
        self.grow = inp.grow if inp.grow is not None else np.zeros(len(self.names))
        return shield(inp, self.shield_cfg)

    def _estimate_off(self, pos: np.ndarray, judged: np.ndarray, now: float) -> np.ndarray:
        """Per drone, how long (clock s) its logged onboard estimate has been more than the shield's
        ``estimate_tolerance`` from its fresh pose (0: it agrees, or it is not judged: not airborne, no pose or no
        estimate). A drone whose link is silent past the link timeout is not judged: its last logged estimate is
        stale, and the silence is the link rule's. Like link and pose ages, the time off counts from the loop's last
        resume after a host pause."""
        judged = judged & (np.asarray(self.links.silence) <= self.shield_cfg.link_timeout)
        estimates = self.bridge.estimates()
        est = np.array([estimates.get(n, (np.nan,) * 4)[:3] for n in self.names], dtype=np.float64)
        apart = np.linalg.norm(est - pos, axis=1)
        off = judged & np.isfinite(apart) & (apart > self.shield_cfg.estimate_tolerance)
        self.off_since = np.where(off, np.where(np.isfinite(self.off_since), self.off_since, now), np.inf)
        return np.where(off, np.minimum(now - self.off_since, self._grace()), 0.0)

    def _velocity(self, pos: np.ndarray, age: np.ndarray) -> np.ndarray:
        """Velocities (D, 3) from the last two ticks' fresh poses (NaN where unknown), for the shield's
        look-ahead; their speeds kept in :attr:`speed`."""
        now, last = self.clock.now(), self._last_pose
        self._last_pose = (now, pos.copy())
        vel = np.full_like(pos, np.nan) if last is None or now - last[0] <= 1e-6 else (pos - last[1]) / (now - last[0])
        vel[~(age <= self.shield_cfg.stale_pose)] = np.nan
        self.speed = np.linalg.norm(vel, axis=1)
        return vel

    def _apply(self, decision: ShieldDecision) -> bool:
        """Post what the shield allows and take its reactions; True when it ends the episode (and the flight)."""
        act = decision.action
        vel = decision.velocity if decision.velocity is not None else np.zeros_like(decision.setpoint)
        stream = {
            n: (decision.setpoint[i], vel[i], np.zeros(3))
            for i, n in enumerate(self.names)
            if act[i] in (Action.TRACK, Action.HOLD) and self.state[n] == "flying"
        }
        self.bridge.post_setpoints(stream)
        for n, sp in stream.items():
            i = self.names.index(n)
            self.prev_setpoint[i] = sp[0]
        if decision.hold_at is not None:
            self.hold_at = decision.hold_at.copy()
        pos = self._last_pose[1] if self._last_pose is not None else np.full((len(self.names), 3), np.nan)
        ended = self._react(decision, pos).reaction >= Reaction.LAND_ONE
        self._call_lost()
        return ended

    def _hold_tick(self, first: Callable[[], None] | None = None) -> bool:
        """One tick holding every streaming drone where it is (latched, zero velocity, through the shield);
        False when the shield ended the flight. ``first`` runs at the tick's start: what it does (its notes, the
        times it records) is this tick's."""
        tick = self._begin_tick()
        if first is not None:
            first()
        pos, yaw, age = self.measured()
        here = np.where(np.isfinite(self.hold_at).all(1)[:, None], self.hold_at, pos)
        decision = self._shield(pos, age, here, np.zeros_like(pos))  # clamped into the fence, zero velocity
        decision = replace(decision, events=tuple(e for e in decision.events if e.rule not in CLAMPS))
        ended = self._apply(decision)
        track = decision.action == Action.TRACK
        self.hold_at[track] = decision.setpoint[track]  # latched: the next hold tick sends the same point
        self._touchdown(pos)
        self._log_tick(tick, -1, pos, yaw, decision, {}, None)
        return not ended

    # ---------------------------------------------------------------- logging
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
        everyone = events.pop("", [])
        for e in decision.events:
            events.setdefault(e.drone, []).append(e.rule)
        for a, b in decision.pairs if decision.pairs is not None else ():  # whom the separation rule held it with
            events.setdefault(decision.names[a], []).append(f"{PAIR}{decision.names[b]}")
            events.setdefault(decision.names[b], []).append(f"{PAIR}{decision.names[a]}")
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
                events=everyone + events.get(n, []),
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
