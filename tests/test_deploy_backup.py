"""A partner drone dropped alone, and a backup drone that takes its slot.

The pure pieces by hand (the config's ``backups``, the choice of a pose-safe spawn, which
faults drop a drone alone), then flights of the shipped sim configs
(configs/deploy/sim_4p2e1o.json and sim_4p2e1o_backup.json) with every threshold as
shipped: a partner's low battery lands it alone while the episode goes on; a backup takes
its slot at a pose-safe spawn; a learner's low battery still lands everyone; a backup's own
fault leaves the slot empty.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from test_deploy import (  # noqa: F401  (the fixtures)
    FAULT_AT,
    ROOT,
    _mlflow_db,
    busy_host,
    end_states,
    landed_softly,
    min_scaled_separation,
    registry_member,
    sim_doc,
    ticks,
)
from test_deploy_health import tick

from atdrone.config import ConfigError, load_task
from atdrone.deploy.backup import JOIN_ARRIVED, Backups, backup_spawn
from atdrone.deploy.clock import ScaledClock
from atdrone.deploy.config import load_deploy
from atdrone.deploy.flightlog import format_summary
from atdrone.deploy.job import run_deploy
from atdrone.deploy.reactions import drops
from atdrone.deploy.shield import Action, Obstacles, ShieldConfig, ellipsoid_distance, geofence, shield
from atdrone.deploy.team import Team
from atdrone.deploy.transit import MARGIN

BACKUP = json.loads((ROOT / "configs" / "deploy" / "sim_4p2e1o_backup.json").read_text())
TASK = load_task("4p2e1o")
CFG = ShieldConfig()
BAR = Obstacles(np.array([[1.75, 2.5, 0.75, 0.05]]))  # 4p2e1o's bar: centre x, y, half sizes
FENCE = geofence((3.6, 5.0), CFG.margin)


# ---------------------------------------------------------------- the config
def test_backup_config_errors_are_one_line_and_name_the_json_path(
    tmp_path: Path,
    registry_member: tuple[str, str],  # noqa: F811
) -> None:
    doc = sim_doc(tmp_path, registry_member, backups=BACKUP["backups"])
    cfg = load_deploy(doc)
    assert [(d.name, d.role) for d in cfg.fleet()][-1] == ("cf7", "backup")
    bad = {
        "backups[0].name: 'cf3' is already a partner drone": [{"name": "cf3"}],
        "backups[0].name: 'cf1' is already a learner drone": [{"name": "cf1"}],
        "backups[1].name: duplicate backup name 'cf7'": [{"name": "cf7"}, {"name": "cf7"}],
        "backups[0].replaces: no partner drone 'cf9' (partner drones: cf3, cf4)": [
            {"name": "cf7", "replaces": ["cf9"]}
        ],
        "backups[0].replaces: no partner drone 'cf1'": [{"name": "cf7", "replaces": ["cf1"]}],
        "backups[0].body: rigid body 'cf2' is already cf2's": [{"name": "cf7", "body": "cf2"}],
    }
    for message, backups in bad.items():
        with pytest.raises(ConfigError) as err:
            load_deploy({**doc, "backups": backups})
        assert str(err.value).startswith(message) and "\n" not in str(err.value), str(err.value)
    radio = [{**d, "uri": f"radio://0/80/2M/E7E7E7E7E{i}"} for i, d in enumerate(doc["drones"])]
    with pytest.raises(ConfigError, match=r"^backups\[0\]\.uri: the cflib backend needs every backup's radio URI"):
        load_deploy({**doc, "backend": "cflib", "drones": radio})
    with pytest.raises(ConfigError, match=r"^faults\[0\]\.drone: no drone 'cf8'"):
        load_deploy({**doc, "faults": [{"kind": "low_battery", "drone": "cf8", "at": 1.0}]})
    load_deploy({**doc, "faults": [{"kind": "low_battery", "drone": "cf7", "at": 1.0}]})  # a backup's fault


# ---------------------------------------------------------------- the pose-safe spawn
def slot_box(slot: int) -> tuple[np.ndarray, np.ndarray]:
    rp = TASK.players.respawn_region.pursuer
    lo = np.maximum([rp.x[0] + rp.x_step * slot, rp.y[0]], FENCE[0])
    hi = np.minimum([rp.x[1] + rp.x_step * slot, rp.y[1]], FENCE[1])
    return lo, hi


def test_a_backup_spawn_lies_in_its_slots_region_clear_of_every_drone() -> None:
    """Inside the slot's part of the pursuers' spawn region and the fence, MARGIN ellipsoids from every drone in
    the air; with the region crowded, none."""
    h = 0.5
    for slot in range(4):
        lo, hi = slot_box(slot)
        middle = (lo + hi) / 2
        others = np.array([[*middle, h], [middle[0] + 0.2, middle[1], h], [1.8, 3.5, h]])
        spot = backup_spawn(slot, TASK, others, h, CFG, FENCE, BAR)
        assert spot is not None
        assert (spot >= lo - 1e-9).all() and (spot <= hi + 1e-9).all(), (slot, spot, lo, hi)
        apart = ellipsoid_distance(others - np.r_[spot, h], CFG.drone_radius, CFG.drone_half_height)
        assert apart.min() >= MARGIN, (slot, spot, apart)
        alone = backup_spawn(slot, TASK, np.zeros((0, 3)), h, CFG, FENCE, BAR)  # nobody near: the middle
        assert alone is not None and np.hypot(*(alone - middle)) <= 0.08
    lo, hi = slot_box(2)
    crowd = np.array(
        [[x, y, h] for x in np.arange(lo[0], hi[0] + 0.3, 0.2) for y in np.arange(lo[1], hi[1] + 0.3, 0.2)]
    )
    assert backup_spawn(2, TASK, crowd, h, CFG, FENCE, BAR) is None
    # a drone far above or below (on the floor, say) is a different layer: it does not crowd the region
    assert backup_spawn(2, TASK, crowd - np.r_[0.0, 0.0, 2.0], h, CFG, FENCE, BAR) is not None


# ---------------------------------------------------------------- which faults drop a drone alone
def test_a_partners_battery_or_lost_link_drops_it_alone_and_anything_else_lands_everyone() -> None:
    apart = [[1.0, 1.0, 0.5], [2.5, 1.0, 0.5], [1.0, 4.0, 0.5]]
    partner = np.array([False, True, False])  # b flies a partner slot
    low = tick(apart, battery=np.array([4.0, 3.2, 4.0]))
    assert drops(shield(low, CFG), partner) == {"b": "battery"}
    assert drops(shield(low, CFG), np.zeros(3, dtype=bool)) == {}  # a learner's: not dropped
    assert drops(shield(replace_(low, stop_requested=True), CFG), partner) == {}  # a signal lands everyone
    lost = tick(apart, link_age=np.array([0.05, 0.9, 0.05]))
    alone = shield(replace_(lost, alone=partner), CFG)
    assert list(alone.action) == [Action.TRACK, Action.LOST, Action.TRACK]  # the others fly on
    assert drops(alone, partner) == {"b": "link_lost"}
    everyone = shield(lost, CFG)  # a learner (not alone) lost: every other drone lands, as before
    assert list(everyone.action) == [Action.LAND, Action.LOST, Action.LAND]
    assert drops(everyone, np.zeros(3, dtype=bool)) == {}


def replace_(inp: Any, **changes: Any) -> Any:
    from dataclasses import replace

    return replace(inp, **changes)


# ---------------------------------------------------------------- flights
def fly_doc(tmp_path: Path, doc: dict[str, Any]) -> Any:
    result = run_deploy(load_deploy(doc), arm=True, tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}", say=print)
    print(f"ended early: {result.ended_early!r}; {result.endings}")
    for n, v in (result.fleet or {}).items():
        print(n, "true", np.round(v["pos"], 3), "stopped by", v["history"], "impacts", v["impacts"][-2:])
    return result


def first(frame: pd.DataFrame, drone: str, mask: pd.Series) -> float:
    return float(frame[(frame.drone == drone) & mask].t.min())


def test_a_partners_low_battery_lands_it_alone_and_the_episode_flies_on(
    tmp_path: Path,
    registry_member: tuple[str, str],  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """cf3 (a partner) at 3.2 V: it lands alone, the others fly the episode to its own end, every drone lands;
    from the drop on, every observation masks its slot as a teammate beyond range (its own row zero, its teammate
    block in every other row zero), as the simulator's drop event does."""
    seen: list[np.ndarray] = []
    act = Team.act

    def record(self: Team, obs: np.ndarray, *args: Any) -> np.ndarray:
        seen.append(obs[0].copy())
        return act(self, obs, *args)

    monkeypatch.setattr(Team, "act", record)
    doc = sim_doc(tmp_path, registry_member, horizon=120)
    doc["faults"] = [{"kind": "low_battery", "drone": "cf3", "volts": 3.2, "at": FAULT_AT}]
    result = fly_doc(tmp_path, doc)
    frame = ticks(result)
    assert not result.ended_early and result.episodes_flown == 1
    episodes = pd.read_parquet(result.log_dir / "episodes.parquet")
    assert episodes.outcome.iloc[0] in ("captured", "timeout", "collision"), episodes
    landed_softly(result)
    cf3_down = first(frame, "cf3", frame.state == "landed")
    others = frame[(frame.t == frame[frame.t >= cf3_down].t.min()) & (frame.drone != "cf3")]
    assert (others.state == "flying").all(), others[["drone", "state"]]  # cf3 landed while the others flew
    steps = frame[(frame.step >= 0) & (frame.t > cf3_down)]
    assert steps.step.nunique() > 10, "the episode did not go on after the drop"
    change = result.summary["team_changes"]
    assert [(c["drone"], c["slot"], c["why"], c["backup"]) for c in change] == [("cf3", 2, "battery", "")]
    # the masking: after the drop, slot 2 sees nothing and nobody sees it
    masked = [obs for obs in seen if not obs[2].any()]
    assert len(masked) > 10, "the dropped slot was never masked"
    E = 2
    for obs in masked:
        mates = obs.reshape(4, -1, 4)[:, E + 1 :]  # (P, P - 1, 4) teammate blocks
        for k in (0, 1, 3):  # slot 2 is the second teammate block of slots 0 and 1, the third of slot 3
            assert not mates[k, 1 if k < 2 else 2].any(), (k, mates[k])
        assert obs[[0, 1, 3]].any(1).all()


def test_a_backup_takes_the_dropped_slot_at_a_pose_safe_spawn_on_a_busy_host(
    tmp_path: Path,
    registry_member: tuple[str, str],  # noqa: F811
    busy_host: None,  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The shipped backup config, cf3's battery low as the episode begins, beside a busy loop: cf3 lands alone, cf7
    takes off, flies to a spawn inside slot 2's region clear of every drone and takes the slot (its memory reset);
    no pair's ellipsoids ever touch; every drone ends on the floor, landed; the flight log and its report say so.

    The battery runs low at the episode's start, not at a flight time: a drop before the episode (while the
    drones fly to their spawns, which takes longer on a busier host) can put the backup in the air before the
    episode begins, and such a backup takes its slot at once, wherever it is (tests/test_deploy_team_log.py)."""
    from atdrone.deploy import job

    fleets: list[Any] = []
    schedule, draw = job._schedule, Team.draw

    def keep_fleet(cfg: Any, faults: Any, fleet: Any, *args: Any) -> None:
        fleets.append(fleet)
        schedule(cfg, faults, fleet, *args)

    def battery_low_at_start(self: Team, rng: np.random.Generator) -> list[Any]:
        fleets[0].set_battery("cf3", 3.2)
        return draw(self, rng)

    monkeypatch.setattr(job, "_schedule", keep_fleet)
    monkeypatch.setattr(Team, "draw", battery_low_at_start)
    doc = sim_doc(tmp_path, registry_member, horizon=150, backups=BACKUP["backups"], name=BACKUP["name"])
    result = fly_doc(tmp_path, doc)
    frame = ticks(result)
    assert not result.ended_early and result.episodes_flown == 1
    landed_softly(result)
    assert set(result.endings) == {f"cf{i}" for i in range(1, 8)}
    assert min_scaled_separation(frame) >= 1.0
    (change,) = result.summary["team_changes"]
    assert change["drone"] == "cf3" and change["why"] == "battery" and change["backup"] == "cf7"
    assert change["memory_reset"] and change["took_slot_t"] > change["t"], change
    took = frame[frame.events.str.contains("took_slot:2")]
    assert list(took.drone) == ["cf7"] and abs(float(took.t.iloc[0]) - change["took_slot_t"]) < 1e-6
    dropped = frame[frame.events.str.contains("dropped:battery")]  # the drop's row is its record's tick too
    assert list(dropped.drone) == ["cf3"] and abs(float(dropped.t.iloc[0]) - change["t"]) < 1e-6
    assert int(dropped.step.iloc[0]) >= 0 and int(took.step.iloc[0]) > 0  # both in the episode: seated on arrival
    at = frame[frame.t == took.t.iloc[0]].set_index("drone")
    spot = at.loc["cf7", ["x", "y"]].to_numpy(np.float64)
    lo, hi = slot_box(2)
    assert (spot >= lo - JOIN_ARRIVED).all() and (spot <= hi + JOIN_ARRIVED).all(), spot
    air = at[at.state.isin(("taking_off", "flying", "landing")) & (at.index != "cf7")]
    xyz = ["x", "y", "z"]
    apart = ellipsoid_distance(air[xyz].to_numpy(np.float64) - at.loc["cf7", xyz].to_numpy(np.float64), 0.125, 0.375)
    assert apart.min() >= 1.1, apart
    # the backup flew the slot: after taking it, it moved with the episode's steps
    flown = frame[(frame.drone == "cf7") & (frame.t > change["took_slot_t"]) & (frame.step >= 0)]
    assert len(flown) > 10 and np.ptp(flown.x) + np.ptp(flown.y) > 0.2
    assert (frame[(frame.drone == "cf7") & (frame.t < change["t"])].state == "idle").all()
    report = format_summary(result.summary)
    assert "team change: cf3 (slot 2) dropped at t = " in report and "backup cf7 took the slot" in report
    assert "its memory reset" in report


def test_a_learners_low_battery_still_lands_everyone_and_the_backup_stays_down(
    tmp_path: Path,
    registry_member: tuple[str, str],  # noqa: F811
) -> None:
    doc = sim_doc(tmp_path, registry_member, horizon=80, backups=BACKUP["backups"])
    doc["faults"] = [{"kind": "low_battery", "drone": "cf2", "volts": 3.2, "at": FAULT_AT}]
    result = fly_doc(tmp_path, doc)
    frame = ticks(result)
    assert result.ended_early.startswith("shield: battery") and "not landed" not in result.ended_early
    landed_softly(result)
    assert (frame[frame.drone == "cf7"].state == "idle").all() and result.fleet["cf7"]["pos"][2] == 0.0
    assert result.summary["team_changes"] == []


def test_a_backup_dropped_on_its_way_lands_and_the_slot_stays_empty(
    tmp_path: Path,
    registry_member: tuple[str, str],  # noqa: F811
) -> None:
    """The backup's own battery runs low (on the floor: it shows once it takes off): it is landed at once, nothing
    else is, the slot stays empty and the flight flies its episode."""
    doc = sim_doc(tmp_path, registry_member, horizon=120, backups=BACKUP["backups"])
    doc["faults"] = [
        {"kind": "low_battery", "drone": "cf3", "volts": 3.2, "at": FAULT_AT},
        {"kind": "low_battery", "drone": "cf7", "volts": 3.2, "at": FAULT_AT},
    ]
    result = fly_doc(tmp_path, doc)
    frame = ticks(result)
    assert not result.ended_early and result.episodes_flown == 1
    landed_softly(result)
    (change,) = result.summary["team_changes"]
    assert change["backup"] == "cf7" and change["took_slot_t"] is None and "dropped (battery)" in change["backup_end"]
    assert not frame.events.str.contains("took_slot").any()
    cf7 = frame[frame.drone == "cf7"]
    assert cf7.events.str.contains("backup_takeoff").any() and cf7.events.str.contains("dropped:battery").any()
    assert end_states(frame)["cf7"] == "landed"


def test_a_partners_lost_link_leaves_it_to_its_watchdog_and_the_others_fly_on(
    tmp_path: Path,
    registry_member: tuple[str, str],  # noqa: F811
) -> None:
    """cf4 (a partner) loses its link for good: it gets the land command every tick and its firmware's watchdog
    cuts it (reported lost, exit 1), while the others fly the episode to its end and land."""
    doc = sim_doc(tmp_path, registry_member, horizon=120)
    doc["faults"] = [{"kind": "link_loss", "drone": "cf4", "at": FAULT_AT}]
    result = fly_doc(tmp_path, doc)
    frame = ticks(result)
    assert result.episodes_flown == 1 and result.ended_early.startswith("not landed: cf4 lost"), result.ended_early
    assert result.endings["cf4"].startswith("lost")
    assert "estop_watchdog" in {w for _, w in result.fleet["cf4"]["history"]}
    landed_softly(result, exclude=("cf4",))
    lost_at = first(frame, "cf4", frame.state == "lost")
    assert frame[(frame.t > lost_at) & (frame.step >= 0)].step.nunique() > 10
    assert [c["why"] for c in result.summary["team_changes"]] == ["link_lost"]


def test_a_backup_called_late_in_an_episode_takes_the_slot_for_the_next(
    tmp_path: Path,
    registry_member: tuple[str, str],  # noqa: F811
) -> None:
    """Short episodes: the backup is called at step 20 of the first (of 30 steps, whatever the host's pace) and is
    still on its way when it ends; between episodes it takes the slot and the transit flies it to the slot's spawn;
    the second episode is flown with it; every drone lands, apart."""
    doc = sim_doc(tmp_path, registry_member, horizon=30, episodes=2, backups=BACKUP["backups"])
    doc["faults"] = [{"kind": "low_battery", "drone": "cf4", "volts": 3.2, "at": 0.0, "step": 20}]
    result = fly_doc(tmp_path, doc)
    frame = ticks(result)
    assert not result.ended_early and result.episodes_flown == 2
    landed_softly(result)
    assert min_scaled_separation(frame) >= 1.0
    fired = frame[frame.events.str.contains("fault:low_battery")]
    assert list(zip(fired.episode, fired.step, strict=True)) == [(0, 20)], fired[["t", "episode", "step", "drone"]]
    (change,) = result.summary["team_changes"]
    assert change["drone"] == "cf4" and change["backup"] == "cf7" and change["took_slot_episode"] == 1, change
    took = frame[frame.events.str.contains("took_slot:3")]
    assert list(took.drone) == ["cf7"] and (took.step == -1).all()  # between episodes, not in one
    assert abs(float(took.t.iloc[0]) - change["took_slot_t"]) < 1e-6  # in a tick of its own, the one it names
    flown = frame[(frame.drone == "cf7") & (frame.episode == 1) & (frame.step >= 0)]
    assert len(flown) >= 20 and (flown.state == "flying").all()


class _Flight(Backups):
    """The backups' part of a flight with nothing behind it: commands and states recorded."""

    def __init__(self, cfg: Any) -> None:
        self.cfg, self.task, self.shield_cfg = cfg, TASK, cfg.shield
        self.pursuers, self.evader_drones = ["cf1", "cf2", "cf3", "cf4"], ["cf5", "cf6"]
        self.names = [*self.pursuers, *self.evader_drones, "cf7"]
        self.partner_slots = np.array([2, 3])
        self.state = dict.fromkeys(self.names, "flying") | {"cf7": "idle"}
        self.notes: dict[str, list[str]] = {}
        self.hold_at = np.full((7, 3), np.nan)
        self.prev_setpoint = np.full((7, 3), np.nan)
        self.said: list[str] = []
        self.progress = self.said.append
        self.episode, self.t0, self.tick_t, self.dt = 0, 0.0, 5.0, 0.1
        self.landed: list[str] = []
        self.clock = ScaledClock(1.0)
        self._init_backups()

    def _land(self, names: Any) -> None:
        self.landed += list(names)
        self._set_state(names, "landing")

    def _set_state(self, names: Any, state: str) -> None:
        for n in names:
            self.state[n] = state


def test_a_backup_too_low_after_its_takeoff_lands_and_the_slot_stays_empty(
    tmp_path: Path,
    registry_member: tuple[str, str],  # noqa: F811
) -> None:
    flight = _Flight(load_deploy(sim_doc(tmp_path, registry_member, backups=BACKUP["backups"])))
    flight._drop("cf3", "battery")
    assert flight.landed == ["cf3"] and not flight.present[2] and flight._alone()[2]
    (join,) = flight.joins
    assert join.drone == "cf7" and join.slot == 2
    join.phase = "takeoff"
    flight.state["cf7"] = "taking_off"
    pos = np.zeros((7, 3))
    pos[6, 2] = 0.1  # it rose 0.1 m of the 0.5 m
    assert not flight._risen(join, pos)
    assert flight.landed == ["cf3", "cf7"] and flight.joins == [] and not flight.present[2]
    assert "failed its takeoff (at 0.10 m)" in flight.team_changes[0]["backup_end"]
    assert flight.team_changes[0]["took_slot_t"] is None and "cf7" in flight.retired
    flight._drop("cf4", "battery")  # the only backup is spent: the next dropped slot stays empty
    assert flight.joins == [] and flight.team_changes[1]["backup"] == ""
