"""The policy thread of a flight: a late step never races a change of the team.

A policy step that runs late is still running in the policy thread when the flight moves
on: a backup takes a slot (its memory forgotten), or a new episode starts (new partners,
every memory reset). Those changes run in the same thread, after the late step and before
the next, so the late step can neither see half a change nor write its memory back over
it. A team whose step waits on an event makes the order visible.
"""

from __future__ import annotations

import threading
from typing import Any

import numpy as np
import pytest

from atdrone.deploy.clock import ScaledClock
from atdrone.deploy.faults import FaultClock
from atdrone.deploy.team import PolicyRunner


class SlowTeam:
    """A team whose step waits for ``release``, and which records what ran in which order (and in which thread)."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.calls: list[tuple[str, str]] = []
        self.memory = {1: "episode 1"}

    def act(self, slot: int) -> np.ndarray:
        self.release.wait(10.0)
        self.memory[slot] = "written by the late step"  # a step writes back what it remembers of its drone
        self.calls.append(("act", threading.current_thread().name))
        return np.zeros(1)

    def forget(self, slot: int) -> None:
        self.memory.pop(slot, None)
        self.calls.append(("forget", threading.current_thread().name))

    def fail(self) -> None:
        raise RuntimeError("the partners could not be reset")


@pytest.fixture
def runner() -> Any:
    team = SlowTeam()
    policy = PolicyRunner(team, ScaledClock(), FaultClock())  # type: ignore[arg-type]
    yield policy, team
    team.release.set()
    policy.close()


def test_a_change_between_steps_waits_for_the_late_step_and_is_not_undone_by_it(runner: Any) -> None:
    policy, team = runner
    assert policy.act(0.01, 1) is None  # the step is late: still running
    policy.between_steps(team.forget, 1)  # a backup took slot 1 meanwhile: returns at once
    assert team.calls == []
    team.release.set()
    assert policy.act(5.0, 1) is not None  # the late step's actions
    policy._pool.submit(lambda: None).result(5.0)  # everything submitted so far has run
    assert [c for c, _ in team.calls] == ["act", "forget"]
    assert {thread for _, thread in team.calls} != {threading.current_thread().name}
    assert 1 not in team.memory  # the late step wrote before the change: the new drone remembers nothing


def test_a_failed_change_is_raised_by_the_next_step(runner: Any) -> None:
    policy, team = runner
    team.release.set()
    policy.between_steps(team.fail)
    policy._pool.submit(lambda: None).result(5.0)
    with pytest.raises(RuntimeError, match="could not be reset"):
        policy.act(5.0, 1)
