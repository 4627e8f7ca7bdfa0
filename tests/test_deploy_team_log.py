"""A team change and the flight log name one tick.

A partner dropped alone and a backup taking its slot are each noted on one row of the
flight log (``dropped:RULE``, ``took_slot:SLOT``) and kept in the flight's team changes
with a time (``t``, ``took_slot_t``). Both must name the tick in which it happened, on
every path: a drop during a takeoff's watch, a backup seated between episodes. The
flight here is the real loop on a fake clock that jumps to each tick and a fake fleet
that flies as commanded, so no tick is ever late and every run is the same.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pandas as pd
import pytest

from atdrone.config import load_task
from atdrone.deploy.config import load_deploy
from atdrone.deploy.flightlog import FlightLog
from atdrone.deploy.loop import Flight
from atdrone.deploy.mocap import Pose

CONFIG = json.loads((Path(__file__).parents[1] / "configs" / "deploy" / "sim_4p2e1o_backup.json").read_text())
# on the floor, apart (x, y): pursuers cf1-cf4, evaders cf5 and cf6, the backup cf7 clear of every column
FLOOR = {
    "cf1": (0.6, 1.0),
    "cf2": (1.4, 1.0),
    "cf3": (2.2, 1.0),
    "cf4": (3.0, 1.0),
    "cf5": (1.0, 4.0),
    "cf6": (2.6, 4.0),
    "cf7": (1.8, 1.8),
}


class FakeClock:
    """A clock that jumps to the time it is asked to sleep until: ticks are never late."""

    rate = 1.0

    def __init__(self) -> None:
        self.t = 100.0

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += max(seconds, 0.0)

    def sleep_until(self, t: float) -> None:
        self.t = max(self.t, t)


class FakeFleet:
    """The bridge and the motion capture at once: takeoffs and landings rise and sink linearly, a streamed drone
    is where its setpoint is; every link fresh, every battery full unless ``low`` says (drone: volts)."""

    def __init__(self, clock: FakeClock) -> None:
        self.clock = clock
        self.xy = {n: np.array(p) for n, p in FLOOR.items()}
        self.climb: dict[str, tuple[float, float, float, float]] = {n: (0.0, 0.0, 0.0, 1.0) for n in FLOOR}
        self.low: dict[str, float] = {}

    def z(self, name: str) -> float:
        z0, z1, t0, duration = self.climb[name]
        return z0 + (z1 - z0) * min(max((self.clock.now() - t0) / duration, 0.0), 1.0)

    def place(self, names: Sequence[str], z: float) -> None:
        for n in names:
            self.climb[n] = (z, z, 0.0, 1.0)

    def _move(self, names: Sequence[str], z1: float, duration: float) -> None:
        for n in names:
            self.climb[n] = (self.z(n), z1, self.clock.now(), duration)

    # the motion capture
    def latest(self) -> dict[str, Pose]:
        t = self.clock.now()
        return {n: Pose(t, np.r_[self.xy[n], self.z(n)], math.pi / 2, moved_t=t) for n in FLOOR}

    # the bridge
    def takeoff(self, names: Sequence[str], height: float, duration: float) -> None:
        self._move(names, height, duration)

    def land(self, names: Sequence[str], duration: float) -> None:
        self._move(names, 0.0, duration)

    def post_setpoints(self, setpoints: Mapping[str, Any]) -> None:
        for n, (pos, _vel, _acc) in setpoints.items():
            self.xy[n] = np.asarray(pos[:2], dtype=np.float64)
            self.place([n], float(pos[2]))

    def battery(self) -> dict[str, float]:
        return {n: self.low.get(n, 4.0) for n in FLOOR}

    def link_age(self) -> dict[str, float]:
        return dict.fromkeys(FLOOR, 0.0)

    def sender_age(self) -> float:
        return 0.0

    def supervisor(self) -> dict[str, int]:
        return {}

    def estimates(self) -> dict[str, tuple[float, float, float, float]]:
        return {}

    def beat(self) -> None:
        pass

    def request_arming(self, names: Sequence[str]) -> None:
        pass

    def notify_stop(self, names: Sequence[str]) -> None:
        pass

    def emergency_stop(self, names: Sequence[str]) -> None:
        raise AssertionError(f"nothing is stopped here: {list(names)}")


@pytest.fixture
def flight() -> Iterator[tuple[Flight, FakeFleet]]:
    """The shipped backup config's flight in the air (cf7 on the floor), between ticks."""
    cfg = load_deploy(CONFIG)
    task = load_task(cfg.task)
    clock = FakeClock()
    fleet = FakeFleet(clock)
    log = FlightLog({"task": cfg.task, "drones": {d.name: d.role for d in cfg.fleet()}})
    team: Any = SimpleNamespace(forget=lambda slot: None)
    out = Flight(cfg, task, team, fleet, fleet, clock, log)  # type: ignore[arg-type]
    fleet.place(out.flyers, cfg.flight_height)
    out._set_state(out.flyers, "flying")
    try:
        yield out, fleet
    finally:
        out.policy.close()
        out._worker.shutdown(wait=True)


def noted(flight: Flight, note: str) -> pd.DataFrame:
    """The log's rows carrying ``note``."""
    frame = flight.log.frame()
    return frame[frame.events.str.split(",").map(lambda events: note in events)]


def test_a_drop_in_a_takeoffs_watch_is_logged_on_the_tick_its_record_names(
    flight: tuple[Flight, FakeFleet],
) -> None:
    """cf3's battery runs low while the takeoff is watched: the drop's record and its ``dropped:battery`` row name
    the tick whose reading dropped it."""
    fl, fleet = flight
    fleet.low["cf3"] = 3.2
    fl._watch(1.0)
    fl._hold_tick()  # a note left for a later tick would land here
    (change,) = fl.team_changes
    rows = noted(fl, "dropped:battery")
    assert list(rows.drone) == ["cf3"]
    assert float(rows.t.iloc[0]) == change["t"], (float(rows.t.iloc[0]), change["t"])
    assert change["t"] == float(fl.log.frame().t.min())  # the watch's first tick read the low battery


def test_a_backup_seated_between_episodes_is_logged_on_the_tick_its_record_names(
    flight: tuple[Flight, FakeFleet], monkeypatch: pytest.MonkeyPatch
) -> None:
    """cf3 was dropped in an episode; between episodes cf7 takes off with the landed drones and takes slot 2 at
    once: its ``took_slot:2`` row and ``took_slot_t`` name one tick, a tick of the flight's clock."""
    fl, fleet = flight
    fl._drop("cf3", "battery")
    fleet.place(["cf3"], 0.0)
    fl._set_state(["cf3"], "landed")
    monkeypatch.setattr(fl, "_plan", lambda start, end: None)  # the transit is not what is checked: stop there
    assert fl._go_to_spawn(*fl._spawn()) is None
    (change,) = fl.team_changes
    assert change["backup"] == "cf7" and change["memory_reset"] and fl.present[2]
    rows = noted(fl, "took_slot:2")
    assert list(rows.drone) == ["cf7"]
    assert float(rows.t.iloc[0]) == change["took_slot_t"], (float(rows.t.iloc[0]), change["took_slot_t"])
    assert (fl.log.frame().t == change["took_slot_t"]).sum() == len(fl.names)  # one tick's rows, every drone
