"""Faults in flight on the sim backend: every drone lands softly, or the firmware cuts it, and the job says which.

The shipped config (configs/deploy/sim_4p2e1o.json) unchanged but for the member, the
horizon and the fault injected once: lost radio links and mocap, frozen poses, a low
battery, a stalled policy, an exception, a paused or hung ground station, a steady push,
and SIGINT / SIGTERM through the entry points (the line and status they end with). The
fault flights run beside two busy-looping processes (``busy_host``). The checks read the
flight log and what the simulated firmware saw; the helpers are in tests/flight_helpers.py.
"""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from flight_helpers import (  # noqa: F401  (the fixtures)
    FAULT_AT,
    ROOT,
    _mlflow_db,
    busy_host,
    end_states,
    fly,
    landed_softly,
    registry_member,
    sim_doc,
    ticks,
)

from atdrone.cli import main as cli_main
from atdrone.deploy.config import load_deploy
from atdrone.deploy.job import run_deploy
from atdrone.deploy.loop import Flight, StopRequest


# ---------------------------------------------------------------- faults
def stops(result: Any, why: str) -> dict[str, float]:
    """Per drone, the first clock time (since the flight began) the simulated firmware stopped it for ``why``."""
    return {
        n: min(t for t, w in v["history"] if w == why) - result.t0
        for n, v in result.fleet.items()
        if any(w == why for _, w in v["history"])
    }


@pytest.mark.parametrize(
    ("fault", "reason"),
    [
        ({"kind": "link_dropout", "drone": "cf3", "duration": 0.2}, ""),
        ({"kind": "mocap_dropout", "duration": 1.0}, "shield: all_stale"),
        ({"kind": "mocap_dropout", "duration": 60.0}, "shield: all_stale"),
        ({"kind": "mocap_freeze", "drone": "cf3", "duration": 1.0}, "shield: stale_pose"),
        ({"kind": "mocap_freeze", "duration": 1.0}, "shield: all_stale"),
        ({"kind": "low_battery", "drone": "cf2", "volts": 3.2}, "shield: battery"),
        ({"kind": "pose_blocked", "drone": "cf3", "duration": 60.0}, "shield: estimate_off"),
        ({"kind": "policy_stall", "duration": 2.0}, "shield: policy_stall"),
        ({"kind": "signal", "signal": "SIGINT"}, "shield: signal"),
        ({"kind": "signal", "signal": "SIGTERM"}, "shield: signal"),
        ({"kind": "exception"}, "InjectedFault: an exception injected"),
    ],
    ids=[
        "link-lost-0.2s",
        "mocap-out-1s",
        "mocap-out-for-good",
        "one-body-frozen-1s",
        "all-bodies-frozen-1s",
        "low-battery",
        "poses-kept-from-cf3",
        "policy-stall-2s",
        "sigint",
        "sigterm",
        "exception",
    ],
)
def test_every_drone_lands_softly_after_a_fault_on_a_busy_host(
    tmp_path: Path, registry_member: tuple[str, str], busy_host: None, fault: dict[str, Any], reason: str
) -> None:
    """The shipped config, the fault injected once, two busy loops beside: every drone ends on the floor, its
    motors off, having met it under 0.5 m/s; the job names the most severe reaction's rule (none where the
    fault was ridden out)."""
    stop = StopRequest()
    cfg = load_deploy(sim_doc(tmp_path, registry_member, horizon=80, faults=[{**fault, "at": FAULT_AT}]))
    result = run_deploy(cfg, arm=True, tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}", say=print, stop=stop)
    print(f"ended early: {result.ended_early!r}; {result.endings}")
    frame = ticks(result)
    assert frame.events.str.contains(f"fault:{fault['kind']}").any()
    if reason:
        assert result.ended_early.startswith(reason) and "not landed" not in result.ended_early
    else:
        assert not result.ended_early and result.episodes_flown == 1
    landed_softly(result)
    assert result.stopped_by == fault.get("signal", "")  # the entry points' line and status (below)
    if fault["kind"] == "signal":
        assert stop.signal == fault["signal"]
    if fault["kind"] == "mocap_freeze":  # frames kept coming: the frozen pose was seen as stale all the same
        frozen = frame[frame.events.str.contains("stale_pose|all_stale") & (frame.drone == fault.get("drone", "cf1"))]
        assert len(frozen), "the frozen pose was taken as fresh"
    if fault["kind"] == "policy_stall":  # the next policy step stalls: held from outside the call at once
        first = frame[frame.step >= 0].t.min()
        late = frame[frame.events.str.contains("policy_late")]
        assert len(late) and late.t.min() - first < 0.5


def test_host_pauses_while_the_loop_sleeps_are_ridden_out(
    tmp_path: Path, registry_member: tuple[str, str], busy_host: None, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Once the drones are up, eight SIGSTOPs of the ground station from outside, 0.2 wall s each (0.4 s of the
    drones' clock: past the 0.3 s stale-pose limit, under the firmware's watchdogs), at phases unrelated to the
    loop's ticks, so most land while the loop sleeps: each is a host pause, not stale poses of every drone nor
    lost links, and the episode is flown to its end. (A stop while cflib waits on an answer, as in arming, is
    a link error that cflib reports: the flight then never takes off.)"""
    pid, pausers = os.getpid(), []
    code = "import os, signal, time\nfor k in range(8):\n"
    code += f"    time.sleep(0.4 + 0.013 * k); os.kill({pid}, signal.SIGSTOP); time.sleep(0.2); "
    code += f"os.kill({pid}, signal.SIGCONT)\n"
    takeoff = Flight._takeoff

    def pausing_takeoff(flight: Flight) -> None:
        takeoff(flight)
        pausers.append(subprocess.Popen([sys.executable, "-S", "-c", code]))

    monkeypatch.setattr(Flight, "_takeoff", pausing_takeoff)
    try:
        result = fly(tmp_path, registry_member, horizon=60)
    finally:
        for pauser in pausers:
            pauser.kill()
            pauser.wait()
        os.kill(pid, signal.SIGCONT)  # never left stopped
    frame = ticks(result)
    assert not result.ended_early and result.episodes_flown == 1
    assert frame.groupby("t").events.apply(lambda e: e.str.contains("host_pause").any()).sum() >= 5
    landed_softly(result)


def test_a_link_lost_for_good_gets_land_commands_until_the_end_and_is_reported_lost(
    tmp_path: Path, registry_member: tuple[str, str], busy_host: None
) -> None:
    """A learner drone whose link dies is marked lost (not the whole fleet): it gets the land command on every tick
    it is lost, the others land; its own firmware cuts its motors (no keep-alive reaches it), and the job says it
    did not land and exits non-zero. (A partner drone's lost link drops it alone: tests/test_deploy_backup.py.)"""
    result = fly(tmp_path, registry_member, horizon=80, faults=[{"kind": "link_loss", "at": FAULT_AT, "drone": "cf1"}])
    frame = ticks(result)
    lost = frame[(frame.drone == "cf1") & (frame.state == "lost")]
    assert len(lost) and (frame[frame.drone != "cf1"].state != "lost").all()
    assert result.sent["land"] >= len(lost) and result.ended_early.startswith("shield: link_lost")
    assert result.endings["cf1"].startswith("lost") and "not landed: cf1 lost" in result.ended_early
    assert "estop_watchdog" in {w for _, w in result.fleet["cf1"]["history"]}
    landed_softly(result, exclude=("cf1",))


def test_a_host_paused_past_the_dead_man_limit_is_cut_by_the_firmware(
    tmp_path: Path, registry_member: tuple[str, str], busy_host: None
) -> None:
    """SIGSTOP for 0.7 wall seconds: 1.4 s of the drones' clock (the shipped rate 2), past their 1 s
    emergency-stop watchdog (docs/deploy.md, "The ground station's host"). The firmware cuts every motor; the
    job says which drones were cut in the air, at what height, and exits non-zero. Nothing is judged lost."""
    result = fly(
        tmp_path, registry_member, horizon=80, faults=[{"kind": "host_pause", "at": FAULT_AT, "duration": 0.7}]
    )
    frame = ticks(result)
    assert frame.events.str.contains("host_pause").any()
    assert set(stops(result, "estop_watchdog")) == set(result.fleet)
    assert all(e.startswith("cut in the air at") for e in result.endings.values()), result.endings
    assert "not landed" in result.ended_early and (frame.state != "lost").all()


def test_a_hung_loop_is_stopped_by_the_firmware_watchdog_within_1_5_s(
    tmp_path: Path, registry_member: tuple[str, str]
) -> None:
    result = fly(tmp_path, registry_member, horizon=80, faults=[{"kind": "loop_hang", "at": FAULT_AT, "duration": 2.0}])
    frame = ticks(result)
    hang = frame[frame.events.str.contains("fault:loop_hang")].t.min()
    assert np.isfinite(hang)
    stopped = stops(result, "estop_watchdog")
    assert set(stopped) == set(result.fleet), result.fleet
    assert all(0 < t - hang <= 1.5 for t in stopped.values()), {n: t - hang for n, t in stopped.items()}
    assert result.ended_early.startswith("shield: locked") and result.episodes_flown == 0
    assert set(end_states(frame).values()) == {"stopped"}


def test_a_drifting_drone_is_held_on_its_reference(
    tmp_path: Path, registry_member: tuple[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A steady 1 m/s^2 push (wind): Mellinger's kp 0.4 / mass 0.029 leaves 0.029 / 0.4 = 7 cm of offset."""
    from atdrone.deploy import job
    from atdrone.deploy.team import Team

    fleets: list[Any] = []
    schedule, draw = job._schedule, Team.draw

    def keep_fleet(cfg: Any, faults: Any, fleet: Any, *args: Any) -> None:
        fleets.append(fleet)
        schedule(cfg, faults, fleet, *args)

    def push_at_start(self: Team, rng: np.random.Generator) -> list[Any]:  # the wind rises as the episode begins
        fleets[0].push("cf1", np.array([1.0, 0.0, 0.0]))
        return draw(self, rng)

    monkeypatch.setattr(job, "_schedule", keep_fleet)
    monkeypatch.setattr(Team, "draw", push_at_start)
    result = fly(tmp_path, registry_member, horizon=60)
    assert not result.ended_early
    frame = ticks(result)
    rows = frame[(frame.drone == "cf1") & (frame.step >= 20)]
    offset = np.hypot(rows.x - rows.setpoint_x, rows.y - rows.setpoint_y)
    assert offset.median() < 0.12


# ---------------------------------------------------------------- a stop signal at the entry points
@pytest.mark.parametrize(
    ("entry", "name", "code"),
    [("jobs/deploy.py", "SIGTERM", 143), ("atdrone deploy", "SIGINT", 130)],
    ids=["job-sigterm", "cli-sigint"],
)
def test_a_stop_signal_lands_every_drone_then_ends_in_one_interrupted_line_with_the_signals_status(
    tmp_path: Path,
    registry_member: tuple[str, str],
    capsys: pytest.CaptureFixture[str],
    load_script: Callable[[Path], Any],
    entry: str,
    name: str,
    code: int,
) -> None:
    """`ray job stop` (SIGTERM) or Ctrl-C in the air: every drone lands, the log is written, and the last line
    says so, names the log and the command that flies again; the status is the signal's, as for every entry
    point (143, 130)."""
    doc = sim_doc(tmp_path, registry_member, horizon=80, faults=[{"kind": "signal", "signal": name, "at": FAULT_AT}])
    path = tmp_path / "deploy.json"
    path.write_text(json.dumps(doc))
    args = [str(path), "--arm", "--tracking-uri", f"sqlite:///{tmp_path / 'mlflow.db'}"]
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}  # main installs its own
    try:
        if entry == "jobs/deploy.py":
            status = load_script(ROOT / "jobs" / "deploy.py").main(args)
        else:
            status = cli_main(["deploy", *args])
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    (log,) = (tmp_path / "flights").iterdir()
    again = f"{'python ' if entry.endswith('.py') else ''}{entry} {shlex.join(args)}"
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"{entry}: interrupted; every drone landed after 0/1 episode(s); kept the flight log {log}; "
        f"fly again with: {again}"
    )
    assert status == code
    endings = json.loads((log / "meta.json").read_text())["endings"]
    assert endings and set(endings.values()) == {"landed"}, endings


@pytest.mark.parametrize("when", ["before the job", "in the preflight"])
def test_a_stop_signal_before_arming_arms_nothing_and_ends_in_one_interrupted_line(
    tmp_path: Path,
    registry_member: tuple[str, str],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    when: str,
) -> None:
    """SIGTERM while the config loads (before the job takes the signals over) or during the preflight checks (after):
    nothing arms, no flight log is written, and the last line says ``nothing armed`` with the command that flies
    again; the status is SIGTERM's, 143."""
    import os

    import atdrone.deploy.config as deploy_config
    import atdrone.deploy.job as deploy_job

    target, name = (deploy_config, "load_deploy") if when == "before the job" else (deploy_job, "run_preflight")
    original = getattr(target, name)

    def signalled(*args: Any, **kwargs: Any) -> Any:
        os.kill(os.getpid(), signal.SIGTERM)  # delivered at once: the main thread's handler runs before this returns
        return original(*args, **kwargs)

    monkeypatch.setattr(target, name, signalled)
    path = tmp_path / "deploy.json"
    path.write_text(json.dumps(sim_doc(tmp_path, registry_member)))
    args = [str(path), "--arm", "--tracking-uri", f"sqlite:///{tmp_path / 'mlflow.db'}"]
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}  # main installs its own
    try:
        status = cli_main(["deploy", *args])
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1] == f"atdrone deploy: interrupted; nothing armed; fly again with: atdrone deploy {shlex.join(args)}"
    assert status == 143
    assert not (tmp_path / "flights").exists() or not any((tmp_path / "flights").iterdir())
