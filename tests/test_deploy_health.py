"""Link health, fault reactions and landing confirmation: the pure pieces of a flight's end, by hand."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from atdrone.deploy import crtp
from atdrone.deploy.clock import Ticker
from atdrone.deploy.faults import FaultClock
from atdrone.deploy.landing import RECENT, confirmed_down, cut_by_firmware
from atdrone.deploy.links import LinkHealth
from atdrone.deploy.reactions import LANDING_COLUMN, Reaction, Verdict, spare_landing, verdict
from atdrone.deploy.shield import Action, ShieldConfig, ShieldInput, shield

CFG = ShieldConfig()
NAMES = ("a", "b", "c")


class Wall:
    """A wall clock the test moves."""

    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def tick(pos: Any, **changes: Any) -> ShieldInput:
    pos = np.asarray(pos, dtype=float)
    D = len(pos)
    base = ShieldInput(
        dt=0.1,
        arena=(3.6, 5.0),
        names=NAMES[:D],
        physical=np.ones(D, dtype=bool),
        pos=pos,
        vel=np.zeros((D, 3)),
        pose_age=np.full(D, 0.01),
        setpoint=pos.copy(),
        prev_setpoint=pos.copy(),
        battery=np.full(D, 4.0),
        link_age=np.full(D, 0.05),
        policy_latency=0.0,
        stop_requested=False,
    )
    return replace(base, **changes)


APART = [[1.0, 1.0, 0.5], [2.5, 1.0, 0.5], [1.0, 4.0, 0.5]]


# ---------------------------------------------------------------- link health
def test_a_host_pause_is_not_silence_and_one_quiet_link_is_a_lost_drone() -> None:
    wall = Wall()
    links = LinkHealth(NAMES, rate=4.0, timeout=0.5, wall=wall)
    # 0.3 wall s without a packet from anyone (1.2 clock s) because the process was paused: nobody is silent
    assert links.host_paused(late_by=1.2, period=0.1)
    wall.t += 0.01
    view = links.update({"a": 0.3, "b": 0.3, "c": 0.3})
    assert (view.silence < 0.5).all() and view.all_silent == 0
    # later, one link alone stays quiet: that drone is silent, nobody else
    wall.t += 1.0
    view = links.update({"a": 0.02, "b": 0.5, "c": 0.02})
    assert list(view.silence > 0.5) == [False, True, False] and view.all_silent == 0
    # every link quiet together: one stall of the ground station (the shortest silence)
    view = links.update({"a": 0.2, "b": 0.5, "c": 0.3})
    assert (view.silence > 0.5).all() and view.all_silent == 0.8
    # a blocked sender reaches nobody either
    view = links.update({"a": 0.0, "b": 0.0, "c": 0.0}, sender_age=0.9)
    assert view.all_silent == 0.9


class OversleepingClock:
    """A clock whose next sleep lasts ``extra`` seconds longer than asked (the process stopped while asleep)."""

    rate = 1.0

    def __init__(self) -> None:
        self.t, self.extra = 0.0, 0.0

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += max(seconds, 0.0) + self.extra
        self.extra = 0.0

    def sleep_until(self, t: float) -> None:
        self.sleep(t - self.t)


def test_a_tick_that_wakes_late_reports_how_late() -> None:
    """A pause while the loop sleeps shows only on waking: the tick says it is 0.35 s late (a host pause, counted
    once), and the schedule restarts from the moment it woke, so the next tick is on time."""
    clock = OversleepingClock()
    ticks = Ticker(clock, 0.1)
    assert ticks.wait() == 0.0 and ticks.late_by == 0.0
    clock.extra = 0.35
    assert ticks.wait() == pytest.approx(0.45) and ticks.late_by == pytest.approx(0.35) and ticks.overruns == 1
    assert LinkHealth(NAMES, rate=1.0, timeout=0.5).host_paused(ticks.late_by, 0.1)
    assert ticks.wait() == pytest.approx(0.55) and ticks.late_by == 0.0 and ticks.overruns == 1


def test_every_link_silent_holds_then_lands_all_and_marks_nobody_lost() -> None:
    silent = np.full(3, 0.7)
    held = shield(tick(APART, link_age=silent, links_silent=0.7), CFG)
    assert (held.action == Action.HOLD).all() and not held.lost()
    assert {e.rule for e in held.events} == {"links_silent"}
    landed = shield(tick(APART, link_age=np.full(3, 1.1), links_silent=1.1), CFG)  # timeout 0.5 + stall 0.5
    assert (landed.action == Action.LAND).all() and not landed.lost()
    one = shield(tick(APART, link_age=np.array([0.05, 0.7, 0.05])), CFG)
    assert one.lost() == ["b"] and list(one.action) == [Action.LAND, Action.LOST, Action.LAND]


# ---------------------------------------------------------------- grown obstacles
def test_a_drone_without_a_valid_pose_is_an_obstacle_grown_by_its_possible_travel() -> None:
    """b's pose is gone: 0.5 m from its last valid one a tracking drone holds once b may have flown 0.3 m
    (grown ellipsoids touch), not while b may have flown only 0.1 m; before, a pose-less drone was skipped."""
    pos = [[1.0, 1.0, 0.5], [np.nan, np.nan, np.nan], [1.0, 4.0, 0.5]]
    last = np.array([[1.0, 1.0, 0.5], [1.5, 1.0, 0.5], [1.0, 4.0, 0.5]])
    age = np.array([0.01, np.inf, 0.01])
    near = shield(tick(pos, pose_age=age, last_pos=last, grow=np.array([0.0, 0.3, 0.0])), CFG)
    assert near.action[0] == Action.HOLD and "separation" in {e.rule for e in near.events if e.drone == "a"}
    far = shield(tick(pos, pose_age=age, last_pos=last, grow=np.array([0.0, 0.1, 0.0])), CFG)
    assert "separation" not in {e.rule for e in far.events if e.drone == "a"}
    blind = shield(tick(pos, pose_age=age), CFG)
    assert "separation" not in {e.rule for e in blind.events}


# ---------------------------------------------------------------- reactions
def test_the_most_severe_reaction_is_taken_and_named() -> None:
    """A low battery lands one drone while another's supervisor reports it locked: stop one, named locked."""
    d = shield(
        tick(APART, battery=np.array([3.0, 4.0, 4.0]), locked=np.array([False, False, True])),
        CFG,
    )
    v = verdict(d, np.ones(3, dtype=bool))
    assert v.reaction == Reaction.STOP_ONE and v.rules == ("locked",) and v.drones == ("c",)
    assert v.line() == "stop one: locked (c)"
    lands = verdict(shield(tick(APART, stop_requested=True), CFG), np.ones(3, dtype=bool))
    assert lands.reaction == Reaction.LAND_ALL and lands.rules == ("signal",)
    one = verdict(shield(tick(APART, battery=np.array([3.0, 4.0, 4.0])), CFG), np.ones(3, dtype=bool))
    assert one.reaction == Reaction.LAND_ONE and one.drones == ("a",)
    assert Reaction.HOLD < Reaction.LAND_ONE < Reaction.LAND_ALL < Reaction.STOP_ONE < Reaction.STOP_ALL


def test_a_landing_drone_is_stopped_only_once_it_leaves_its_landing_column() -> None:
    began = {"a": np.array([1.0, 1.0, 0.5]), "b": np.array([2.0, 2.0, 0.5])}
    state = {"a": "landing", "b": "landing", "c": "flying"}
    pos = {
        "a": np.array([1.0 + LANDING_COLUMN / 2, 1.0, 0.3]),  # inside its column: spared
        "b": np.array([2.0 + 2 * LANDING_COLUMN, 2.0, 0.3]),  # out of it: stopped
        "c": np.array([3.0, 3.0, 0.5]),  # not landing: stopped
    }
    assert spare_landing(["a", "b", "c"], state, pos, began) == ["b", "c"]
    unseen = {**pos, "a": np.full(3, np.nan)}  # no pose: its planner goes on
    assert spare_landing(["a"], state, unseen, began) == []


# ---------------------------------------------------------------- landing confirmed
def test_landed_means_the_firmware_says_so_not_a_low_height() -> None:
    flying = 1 << crtp.BIT_IS_FLYING
    finished, idle = 1 << crtp.BIT_HL_FINISHED, 1 << crtp.BIT_HL_DISABLED
    assert confirmed_down(idle, 0.0) and confirmed_down(finished, float("nan"))
    assert not confirmed_down(flying | idle, 0.0)  # motors idled less than 2 s ago (or a takeoff begins)
    assert not confirmed_down(0, 0.0)  # the planner still flies
    assert not confirmed_down(idle, 0.3)  # measured moving
    cut = idle | 1 << crtp.BIT_LOCKED
    assert not confirmed_down(cut, 0.0) and cut_by_firmware(cut)
    assert cut_by_firmware(1 << crtp.BIT_TUMBLED) and cut_by_firmware(1 << crtp.BIT_CRASHED)
    assert not cut_by_firmware(flying | finished)


def _cut_report(heights: list[float], state: str, pauses: int = 0) -> tuple[float, str]:
    """Where :meth:`Landing._cut_at` places a cut drone whose last ticks saw ``heights`` in ``state``."""
    from collections import deque
    from types import SimpleNamespace

    from atdrone.deploy.landing import RECENT, Landing

    seen = deque(((z, state, pauses) for z in heights), maxlen=RECENT)
    aloft = {"cf1": max(heights)} if state in ("taking_off", "flying") else {}
    fake = SimpleNamespace(recent={"cf1": seen}, aloft=aloft, last_seen={"cf1": heights[-1]}, state={"cf1": "stopped"})
    return Landing._cut_at(fake, "cf1")  # type: ignore[arg-type]


def test_a_drone_that_fell_before_the_report_is_cut_in_the_air_whether_flying_or_taking_off() -> None:
    """The supervisor's report comes ticks after the cut; by then a falling drone lies on the floor. A drone
    that was taking off or flying at 0.5 m is reported cut at 0.5 m, one still on the floor at the floor."""
    fell = [0.5, 0.5, 0.5, 0.4, 0.2, 0.0, 0.0, 0.0, 0.0, 0.0]
    assert _cut_report(fell, "flying") == (0.5, "flying")
    assert _cut_report(fell, "taking_off") == (0.5, "taking_off")
    assert _cut_report([0.0] * 10, "taking_off")[0] < 0.05
    # the report held back by a silent link until the ticks kept hold only the floor: still its height aloft
    assert _cut_report([0.5] * 5 + [0.0] * (2 * RECENT), "flying") == (0.5, "flying")
    # a landing drone near the floor stays where it was two ticks back (it was coming down anyway)
    assert _cut_report([0.3, 0.2, 0.1, 0.02, 0.0, 0.0], "landing")[0] < 0.05


class _Fleet:
    """The bridge's supervisor bits per drone, and the emergency stops sent."""

    def __init__(self) -> None:
        self.bits: dict[str, int] = {}
        self.stopped: list[str] = []

    def supervisor(self) -> dict[str, int]:
        return dict(self.bits)

    def emergency_stop(self, names: list[str]) -> None:
        self.stopped += names


def test_a_drone_locked_before_its_link_is_heard_again_is_reported_cut_in_the_air() -> None:
    """After a host pause the supervisor's locked bit can reach the shield (rule ``locked``: stop) while the
    drone's link is not yet judged fresh; by then the drone lies on the floor. The job reports it cut in the
    air at the height it flew at, not stopped on the ground."""
    from types import SimpleNamespace

    from atdrone.deploy.landing import Landing

    flight = Landing.__new__(Landing)
    fleet = _Fleet()
    names = list(NAMES)
    flight.bridge, flight.names, flight.shield_cfg = fleet, names, CFG  # type: ignore[assignment]
    flight.state = dict.fromkeys(names, "flying")
    flight.last_seen, flight.recent, flight.aloft, flight.cut, flight.landing_from = {}, {}, {}, {}, {}
    flight.link_health = SimpleNamespace(pauses=0)  # type: ignore[assignment]
    flight.links = SimpleNamespace(silence=np.zeros(3))  # type: ignore[assignment]
    flight.speed, flight.aborted, flight.progress = np.zeros(3), "", lambda line: None
    flight.reaction = Verdict(Reaction.HOLD, (), ())
    pos = np.array(APART)
    for _ in range(5):  # flying at 0.5 m
        flight._react(shield(tick(pos), CFG), pos)
    fleet.bits["c"] = 1 << crtp.BIT_LOCKED  # cut during the pause; it fell
    floor = pos.copy()
    floor[2, 2] = 0.0
    flight.links = SimpleNamespace(silence=np.array([0.0, 0.0, 2 * CFG.link_timeout]))  # type: ignore[assignment]
    for _ in range(2 * RECENT):  # a long while on the floor before the locked bit is read
        flight._react(shield(tick(floor), CFG), floor)
    decision = shield(tick(floor, locked=np.array([False, False, True])), CFG)
    assert decision.action[2] == Action.STOP
    flight._react(decision, floor)
    assert fleet.stopped == ["c"] and flight.state["c"] == "stopped"
    assert flight.endings()["c"] == "cut in the air at 0.50 m (flying)"


def test_a_fault_given_a_step_fires_at_that_step_of_its_episode_whatever_the_time() -> None:
    fired: list[str] = []
    faults = FaultClock()
    faults.add(2.0, "cf1", "timed", lambda: fired.append("timed"))
    faults.add(0.0, "cf2", "step", lambda: fired.append("step"), episode=1, step=5)
    faults.add(30.0, "cf3", "late_step", lambda: fired.append("late_step"), episode=0, step=3)
    assert faults.fire(1.0, 0, 4) == [] and fired == []
    assert faults.fire(2.0, 0, -1) == [("cf1", "fault:timed")]  # a time: on any tick once it has passed
    assert faults.fire(50.0, 0, 20) == [("cf3", "fault:late_step")]  # a step, once its time has passed too
    assert faults.fire(60.0, 1, -1) == [] and faults.fire(61.0, 1, 4) == []  # the episode's transit, step 4
    assert faults.fire(61.1, 1, 5) == [("cf2", "fault:step")] and fired == ["timed", "late_step", "step"]
    assert faults.pending == []
    # an episode that ended before the step: the fault fires on the first tick after it
    faults.add(0.0, "", "early_end", lambda: fired.append("early_end"), episode=0, step=25)
    assert faults.fire(9.0, 0, 12) == [] and faults.fire(9.1, 1, -1) == [("", "fault:early_end")]
