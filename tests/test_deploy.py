"""The deploy job end to end on the sim backend: real cflib against the simulated fleet.

Every flight flies the shipped config (configs/deploy/sim_4p2e1o.json) unchanged: its
scaled clock (two simulated seconds per wall second), the radio model with lost and
retried packets, the shield's and the heartbeat's thresholds; a test changes only the
member (a registry entry), the horizon, the faults and where the log goes. The checks
read the flight log the job wrote, what the simulated firmware saw (its counters, what
stopped its motors and when, every impact with the floor, its true height) and the
preflight's findings. The fault flights run beside two busy-looping processes.
"""

from __future__ import annotations

import gc
import json
import os
import shlex
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from atdrone.cli import main as cli_main
from atdrone.config import ConfigError
from atdrone.deploy.config import load_deploy
from atdrone.deploy.job import run_deploy
from atdrone.deploy.loop import COLUMN_CLEAR, StopRequest
from atdrone.deploy.shield import geofence

ROOT = Path(__file__).resolve().parent.parent
CHECKPOINT = next(
    p
    for p in (
        ROOT / "configs" / "zoos" / "checkpoints" / "4p2e1o" / "sp_high.pt",
        ROOT / "configs" / "zoos" / "checkpoints" / "sp_high.pt",
    )
    if p.is_file()
)
SHIPPED = json.loads((ROOT / "configs" / "deploy" / "sim_4p2e1o.json").read_text())
RATE = SHIPPED["sim"]["clock_rate"]  # the simulated clock's speed: a host's pause costs the drones RATE x its length
TOC_CACHE = Path(tempfile.gettempdir()) / "atdrone-test-toc"
AIRBORNE = ("taking_off", "flying", "landing")


@pytest.fixture(autouse=True)
def _mlflow_db(tmp_path: Path, mlflow_store: Callable[[Path], str]) -> None:
    """The flights' MLflow store (``tmp_path / "mlflow.db"``), made with its schema."""
    mlflow_store(tmp_path / "mlflow.db")


@pytest.fixture(scope="module")
def registry_member(tmp_path_factory: pytest.TempPathFactory) -> tuple[str, str]:
    """A registry file holding one member (the sp_high checkpoint) and that member's id."""
    from atdrone.registry import Registry

    db = tmp_path_factory.mktemp("registry") / "registry.db"
    with Registry(db) as reg:
        member = reg.add_checkpoint(CHECKPOINT, run="deploy-test", generation=0)
    return str(db), member


def sim_doc(tmp_path: Path, registry_member: tuple[str, str], **changes: Any) -> dict[str, Any]:
    db, member = registry_member
    doc = json.loads(json.dumps(SHIPPED))
    assert "radio" not in doc and "shield" not in doc  # the shipped config keeps every default: so do the tests
    doc.update(member={"registry": db, "id": member}, horizon=40, out_dir=str(tmp_path / "flights"))
    doc["radio"] = {"toc_cache": str(TOC_CACHE)}  # where cflib caches the tables (no threshold)
    doc.update(changes)
    return doc


def fly(
    tmp_path: Path, registry_member: tuple[str, str], arm: bool = True, stop: StopRequest | None = None, **changes: Any
):
    cfg = load_deploy(sim_doc(tmp_path, registry_member, **changes))
    result = run_deploy(cfg, arm=arm, tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}", say=print, stop=stop)
    print(f"ended early: {result.ended_early!r}")  # shown with a failure
    for n, v in (result.fleet or {}).items():
        print(n, "true", np.round(v["pos"], 3), "stopped by", v["history"], "impacts", v["impacts"][-2:])
    return result


def ticks(result: Any) -> pd.DataFrame:
    return pd.read_parquet(result.log_dir / "flight.parquet")


def end_states(frame: pd.DataFrame) -> dict[str, str]:
    physical = frame[frame.state != "virtual"]
    return physical.groupby("drone")["state"].last().to_dict()


class Closest(float):
    """A scaled separation that says, when an assertion shows it, where it happened."""

    where: str

    def __repr__(self) -> str:
        return f"{float(self)!r} ({self.where})"


def min_scaled_separation(frame: pd.DataFrame, radius: float = 0.125, half_height: float = 0.375) -> Closest:
    """The smallest scaled ellipsoid distance between two airborne drones at one tick (< 1: they touched),
    with the tick, the pair, their states and the shield's events around it for a failure's message."""
    air = frame[frame.state.isin(AIRBORNE)]
    grid = air.groupby(["t", "drone"])[["x", "y", "z"]].first().unstack("drone")
    names = list(grid["x"].columns)
    pos = np.stack([grid[c][names].to_numpy(np.float64) for c in "xyz"], -1)
    delta = (pos[:, :, None] - pos[:, None]) / np.array([2 * radius, 2 * radius, 2 * half_height])
    scaled = np.sqrt((delta**2).sum(-1))
    scaled[:, np.arange(len(names)), np.arange(len(names))] = np.inf
    scaled = np.where(np.isfinite(scaled), scaled, np.inf)
    k, a, b = np.unravel_index(int(np.argmin(scaled)), scaled.shape)
    t = float(grid.index[k])
    pair = frame[frame.drone.isin([names[a], names[b]]) & frame.t.between(t - 1.0, t + 0.2)]
    cols = ["t", "step", "drone", "state", "x", "y", "z", "setpoint_x", "setpoint_y", "events", "latency_tick"]
    cols = [c for c in cols if c in frame.columns]
    out = Closest(scaled[k, a, b])
    out.where = f"t={t:.2f}, {names[a]}-{names[b]}; the second before:\n{pair[cols].to_string()}"
    return out


def stops(result: Any, why: str) -> dict[str, float]:
    """Per drone, the first clock time (since the flight began) the simulated firmware stopped it for ``why``."""
    return {
        n: min(t for t, w in v["history"] if w == why) - result.t0
        for n, v in result.fleet.items()
        if any(w == why for _, w in v["history"])
    }


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


# ---------------------------------------------------------------- faults
IMPACT = 0.5  # m/s: the fastest a drone may meet the floor to count as landed
FAULT_AT = 6.0  # s into the flight: after the takeoff, on the way to the spawn or in the episode


@pytest.fixture
def busy_host() -> Iterator[None]:
    """Two processes spinning beside the flight, all on one core: the ground station (this process) shares that
    core with two busy loops, a third of it at best. That is harsher than two busy loops on a 2-core host (two
    thirds of a core each), the same on any machine, and leaves the other cores to the suite's other tests,
    which two loops free to roam would starve. The simulated fleet, the drones' own hardware, leaves the core
    for any (atdrone.deploy.simproc)."""
    allowed = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()
    if allowed:
        os.sched_setaffinity(0, {max(allowed)})  # inherited by the loops and everything the flight starts
    procs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    try:
        yield
    finally:
        for p in procs:
            p.kill()
            p.wait()
        if allowed:
            os.sched_setaffinity(0, allowed)


def landed_softly(result: Any, exclude: tuple[str, ...] = ()) -> None:
    """Every drone (but ``exclude``) is on the floor by its simulated true height with its motors off, met the
    floor slower than :data:`IMPACT`, and the job says it landed."""
    for n, v in result.fleet.items():
        if n in exclude:
            continue
        assert v["pos"][2] == 0.0 and not v["motors_on"], (n, v["pos"], v["history"])
        assert max((speed for _, speed, _ in v["impacts"]), default=0.0) < IMPACT, (n, v["impacts"], v["history"])
        assert result.endings[n] == "landed", result.endings


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
    schedule, new_episode = job._schedule, Team.new_episode

    def keep_fleet(cfg: Any, faults: Any, fleet: Any, *args: Any) -> None:
        fleets.append(fleet)
        schedule(cfg, faults, fleet, *args)

    def push_at_start(self: Team, rng: np.random.Generator) -> None:  # the wind rises as the episode begins
        fleets[0].push("cf1", np.array([1.0, 0.0, 0.0]))
        new_episode(self, rng)

    monkeypatch.setattr(job, "_schedule", keep_fleet)
    monkeypatch.setattr(Team, "new_episode", push_at_start)
    result = fly(tmp_path, registry_member, horizon=60)
    assert not result.ended_early
    frame = ticks(result)
    rows = frame[(frame.drone == "cf1") & (frame.step >= 20)]
    offset = np.hypot(rows.x - rows.setpoint_x, rows.y - rows.setpoint_y)
    assert offset.median() < 0.12


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
