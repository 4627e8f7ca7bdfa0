"""The deploy job end to end on the sim backend: real cflib against the simulated fleet.

Every flight flies the shipped config (configs/deploy/sim_4p2e1o.json) unchanged: its
scaled clock (two simulated seconds per wall second), the radio model with lost and
retried packets, the shield's and the heartbeat's thresholds; a test changes only the
member (a registry entry), the horizon, the faults and where the log goes. The checks
read the flight log the job wrote, what the simulated firmware saw (its counters, what
stopped its motors and when, every impact with the floor, its true height) and the
preflight's findings. Here: the config's errors, whole flights, the separation shield,
the preflight's refusals and the CLI's dry run and report; the fault flights (beside two
busy-looping processes) and the stop signals are in tests/test_deploy_faults.py, the
helpers they share in tests/flight_helpers.py.
"""

from __future__ import annotations

import ctypes
import gc
import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from flight_helpers import (  # noqa: F401  (the fixtures; busy_host, landed_softly: tests/test_deploy_backup.py's)
    CHECKPOINT,
    FAULT_AT,
    RATE,
    ROOT,
    TOC_CACHE,
    _mlflow_db,
    busy_host,
    end_states,
    fly,
    landed_softly,
    min_scaled_separation,
    registry_member,
    sim_doc,
    ticks,
)

from atdrone.cli import main as cli_main
from atdrone.config import ConfigError
from atdrone.deploy.config import load_deploy
from atdrone.deploy.loop import COLUMN_CLEAR
from atdrone.deploy.shield import geofence


def landed_before_any_stop(result: Any, frame: pd.DataFrame) -> None:
    """Every drone reached 'landed' (under control) before the firmware stopped any motor."""
    landed = frame[frame.state == "landed"].groupby("drone").t.min()
    assert set(landed.index) == {d for d in result.fleet}, end_states(frame)
    for n, v in result.fleet.items():
        cut = [t - result.t0 for t, _ in v["history"]]
        assert not cut or min(cut) >= landed[n] - 0.2, (n, v["history"], landed[n])


# ---------------------------------------------------------------- the extra
def test_the_core_imports_without_cflib_or_motioncapture() -> None:
    """cflib is GPLv3 and optional: blocking both packages leaves the core and the deploy config importable."""
    import subprocess
    import sys

    code = (
        "import sys; sys.modules['cflib'] = None; sys.modules['motioncapture'] = None\n"
        "import atdrone.cli, atdrone.service.driver, atdrone.teams.evaluation, atdrone.deploy.job\n"
        "from atdrone.deploy.config import load_deploy; load_deploy('sim_4p2e1o')\n"
        "print('ok')"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr


# ---------------------------------------------------------------- config
def test_config_errors_name_the_json_path(tmp_path: Path, registry_member: tuple[str, str]) -> None:
    doc = sim_doc(tmp_path, registry_member)
    doc["drones"][2]["role"] = "pilot"
    with pytest.raises(ConfigError, match=r"drones\[2\]\.role"):
        load_deploy(doc)
    doc = sim_doc(tmp_path, registry_member, member={"checkpoint": "a.pt", "model": "models:/x@champion"})
    with pytest.raises(ConfigError, match=r"^member: give exactly one"):
        load_deploy(doc)
    doc = sim_doc(tmp_path, registry_member, evaders="virtual")
    with pytest.raises(ConfigError, match=r"^drones: evaders .virtual. needs 0 evader drones, got 2"):
        load_deploy(doc)
    doc = sim_doc(tmp_path, registry_member, faults=[{"kind": "link_loss", "at": 1.0}])
    with pytest.raises(ConfigError, match=r"faults\[0\]\.drone"):
        load_deploy(doc)
    doc = sim_doc(tmp_path, registry_member, faults=[{"kind": "exception", "at": 0.0, "episode": 1, "step": 3}])
    with pytest.raises(ConfigError, match=r"^faults\[0\]\.episode: the flight has 1 episode"):
        load_deploy(doc)
    doc = sim_doc(tmp_path, registry_member, faults=[{"kind": "exception", "at": 0.0, "step": -2}])
    with pytest.raises(ConfigError, match=r"^faults\[0\]\.step: must be >= 0"):
        load_deploy(doc)
    doc = sim_doc(tmp_path, registry_member, backend="cflib")
    with pytest.raises(ConfigError, match=r"drones\[0\]\.uri"):
        load_deploy(doc)
    for bad in ("../../etc", "a/b", ".hidden", ""):
        with pytest.raises(ConfigError, match=r"^name: must be"):
            load_deploy(sim_doc(tmp_path, registry_member, name=bad))


def test_a_registry_member_whose_file_changed_is_refused(tmp_path: Path) -> None:
    """The registry's sha256 is checked: a different (valid) checkpoint at the registered path is not flown."""
    import shutil

    from atdrone.deploy.job import DeployError, member_checkpoint
    from atdrone.registry import Registry

    path = tmp_path / "member.pt"
    shutil.copy(CHECKPOINT, path)
    with Registry(tmp_path / "registry.db") as reg:
        member = reg.add_checkpoint(path, run="deploy-test", generation=0)
    doc = sim_doc(tmp_path, (str(tmp_path / "registry.db"), member))
    assert member_checkpoint(load_deploy(doc)) == path
    shutil.copy(CHECKPOINT.with_name("sp_low.pt"), path)
    with pytest.raises(DeployError, match="not the member registered"):
        member_checkpoint(load_deploy(doc))


# ---------------------------------------------------------------- a whole flight
FROZEN: list[int] = []  # objects out of the collector's view at each planned transit (refusing_transits)


def refusing_transits(monkeypatch: pytest.MonkeyPatch, refuse: Callable[[int], bool]) -> list[np.ndarray]:
    """Make the loop's transit planner refuse its ``n``-th call (from 0) where ``refuse(n)``; the targets of
    every call, in order."""
    from atdrone.deploy import sequence
    from atdrone.deploy.transit import TransitBlocked, plan_transit

    targets: list[np.ndarray] = []

    def planner(start: np.ndarray, end: np.ndarray, *args: Any, **kwargs: Any) -> Any:
        FROZEN.append(gc.get_freeze_count())
        targets.append(np.array(end))
        if refuse(len(targets) - 1):
            raise TransitBlocked("refused by the test")
        return plan_transit(start, end, *args, **kwargs)

    monkeypatch.setattr(sequence, "plan_transit", planner)
    return targets


def test_sim_flight_of_4p2e1o_with_evader_drones(
    tmp_path: Path, registry_member: tuple[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two episodes; the transit to the second episode's first spawn draw is refused (drones in the way), and
    the flight goes on to another draw of the task's spawn."""
    targets = refusing_transits(monkeypatch, lambda n: n == 1)
    result = fly(tmp_path, registry_member, episodes=2, horizon=30)
    assert result.preflight.ok, result.preflight.text()
    assert not result.ended_early and result.episodes_flown == 2
    frame = ticks(result)
    assert len(targets) == 3 and np.abs(targets[2] - targets[1]).max() > 0.1
    # in flight the heap from before takeoff is frozen (a full collection of it stopped the loop for 0.3 s,
    # past the stale-pose limit: "shield: all_stale"); afterwards it is handed back
    assert len(FROZEN) >= 3 and min(FROZEN[-3:]) > 10_000 and gc.get_freeze_count() == 0
    redrawn = frame[frame.events.str.contains("spawn_redrawn")]
    assert set(redrawn.episode) == {1} and (redrawn.step < 0).all()
    cfg = load_deploy(sim_doc(tmp_path, registry_member))
    names = [d.name for d in cfg.drones]
    assert set(end_states(frame).values()) == {"landed"}, end_states(frame)
    # every tick of an episode has a row for every drone
    flying = frame[frame.step >= 0]
    for _, rows in flying.groupby("episode"):
        per_step = rows.groupby("step")["drone"].nunique()
        assert (per_step == len(names)).all() and list(per_step.index) == list(range(len(per_step)))
    episodes = pd.read_parquet(result.log_dir / "episodes.parquet")
    assert list(episodes.episode) == [0, 1]
    # no setpoint outside the geofence; no two drones' separation ellipsoids touching, transits included
    lo, hi = geofence((3.6, 5.0), cfg.shield.margin)
    sp = frame[["setpoint_x", "setpoint_y"]].dropna().to_numpy()
    assert len(sp) > 0 and (sp >= lo - 1e-9).all() and (sp <= hi + 1e-9).all()
    assert min_scaled_separation(frame) >= 1.0
    # what the firmware saw: the estimator reset, poses with their quaternion, full-state setpoints, keep-alives
    counts = result.fleet["cf1"]["counts"]
    assert counts["estimator_reset"] == 2 and counts["extpose"] > 100 and counts.get("extpos", 0) == 0
    assert counts["setpoint_full_state"] > 50 and counts.get("setpoint_position", 0) == 0
    assert counts["estop_keepalive"] > 50 and counts.get("idle_planner_motors_off", 0) == 0
    landed_before_any_stop(result, frame)


def test_a_transit_blocked_on_every_spawn_draw_lands_everyone(
    tmp_path: Path, registry_member: tuple[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    targets = refusing_transits(monkeypatch, lambda n: True)
    result = fly(tmp_path, registry_member, episodes=1, horizon=30)
    assert result.ended_early == "transit blocked: refused by the test (5 spawn draws)"
    assert len(targets) == 5 and result.episodes_flown == 0
    assert set(end_states(ticks(result)).values()) == {"landed"}


def test_pursuers_fly_the_trained_speed(tmp_path: Path, registry_member: tuple[str, str]) -> None:
    """Full-state setpoints along a reference at 0.3 m/s under the Mellinger-like controller: the measured
    ground speed on the policy legs is the trained one (the old one-step-ahead position setpoints gave 0.06)."""
    drones = [
        {"name": n, "role": r}
        for n, r in (("cf1", "learner"), ("cf2", "learner"), ("cf3", "partner"), ("cf4", "partner"))
    ]
    result = fly(tmp_path, registry_member, evaders="virtual", drones=drones, horizon=60)
    assert result.summary["ground_speed_median"] == pytest.approx(0.30, rel=0.1)


def test_no_arm_sends_no_arming_packet(tmp_path: Path, registry_member: tuple[str, str]) -> None:
    result = fly(tmp_path, registry_member, arm=False)
    assert result.preflight.ok and not result.flown and result.log_dir is None
    assert result.sent.get("arming", 0) == 0
    assert result.sent.get("takeoff", 0) == 0 and result.sent.get("setpoint", 0) == 0


# ---------------------------------------------------------------- separation
class Attract:
    """A policy steering every pursuer straight at the mean of the other pursuers."""

    name = "attract"

    def act(self, batch: Any) -> np.ndarray:
        from atdrone.envs.kinematics import turn_towards

        poses = batch.poses
        P = len(poses.heading[0]) - 2
        out = []
        for slot in batch.slot:
            others = [i for i in range(P) if i != slot]
            target = poses.pos[0, others].mean(0)
            d = target - poses.pos[0, slot]
            out.append(turn_towards(poses.heading[0, slot], np.arctan2(d[1], d[0])))
        return np.array(out, dtype=float)

    def reset(self, done: np.ndarray) -> None:
        pass


def test_drones_steered_at_each_other_never_touch_ellipsoids(
    tmp_path: Path, registry_member: tuple[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from atdrone.deploy import job
    from atdrone.deploy.loop import Team

    monkeypatch.setattr(job, "build_team", lambda cfg: (Team(Attract(), [Attract(), Attract()]), "attract"))
    result = fly(tmp_path, registry_member, episodes=2, horizon=50)
    frame = ticks(result)
    assert frame.events.str.contains("separation").any()  # the shield had work to do
    assert min_scaled_separation(frame) >= 1.0
    assert set(end_states(frame).values()) == {"landed"}


class Chase:
    """A policy steering pursuers 0, 2 at evader 0 and 1, 3 at evader 1 (the nearest free one once theirs is
    captured), around the end of 4p2e1o's bar
    (x 1.0-2.5 at y 2.5) nearer to it when the bar is in between."""

    name = "chase"

    def act(self, batch: Any) -> np.ndarray:
        from atdrone.envs.kinematics import turn_towards

        poses = batch.poses
        P = len(poses.heading[0]) - 2
        free = np.flatnonzero(~poses.captured[0]) + P
        out = []
        for slot in batch.slot:
            d = poses.pos[0, free] - poses.pos[0, slot]
            if not len(d):
                out.append(0.0)
                continue
            me = poses.pos[0, slot]
            mine = P + slot % 2  # two pursuers on each evader, then all on the one left
            target = poses.pos[0, mine] if mine in free else me + d[np.argmin(np.hypot(d[:, 0], d[:, 1]))]
            if (me[1] - 2.5) * (target[1] - 2.5) < 0:  # on the other side of the bar's row: past an end first
                x = me[0] + (target[0] - me[0]) * (2.5 - me[1]) / (target[1] - me[1])
                if 0.8 < x < 2.7:
                    target = np.array([0.5 if me[0] + x < 3.5 else 3.1, 2.5])
            step = target - me
            out.append(turn_towards(poses.heading[0, slot], np.arctan2(step[1], step[0])))
        return np.array(out, dtype=float)

    def reset(self, done: np.ndarray) -> None:
        pass


def held_at_an_evader_without_capture(frame: pd.DataFrame, near: float = 0.55) -> int:
    """Ticks on the policy legs where the separation rule held a flying evader drone together with a pursuer
    (the log's ``pair:`` note) within ``near`` of it, and the evader did not begin to land (its capture) within
    the next two ticks."""
    legs = frame[frame.step >= 0]
    grid = legs.pivot_table(index=["episode", "step"], columns="drone", values=["x", "y"])
    state = legs.pivot_table(index=["episode", "step"], columns="drone", values="state", aggfunc="first")
    roles = legs.groupby("drone").role.first()
    count = 0
    for e in roles.index[roles == "evader"]:
        for p in roles.index[roles != "evader"]:
            d = np.hypot(grid["x"][e] - grid["x"][p], grid["y"][e] - grid["y"][p])
            mine = legs[legs.drone == e]
            held = mine.events.str.split(",").apply(lambda ev, p=p: f"pair:{p}" in ev)
            together = held.groupby([mine.episode, mine.step]).any().reindex(d.index, fill_value=False)
            both = together & (d <= near) & (state[e] == "flying")
            for episode, step in both.index[both.to_numpy(bool)]:
                later = state[e].loc[episode].loc[step + 1 : step + 2]
                count += not (later == "landing").any()
    return count


def test_pursuers_steered_at_evader_drones_capture_them_and_every_pair_stays_apart(
    tmp_path: Path, registry_member: tuple[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The shield keeps every pair 0.25 m apart, beyond the task's 0.2 m capture range: a pursuer that the
    separation rule stops at an evader drone has captured it (before, it was held there and no capture could
    happen). A captured drone lands and takes off again for the next episode while the others keep flying,
    and the transit there leads around the bar."""
    from atdrone.deploy import job
    from atdrone.deploy.loop import Team

    monkeypatch.setattr(job, "build_team", lambda cfg: (Team(Chase(), [Chase(), Chase()]), "chase"))
    result = fly(tmp_path, registry_member, episodes=2, horizon=300)
    assert not result.ended_early and result.episodes_flown == 2, result.ended_early
    episodes = pd.read_parquet(result.log_dir / "episodes.parquet")
    assert episodes.captured.iloc[0] >= 1, episodes  # the second episode's (re)start is checked below
    frame = ticks(result)
    assert min_scaled_separation(frame) >= 1.0  # pursuers and evader drones alike, captures included
    separated = frame[frame.events.str.contains("separation")]
    assert len(separated) and separated.events.str.contains("pair:").all()  # whom each was held with is logged
    assert held_at_an_evader_without_capture(frame) == 0
    # while a captured evader drone took off again, the drones in the air kept their setpoints and altitude
    retook = frame[(frame.episode == 1) & (frame.step < 0) & (frame.state == "taking_off")]
    assert len(retook), "no captured evader drone took off again"
    # ... through a column no drone in the air was near: those hovering beside it were flown off it first
    for t, up in retook.groupby("t"):
        air = frame[(frame.t == t) & (frame.state == "flying")]
        for _, d in up.iterrows():
            assert np.hypot(air.x - d.x, air.y - d.y).min() >= COLUMN_CLEAR - 0.05, (t, d.drone)
    flying = frame[frame.state == "flying"]
    assert flying.z.min() > 0.4, flying.loc[flying.z.idxmin()]
    landed_before_any_stop(result, frame)


# ---------------------------------------------------------------- preflight
@pytest.mark.parametrize(
    ("changes", "failed"),
    [
        ({"radio": {"pose": "extpos", "reset_estimator": False, "toc_cache": str(TOC_CACHE)}}, {"estimate"}),
        ({"sim": {"clock_rate": RATE, "true_frame": {"origin": [0.3, 0.0, 0.0]}}}, {"frame"}),
        ({"sim": {"clock_rate": RATE, "true_frame": {"origin": [0.0, -0.3, 0.0]}}}, {"frame"}),
        ({"sim": {"clock_rate": RATE, "true_frame": {"yaw_offset_deg": 90.0}}}, {"frame", "heading"}),
        ({"sim": {"clock_rate": RATE, "true_frame": {"axes": ["-y", "x", "z"]}}}, {"frame"}),
    ],
    ids=["estimator-yaw-left-at-0", "origin-x+0.3", "origin-y-0.3", "yaw-offset-90", "swapped-axes"],
)
def test_preflight_refuses(
    tmp_path: Path, registry_member: tuple[str, str], changes: dict[str, Any], failed: set[str]
) -> None:
    result = fly(tmp_path, registry_member, arm=True, **changes)
    assert not result.preflight.ok and not result.flown
    bad = {c.name for c in result.preflight.checks if not c.ok}
    assert failed <= bad, result.preflight.text()
    assert result.sent.get("arming", 0) == 0


# ---------------------------------------------------------------- the CLI
def test_cli_dry_run_report_and_an_early_end(
    tmp_path: Path, registry_member: tuple[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    doc = sim_doc(tmp_path, registry_member)
    path = tmp_path / "deploy.json"
    path.write_text(json.dumps(doc))
    assert cli_main(["deploy", str(path)]) == 0
    out = capsys.readouterr().out
    assert "dry run: nothing armed" in out and "plan: fly member" in out
    assert cli_main(["deploy", str(path), "--arm", "--tracking-uri", f"sqlite:///{tmp_path / 'm.db'}"]) == 0
    logs = sorted((tmp_path / "flights").iterdir())
    assert len(logs) == 1
    capsys.readouterr()
    assert cli_main(["deploy", "report", str(logs[0])]) == 0
    assert "SUC" in capsys.readouterr().out
    assert cli_main(["deploy", "report", str(tmp_path / "nothing")]) == 2
    # an armed flight that ends early: a one-line reason, a non-zero exit, the log still written
    path.write_text(json.dumps(dict(doc, horizon=80, faults=[{"kind": "exception", "at": FAULT_AT}])))
    assert cli_main(["deploy", str(path), "--arm", "--tracking-uri", f"sqlite:///{tmp_path / 'm.db'}"]) == 1
    captured = capsys.readouterr()
    assert "flight ended early after 0/1 episode(s): InjectedFault" in captured.err
    assert len(list((tmp_path / "flights").iterdir())) == 2
    bad = dict(doc, episodes=0)
    path.write_text(json.dumps(bad))
    assert cli_main(["deploy", str(path)]) == 2
    assert "episodes: must be > 0" in capsys.readouterr().err


def test_a_collection_that_holds_the_interpreter_past_the_radio_timeout_loses_no_link(
    tmp_path: Path, registry_member: tuple[str, str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The flight's one full collection (the heap is then frozen) holds the interpreter: every thread stands still.
    A long one (a large heap on a slow host) must come before any link is open: with links open, a send waiting
    on the radio's one-packet queue when it starts gives up 2 s later (cflib's radio driver), cflib drops that
    link and the drone cannot arm. Here the collection holds the interpreter 2.5 s, and, where links are open, the
    radio is first jammed for 0.3 s so that a send surely waits (the pose stream sends 50 times a second)."""
    from atdrone.deploy.simradio import _RADIOS

    hold = 2.5  # s, past the radio driver's 2 s
    held: list[int] = []  # the open links at the start of each long collection
    collect = gc.collect

    def slow_collect(*args: Any) -> int:
        if not held:  # the flight's collection
            radios = [r for r in _RADIOS.values() if r.links]
            held.append(sum(len(r.links) for r in radios))
            for r in radios:
                r.jam(0.3)
            time.sleep(0.2)  # the interpreter free: the senders run into the jammed radio
            ctypes.PyDLL(None).usleep(int(hold * 1e6))  # PyDLL keeps the interpreter through the call
        return collect(*args)

    monkeypatch.setattr(gc, "collect", slow_collect)
    result = fly(tmp_path, registry_member, horizon=20)
    assert result.flown and not result.ended_early, result.ended_early
    assert held == [0], f"the flight's full collection came with {held} links open"
    assert result.episodes_flown == 1
