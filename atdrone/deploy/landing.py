"""Landing and the end of a flight: land commands, reactions to faults, confirmation, how each drone ended.

:class:`Landing` is the part of :class:`~atdrone.deploy.loop.Flight` that brings drones
down and says how they came down:

- a drone is handed to the onboard planner to land (the land command, then
  ``notify_setpoint_stop``); a drone whose link is judged lost gets that command again on
  every tick until it is heard again (then it lands under watch) or the flight is over;
- the most severe reaction of a tick is taken (:mod:`atdrone.deploy.reactions`): drones
  the shield stops get the emergency stop, except a landing drone still in its landing
  column; a drone whose supervisor reports itself locked (its firmware cut the motors) is
  recorded as cut, with the height it was last measured at;
- a drone is **landed** only when its firmware confirms it: the supervisor's flying bit
  off and its planner finished or idle, heard over a live link, and the drone measured
  still (or not measured); a height near the floor is not enough (it is also true at the
  start of a takeoff);
- after any end of a flight, whatever the reason, :meth:`Landing._settle` keeps the
  ticks (so the dead-man heartbeat) and the land commands going until every drone is
  landed, cut or the hard limit passes; :meth:`Landing.endings` then says per drone
  ``landed``, ``cut in the air at Z m (STATE)``, ``lost (...)`` or ``not confirmed
  landed (...)``.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

from atdrone.deploy.bridge import Bridge
from atdrone.deploy.clock import Clock
from atdrone.deploy.config import DeployConfig
from atdrone.deploy.crtp import BIT_CRASHED, BIT_HL_DISABLED, BIT_HL_FINISHED, BIT_IS_FLYING, BIT_LOCKED, BIT_TUMBLED
from atdrone.deploy.hooks import FlightHooks
from atdrone.deploy.links import LinkHealth, LinkView
from atdrone.deploy.reactions import Reaction, Verdict, drops, spare_landing, verdict
from atdrone.deploy.shield import Action, ShieldConfig, ShieldDecision, ellipsoid_distance

AIRBORNE = ("taking_off", "flying", "landing")
CLAMPS = ("speed", "step", "altitude", "geofence", "obstacle", "nan_setpoint")  # rules on our own setpoints
STILL = 0.1  # m/s: a landed drone measured slower than this
LANDED_CONFIRM = 2.5  # s: the supervisor reports a drone flying until its motors idled for 2 s
SETTLE_EXTRA = 3.0  # s past a landing and its confirmation before the flight gives up waiting (the hard limit)
TOUCH = 1.0  # scaled distance: two ellipsoids touching
RECENT = 50  # ticks of heights kept (5 s of the drones' clock): a paused host's cut is reported late
CUT_BITS = (1 << BIT_LOCKED) | (1 << BIT_TUMBLED) | (1 << BIT_CRASHED)


def cut_by_firmware(bits: int) -> bool:
    """The supervisor reports the drone locked, tumbled or crashed: its motors are off until a reboot."""
    return bool(bits & CUT_BITS)


def confirmed_down(bits: int, speed: float) -> bool:
    """The firmware says the drone is on the ground: not flying, its planner finished or idle, not cut; and it
    is measured still (``speed`` NaN: not measured)."""
    planner_done = bool(bits >> BIT_HL_FINISHED & 1 or bits >> BIT_HL_DISABLED & 1)
    return not bits >> BIT_IS_FLYING & 1 and planner_done and not cut_by_firmware(bits) and not speed > STILL


class Landing(FlightHooks):
    """Landing, reactions and the end of a flight (see the module docstring)."""

    cfg: DeployConfig
    bridge: Bridge
    clock: Clock
    shield_cfg: ShieldConfig
    names: list[str]
    state: dict[str, str]
    aborted: str
    progress: Callable[[str], None]
    links: LinkView
    speed: np.ndarray
    reaction: Verdict
    landing_from: dict[str, np.ndarray]
    cut: dict[str, tuple[float, str]]
    last_seen: dict[str, float]
    recent: dict[str, deque[tuple[float, str, int]]]
    aloft: dict[str, float]
    link_health: LinkHealth
    grow: np.ndarray
    hold_at: np.ndarray
    prev_setpoint: np.ndarray
    notes: dict[str, list[str]]

    def _alone(self) -> np.ndarray:
        """(D,) the drones a low battery or lost link drops alone: none, unless the flight's backups part (before
        this one in a flight's bases) says otherwise."""
        return np.zeros(len(self.names), dtype=bool)

    def _drop(self, name: str, why: str) -> None:
        """Drop ``name`` alone (the backups' part of a flight does; with no drone alone it is never called)."""
        raise NotImplementedError

    def _airborne(self) -> np.ndarray:
        return np.array([self.state[n] in AIRBORNE for n in self.names])

    def _set_state(self, names: Sequence[str], state: str) -> None:
        for n in names:
            if self.state[n] not in ("stopped", "lost") or state in ("stopped", "lost", "landing"):
                self.state[n] = state

    def _landing_time(self) -> float:
        """Seconds the planner takes to land from the flight height."""
        return max(2.0, self.cfg.flight_height / 0.25)

    # ------------------------------------------------------------ commands
    def _land(self, names: Sequence[str]) -> None:
        """Hand the drones to the high-level commander to land: the land command first, then notify."""
        names = [n for n in names if self.state[n] in ("taking_off", "flying")]
        if names:
            self.bridge.land(names, self._landing_time())
            self.bridge.notify_stop(names)
            pos = self.measured()[0]
            for n in names:
                self.landing_from[n] = pos[self.names.index(n)].copy()
            self._set_state(names, "landing")

    def _call_lost(self) -> None:
        """The land command again to every drone judged lost (it reaches the drone once its link carries)."""
        lost = [n for n in self.names if self.state[n] == "lost"]
        if lost:
            self.bridge.land(lost, self._landing_time())
            self.bridge.notify_stop(lost)

    # ------------------------------------------------------------ reactions
    def _react(self, decision: ShieldDecision, pos: np.ndarray) -> Verdict:
        """Take this tick's reactions (lost links, stops, firmware cuts); the most severe one, remembered and
        printed when it is the worst so far."""
        bits = self.bridge.supervisor()
        for i, n in enumerate(self.names):
            if np.isfinite(pos[i, 2]):
                self.last_seen[n] = float(pos[i, 2])
                entry = (float(pos[i, 2]), self.state[n], self.link_health.pauses)
                self.recent.setdefault(n, deque(maxlen=RECENT)).append(entry)
                if self.state[n] in ("taking_off", "flying"):  # the top of its current stretch in the air
                    self.aloft[n] = max(self.aloft.get(n, 0.0), entry[0])
                else:
                    self.aloft.pop(n, None)
            fresh = self.links.silence[i] <= self.shield_cfg.link_timeout
            if fresh and cut_by_firmware(bits.get(n, 0)) and n not in self.cut and self.state[n] != "idle":
                self.cut[n] = self._cut_at(n)
                self.state[n] = "stopped"
            if decision.action[i] == Action.LOST and self.state[n] in (*AIRBORNE, "landed"):
                if self.state[n] != "landed" or not confirmed_down(bits.get(n, 0), float(self.speed[i])):
                    self.state[n] = "lost"
            elif self.state[n] == "lost" and decision.action[i] != Action.LOST:
                # heard again: it had the land command on every tick; it lands under watch from here
                self.bridge.land([n], self._landing_time())
                self.bridge.notify_stop([n])
                self.state[n] = "landing"
        dropped = drops(decision, self._alone())  # a partner's own battery or lost link: it alone leaves the flight
        for n in dropped:
            self._drop(n, dropped[n])
        stop = [n for i, n in enumerate(self.names) if decision.action[i] == Action.STOP and self.state[n] in AIRBORNE]
        where = {n: pos[i] for i, n in enumerate(self.names)}
        stop = spare_landing(stop, self.state, where, self.landing_from)
        if stop:
            self.bridge.emergency_stop(stop)
            for n in stop:  # one its firmware locked already (the shield's `locked`, heard before its link is
                # judged fresh again) fell before the report: where it was cut, as for a cut seen on a fresh link
                if n not in self.cut:
                    locked = cut_by_firmware(bits.get(n, 0))
                    self.cut[n] = self._cut_at(n) if locked else (self.last_seen.get(n, float("nan")), self.state[n])
            self._set_state(stop, "stopped")
        # the reaction taken: a landing drone spared the stop is landing
        taken = decision.action.copy()
        for i, n in enumerate(self.names):
            if taken[i] == Action.STOP and n not in stop and self.state[n] != "stopped":
                taken[i] = Action.LAND
            if n in dropped:  # landing (or lost) alone: nothing for the rest of the flight to react to
                taken[i] = Action.TRACK
        scope = self._airborne() | np.array([self.state[n] in ("lost", "stopped") for n in self.names])
        now = verdict(replace(decision, action=taken), scope)
        if now.reaction > self.reaction.reaction:
            self.reaction = now
            if now.reaction >= Reaction.LAND_ONE:
                self.progress(f"[deploy] {now.line()}")
                if not self.aborted or self.aborted.startswith("shield:"):
                    self.aborted = "shield: " + (",".join(now.rules) or "land")
        return now

    # ------------------------------------------------------------ separation under the planner
    def _touching(self, decision: ShieldDecision, pos: np.ndarray) -> set[int]:
        """Drones of the pairs the separation rule held whose ellipsoids touch now (both with valid poses): under
        the planner, only that is acted on (the planner flies straight up and down: nearer pairs stay as near)."""
        pairs = decision.pairs if decision.pairs is not None else np.zeros((0, 2), dtype=int)
        r, h = self.shield_cfg.drone_radius, self.shield_cfg.drone_half_height
        return {
            int(k)
            for a, b in pairs
            if self.grow[a] == 0 and self.grow[b] == 0 and ellipsoid_distance(pos[b] - pos[a], r, h) < TOUCH
            for k in (a, b)
        }

    def _separate_planned(self, decision: ShieldDecision, pos: np.ndarray) -> list[str]:
        """Drones under the onboard planner (taking off, landing) whose ellipsoids touch another's (both with
        valid poses) are taken over: a hold setpoint (pushed apart) stops their planner; they land again once
        clear. A grown obstacle (a drone without a valid pose) never stops a landing. The drones taken over."""
        held = self._touching(decision, pos)
        take = [
            self.names[k]
            for k in sorted(held)
            if self.state[self.names[k]] in ("taking_off", "landing") and decision.action[k] == Action.HOLD
        ]
        if take:
            zero = np.zeros(3)
            stream = {n: (decision.setpoint[self.names.index(n)], zero, zero) for n in take}
            self.bridge.post_setpoints(stream)
            for n, (sp, _, _) in stream.items():
                k = self.names.index(n)
                self.prev_setpoint[k] = self.hold_at[k] = sp
                self.notes.setdefault(n, []).append("separation_takeover")
            self._set_state(take, "flying")
        return take

    def _reland(self, decision: ShieldDecision, pos: np.ndarray, land: bool = True) -> None:
        """Drones taken over for separation (streaming, state ``flying``): those still touching hold, those
        clear again land (``land``) or hold where they are (a takeoff: the flight takes them over after it)."""
        busy = {self.names[k] for k in self._touching(decision, pos)}
        flying = [n for n in self.names if self.state[n] == "flying"]
        if not flying:
            return
        clear = [n for n in flying if n not in busy] if land else []
        held = {n: (decision.setpoint[self.names.index(n)], np.zeros(3), np.zeros(3)) for n in flying if n not in clear}
        held = {n: v for n, v in held.items() if np.isfinite(v[0]).all()}
        self.bridge.post_setpoints(held)
        self._land(clear)

    def _cut_at(self, n: str) -> tuple[float, str]:
        """Where a drone the firmware cut was, and its state then: the supervisor's report arrives a tick or two
        after the cut (a drone falls 0.5 m in 0.3 s), so two ticks back; after a pause of the host (in the last
        :data:`RECENT` ticks), the tick before the pause, when the keep-alives last flowed. A drone taking off or
        flying found on the floor fell before the report came (a silent link can hold the report back for
        longer than :data:`RECENT` ticks): the top of its last stretch in the air."""
        seen = list(self.recent.get(n, ()))
        if not seen:
            return self.last_seen.get(n, float("nan")), self.state[n]
        paused = [k for k in range(1, len(seen)) if seen[k][2] != seen[k - 1][2]]
        z, state, _ = seen[paused[-1] - 1] if paused else seen[max(0, len(seen) - 3)]
        if state in ("taking_off", "flying") and z < 0.05:  # it fell before the report came (or never rose)
            z = max(z, self.aloft.get(n, z))  # the top of its last stretch in the air, however long ago
        return z, state

    # ------------------------------------------------------------ landing
    def _poses_fresh(self) -> bool:
        """Every airborne drone has a fresh pose (holding it in place means something)."""
        _, _, age = self.measured()
        air = self._airborne()
        return bool((age[air] <= self.shield_cfg.stale_pose).all())

    def _brake(self, seconds: float = 0.6) -> None:
        """Hold every streaming drone for ``seconds``: a drone handed to the planner at speed would swing back
        to where the land command found it."""
        end = self.clock.now() + seconds
        while self.clock.now() < end and any(self.state[n] == "flying" for n in self.names):
            if not self._hold_tick():
                return

    def _land_all(self) -> None:
        """Brake (when every pose is fresh), then land every drone still in the air, watching the shield (and
        feeding the heartbeat) until they are down."""
        if self._poses_fresh():
            self._brake()
        self._land([n for n in self.names if self.state[n] in AIRBORNE])
        if any(self.state[n] == "landing" for n in self.names):
            self._watch(self._landing_time() + 1.0, landing=True)

    def _watch(self, seconds: float, landing: bool = False) -> None:
        """Let the high-level commander fly ``seconds`` (takeoff, landing), logging ticks and watching the shield.

        The shield's rules on poses, links, batteries and signals still apply: during a
        takeoff a landing reaction ends the flight (everything lands); drones that are
        confirmed down become ``landed``; a landing ends early once every landing drone is down.
        """
        end = self.clock.now() + seconds
        while self.clock.now() < end:
            tick = self._begin_tick()
            pos, yaw, age = self.measured()
            decision = self._shield(pos, age, pos)  # no setpoints of ours: the high-level commander flies
            decision = replace(decision, events=tuple(e for e in decision.events if e.rule not in CLAMPS))
            reaction = self._react(decision, pos)
            self._separate_planned(decision, pos)
            self._reland(decision, pos, land=landing)
            self._call_lost()
            self._touchdown(pos)
            # logged after the reactions, as every tick is: a drop's note is on the row of the tick its record names
            self._log_tick(tick, -1, pos, yaw, decision, {}, None)
            if not landing and reaction.reaction >= Reaction.LAND_ONE:
                return
            if landing and not any(self.state[n] == "landing" for n in self.names):
                return

    def _touchdown(self, pos: np.ndarray) -> None:
        """Landing drones the firmware confirms down (over a live link) are ``landed``."""
        bits = self.bridge.supervisor()
        down = [
            n
            for i, n in enumerate(self.names)
            if self.state[n] == "landing"
            and self.links.silence[i] <= self.shield_cfg.link_timeout
            and confirmed_down(bits.get(n, 0), float(self.speed[i]))
        ]
        self._set_state(down, "landed")

    def _settle(self) -> None:
        """After any end: ticks (the heartbeat) and land commands until every drone is landed, cut or the hard
        limit (a landing, its confirmation and :data:`SETTLE_EXTRA`) passes."""
        end = self.clock.now() + self._landing_time() + LANDED_CONFIRM + SETTLE_EXTRA
        while self.clock.now() < end:
            if all(self.state[n] in ("idle", "landed", "stopped") for n in self.names):
                return
            tick = self._begin_tick()
            pos, yaw, age = self.measured()
            decision = self._shield(pos, age, pos)
            decision = replace(decision, events=tuple(e for e in decision.events if e.rule not in CLAMPS))
            self._react(decision, pos)
            self._separate_planned(decision, pos)
            self._reland(decision, pos)
            self._land([n for n in self.names if self.state[n] == "taking_off"])
            self._call_lost()
            self._touchdown(pos)
            self._log_tick(tick, -1, pos, yaw, decision, {}, None)

    def endings(self) -> dict[str, str]:
        """How each drone ended (see the module docstring)."""
        out = {}
        for n in self.names:
            z = self.last_seen.get(n, float("nan"))
            if n in self.cut:
                at, was = self.cut[n]
                if not at < 0.05:
                    out[n] = f"cut in the air at {at:.2f} m ({was})"
                else:  # on the floor already: a landing drone locked by its firmware (the keep-alive stopped) is down
                    out[n] = "landed" if was in ("landing", "landed") else f"stopped on the ground ({was})"
            elif self.state[n] in ("landed", "idle"):
                out[n] = "landed"
            elif self.state[n] == "lost":
                out[n] = f"lost (last seen at {z:.2f} m)"
            else:
                out[n] = f"not confirmed landed ({self.state[n]}, last seen at {z:.2f} m)"
        return out
