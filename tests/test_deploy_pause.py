"""A host pause inside a tick: after the loop woke on time, before its shield judged the poses and links.

The real loop on the fake clock and fleet of tests/test_deploy_team_log.py, with one
pause of 0.4 s (past the 0.3 s stale-pose limit) put where no thread of the process ran:
the motion capture's last frames and the radio's last packets are as old as the pause.
It is a host pause (ages count from the moment the loop resumed), not a loss of every
pose or link. The flights with real pauses, at any phase of the tick, are in
tests/test_deploy_faults.py.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
from test_deploy_team_log import FakeClock, FakeFleet, flight, noted  # noqa: F401  (the fixture)

from atdrone.deploy.loop import Flight
from atdrone.deploy.mocap import Pose

PAUSE = 0.4


def pause_after_waking(fl: Flight, fleet: FakeFleet, monkeypatch: pytest.MonkeyPatch, where: str) -> None:
    """On the next tick, stop the whole process for :data:`PAUSE` s right after the loop woke: the clock jumps; the
    poses (``where == "poses"``) or the links (``"links"``) keep the age they had when it stopped."""
    clock: FakeClock = fleet.clock
    fl.link_health.wall = lambda: clock.t  # one clock for the loop and its link health
    measured, latest, link_age = fl.measured, fleet.latest, fleet.link_age
    stopped_at: list[float] = []

    def paused_measured() -> Any:
        if not stopped_at:
            stopped_at.append(clock.t)
            clock.t += PAUSE
        return measured()

    def stale_latest() -> dict[str, Pose]:
        poses = latest()
        if stopped_at and where == "poses":
            return {n: Pose(stopped_at[0], p.pos, p.yaw, moved_t=stopped_at[0]) for n, p in poses.items()}
        return poses

    def silent_links() -> dict[str, float]:
        return {n: clock.t - stopped_at[0] for n in link_age()} if stopped_at and where == "links" else link_age()

    monkeypatch.setattr(fl, "measured", paused_measured)
    monkeypatch.setattr(fleet, "latest", stale_latest)
    monkeypatch.setattr(fleet, "link_age", silent_links)


@pytest.mark.parametrize("where", ["poses", "links"])
def test_a_pause_between_waking_and_the_shield_is_a_host_pause(
    flight: tuple[Flight, FakeFleet],  # noqa: F811  (the fixture imported above)
    monkeypatch: pytest.MonkeyPatch,
    where: str,
) -> None:
    fl, fleet = flight
    fl._hold_tick()
    pause_after_waking(fl, fleet, monkeypatch, where)
    assert fl._hold_tick() and not fl.aborted
    frame = fl.log.frame()
    assert len(noted(fl, "host_pause")) == len(fl.names)  # the paused tick's rows, one per drone
    assert not frame.events.str.contains("stale|link_lost|links_silent").any(), frame.events.unique()
    assert np.isclose(fl.link_health.resumed, fleet.clock.t)


def estimate_off_of(fleet: FakeFleet, monkeypatch: pytest.MonkeyPatch, name: str, silent_from: float | None) -> None:
    """``name``'s logged onboard estimate stays 1 m beside its pose (the others' agree with theirs); its link is
    silent from clock time ``silent_from`` on (None: never)."""
    latest, link_age = fleet.latest, fleet.link_age

    def estimates() -> dict[str, tuple[float, float, float, float]]:
        out = {n: (*p.pos, p.yaw) for n, p in latest().items()}
        x, y, z, yaw = out[name]
        return out | {name: (x + 1.0, y, z, yaw)}

    def ages() -> dict[str, float]:
        silent = silent_from is not None and fleet.clock.t >= silent_from
        return link_age() | ({name: fleet.clock.t - silent_from} if silent and silent_from is not None else {})

    monkeypatch.setattr(fleet, "estimates", estimates)
    monkeypatch.setattr(fleet, "link_age", ages)


def test_a_silent_links_stale_estimate_is_left_to_the_link_rule(
    flight: tuple[Flight, FakeFleet],  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A partner's link falls silent with its last estimate beside its pose: it is dropped alone for its lost link,
    never landed for its estimate (which would land everyone)."""
    fl, fleet = flight
    fl.link_health.wall = lambda: fleet.clock.t
    estimate_off_of(fleet, monkeypatch, "cf4", silent_from=fleet.clock.t)
    for _ in range(12):
        assert fl._hold_tick() and not fl.aborted
    frame = fl.log.frame()
    assert frame[frame.drone == "cf4"].events.str.contains("link_lost").any()
    assert not frame.events.str.contains("estimate_off").any(), frame.events.unique()


def test_an_estimate_off_counts_its_time_from_the_last_host_pause(
    flight: tuple[Flight, FakeFleet],  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """0.3 s off, then a host pause of 0.4 s: not yet the 0.5 s hold; held off 0.5 s after the pause, it lands."""
    fl, fleet = flight
    estimate_off_of(fleet, monkeypatch, "cf4", silent_from=None)
    assert fl.shield_cfg.estimate_hold == 0.5 and fl.dt == 0.1
    for _ in range(4):  # off from the first of these ticks: 0.3 s by the fourth
        fl._hold_tick()
    fl.link_health.wall = lambda: fleet.clock.t
    fl._hold_tick(first=lambda: setattr(fleet.clock, "t", fleet.clock.t + PAUSE))  # the whole process stopped
    frame = fl.log.frame()
    assert len(noted(fl, "host_pause")) == len(fl.names)
    assert not frame.events.str.contains("estimate_off").any(), frame.events.unique()
    for _ in range(7):  # 0.5 s off after the pause (the first of these ticks makes up for the pause's lateness)
        fl._hold_tick()
    frame = fl.log.frame()
    assert set(frame[frame.events.str.contains("estimate_off")].drone) == {"cf4"}
