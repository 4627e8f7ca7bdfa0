"""The Ray processes a SIGKILLed driver's local Ray leaves behind are ended by the next local start, and nothing of
a live Ray is touched."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from atdrone.service import rayclean

pytestmark = pytest.mark.skipif(not Path("/proc/self/fd").is_dir(), reason="needs Linux /proc")

# a driver with a local Ray of its own: prints its session and the raylet's children (the agents), then waits
DRIVER = textwrap.dedent(
    """
    import json, os, time
    from atdrone.service.driver import init_ray
    import ray
    init_ray(None, num_cpus=1)
    session = os.path.basename(ray._private.worker._global_node.get_session_dir_path())
    print(json.dumps({"session": session}), flush=True)
    time.sleep(600)
    """
)
NEXT_START = "from atdrone.service.driver import init_ray; init_ray(None, num_cpus=1); import ray; ray.shutdown()"


def _alive(pid: int) -> bool:
    state = rayclean._status(pid)[2]
    return state not in ("", "Z", "X")


def _wait(predicate, timeout_s: float, what: str) -> None:  # type: ignore[no-untyped-def]
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(what)
        time.sleep(0.2)


def _orphans_of_a_killed_driver(env: dict[str, str]) -> tuple[str, list[int]]:
    """A driver's local Ray, its agents stopped (as a starved agent on a busy host: it cannot notice its raylet's
    death before the next run starts), the driver SIGKILLed: (its session, the agents it left alive)."""
    driver = subprocess.Popen([sys.executable, "-c", DRIVER], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert driver.stdout is not None
        session = json.loads(driver.stdout.readline())["session"]
        mine = lambda: [p for p in rayclean.ray_processes() if p.session == session]
        daemons = {p.pid for p in mine() if p.daemon}
        assert len(daemons) == 2, mine()  # its GCS and raylet
        _wait(lambda: len([p for p in mine() if "Agent" in p.title]) == 2, 60, "the agents never started")
        agents = [p for p in mine() if p.ppid in daemons and not p.daemon]
        for p in agents:
            os.kill(p.pid, signal.SIGSTOP)
    finally:
        driver.kill()
        driver.wait()
    _wait(lambda: not any(_alive(pid) for pid in daemons), 30, "the killed driver's GCS and raylet live on")
    left = [p.pid for p in agents if _alive(p.pid)]
    assert left and {p.pid for p in rayclean.orphans()} >= set(left), "no orphan was made: the test is broken"
    return session, left


# Another xdist worker's Ray start (any test's) ends orphans too, and may get there first: then this start has
# nothing to end. That attempt proves nothing either way, so the scenario is made again; a start that never
# ends them fails every attempt.
ATTEMPTS = 3


def test_agents_a_killed_drivers_ray_left_are_ended_by_the_next_start_and_live_rays_are_untouched(monkeypatch):
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    for _ in range(ATTEMPTS):
        session, left = _orphans_of_a_killed_driver(env)
        ended = subprocess.run([sys.executable, "-c", NEXT_START], capture_output=True, text=True, env=env, timeout=120)
        assert ended.returncode == 0, ended.stderr[-2000:]
        _wait(lambda pids=left: not any(_alive(pid) for pid in pids), 10, "the next start left the orphans alive")
        if "a killed run left behind" in ended.stderr:
            break
    else:
        pytest.fail(f"in {ATTEMPTS} attempts the next start never said it ended the orphans: {ended.stderr[-2000:]}")
    # the line names the sessions of all it ended: the dead one alone
    assert f"Ray process(es) a killed run left behind ({session}):" in ended.stderr, ended.stderr[-2000:]
    # the live Rays on this host (the suite's own, another run's, one shutting down) are nothing to end; another
    # test's killed driver may have left orphans of its own meanwhile: those it may end
    killed: list[int] = []
    monkeypatch.setattr(rayclean.os, "kill", lambda pid, sig: killed.append(pid))
    would_end = rayclean.clean_orphans()
    assert sorted(killed) == sorted(p.pid for p in would_end)
    assert not [p for p in would_end if _driver_alive(p.session)], would_end


def _driver_alive(session: str) -> bool:
    """Whether the process that started ``session`` lives and still parents some of its processes."""
    starter = rayclean._starter(session)
    return _alive(starter) and any(p.ppid == starter for p in rayclean.ray_processes() if p.session == session)


def test_a_drivers_ray_whose_raylet_and_gcs_are_gone_while_the_driver_lives_is_no_orphan():
    """``ray.shutdown()`` ends the raylet and the GCS first, then the processes the driver started itself, one by
    one: on a busy host another run's start sees that session for seconds with no daemon alive. Here the driver is
    stopped in that state (its daemons killed, itself alive): nothing of its session is an orphan until it dies."""
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    driver = subprocess.Popen([sys.executable, "-c", DRIVER], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert driver.stdout is not None
        session = json.loads(driver.stdout.readline())["session"]
        mine = lambda: [p for p in rayclean.ray_processes() if p.session == session]
        os.kill(driver.pid, signal.SIGSTOP)
        daemons = [p.pid for p in mine() if p.daemon]
        assert len(daemons) == 2, mine()
        for pid in daemons:
            os.kill(pid, signal.SIGKILL)
        _wait(lambda: not any(_alive(pid) for pid in daemons), 30, "the GCS and raylet live on")
        children = [p for p in mine() if p.ppid == driver.pid]
        assert children, mine()  # the log monitor, dashboard, autoscaler monitor: the driver's own
        assert not [p for p in rayclean.orphans() if p.session == session]
    finally:
        driver.kill()
        driver.wait()
    # the driver dead, what it left is an orphan (and ended, as the next start would)
    _wait(lambda: any(p.session == session for p in rayclean.orphans()) or not mine(), 30, "nothing left to see")
    rayclean.clean_orphans()
    _wait(lambda: not mine(), 30, "its processes were never ended")


def test_a_live_ray_installed_under_a_long_path_is_no_orphan(tmp_path):
    """Its daemons' command lines start with a path past the 80 characters of a title (a CI checkout's venv is
    one): they are still its GCS and raylet, so a start beside it ends nothing of it."""
    venv = tmp_path / ("x" * 100) / "venv"
    venv.parent.mkdir()
    venv.symlink_to(sys.prefix, target_is_directory=True)  # Python finds the venv (and ray) by the path it was run as
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    driver = subprocess.Popen([str(venv / "bin" / "python"), "-c", DRIVER], stdout=subprocess.PIPE, text=True, env=env)
    try:
        assert driver.stdout is not None
        session = json.loads(driver.stdout.readline())["session"]
        mine = [p for p in rayclean.ray_processes() if p.session == session]
        daemons = [p for p in mine if p.daemon]
        assert len(daemons) == 2 and all(len(p.program) > 80 for p in daemons), mine
        assert not [p for p in rayclean.orphans() if p.session == session]
    finally:
        driver.kill()
        driver.wait()
