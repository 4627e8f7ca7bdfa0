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
