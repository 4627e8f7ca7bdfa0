"""The safety shield, rule by rule, on hand-made ticks (numbers computed by hand), plus properties."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from atdrone.config import ConfigError, parse_document
from atdrone.deploy.shield import Action, ShieldConfig, ShieldInput, geofence, shield

CFG = ShieldConfig()  # margin .25, separation .15, max_step .3, max_speed .8 (0.08 per 0.1 s tick)
ARENA = (3.6, 5.0)


def tick(pos: Any, setpoint: Any = None, **changes: Any) -> ShieldInput:
    """A tick of drones at ``pos`` (D, 3) proposing ``setpoint`` (default: 5 cm ahead in +y), all fine."""
    pos = np.asarray(pos, dtype=float)
    D = len(pos)
    sp = pos + np.array([0.0, 0.05, 0.0]) if setpoint is None else np.asarray(setpoint, dtype=float)
    base = ShieldInput(
        dt=0.1,
        arena=ARENA,
        names=tuple(f"cf{i}" for i in range(D)),
        physical=np.ones(D, dtype=bool),
        pos=pos,
        vel=np.zeros((D, 3)),
        pose_age=np.full(D, 0.01),
        setpoint=sp,
        prev_setpoint=pos.copy(),
        battery=np.full(D, 4.0),
        link_age=np.full(D, 0.05),
        policy_latency=0.005,
        stop_requested=False,
    )
    return replace(base, **changes)


def rules(decision: Any, drone: str | None = None) -> set[str]:
    return {e.rule for e in decision.events if drone is None or e.drone == drone}


TWO_APART = [[1.0, 1.0, 0.5], [2.5, 3.0, 0.5]]


def test_a_quiet_tick_tracks_every_setpoint_unchanged() -> None:
    d = shield(tick(TWO_APART), CFG)
    assert list(d.action) == [Action.TRACK, Action.TRACK] and not d.events
    np.testing.assert_allclose(d.setpoint, np.array(TWO_APART) + np.array([0, 0.05, 0]))


def test_geofence_pulls_a_setpoint_inside() -> None:
    pos = [[3.3, 2.0, 0.5], [1.0, 1.0, 0.5]]
    d = shield(tick(pos, setpoint=[[3.37, 2.0, 0.5], [1.0, 1.05, 0.5]], prev_setpoint=np.array(pos)), CFG)
    assert d.action[0] == Action.TRACK and rules(d, "cf0") == {"geofence"}
    np.testing.assert_allclose(d.setpoint[0], [3.35, 2.0, 0.5])  # 3.6 - 0.25
    lo, hi = geofence(ARENA, 0.25)
    np.testing.assert_allclose([lo, hi], [[0.25, 0.25], [3.35, 4.75]])


def test_a_drone_outside_the_fence_lands() -> None:
    pos = [[3.55, 2.0, 0.5], [3.45, 2.0 + 1.0, 0.5]]  # 0.20 and 0.10 beyond the fence at x = 3.35 (tolerance 0.15)
    d = shield(tick(pos), CFG)
    assert d.action[0] == Action.LAND and "outside" in rules(d, "cf0")
    assert d.action[1] == Action.TRACK and "outside" not in rules(d, "cf1")


def test_step_and_speed_clamps() -> None:
    pos = [[1.0, 1.0, 0.5]]
    # 0.5 m ahead of the drone: clamped to max_step 0.3 -> (1.3, 1.0); no previous setpoint
    d = shield(tick(pos, setpoint=[[1.5, 1.0, 0.5]], prev_setpoint=np.full((1, 3), np.nan)), CFG)
    np.testing.assert_allclose(d.setpoint[0], [1.3, 1.0, 0.5])
    assert rules(d) == {"step"} and d.action[0] == Action.TRACK
    # 0.2 m from the previous setpoint in one tick: clamped to 0.8 m/s * 0.1 s = 0.08
    d = shield(tick(pos, setpoint=[[1.2, 1.0, 0.5]]), CFG)
    np.testing.assert_allclose(d.setpoint[0], [1.08, 1.0, 0.5])
    assert rules(d) == {"speed"}


def test_altitude_clamp_and_nan_setpoint_hold() -> None:
    d = shield(tick([[1.0, 1.0, 0.5]], setpoint=[[1.0, 1.05, 2.0]]), CFG)
    assert d.setpoint[0, 2] == pytest.approx(1.5) and rules(d) == {"altitude"}
    d = shield(tick([[1.0, 1.0, 0.5]], setpoint=[[np.nan, 1.0, 0.5]]), CFG)
    assert d.action[0] == Action.HOLD and rules(d) == {"nan_setpoint"}
    np.testing.assert_allclose(d.setpoint[0], [1.0, 1.0, 0.5])  # held where it is


def test_two_drones_converging_head_on_hold() -> None:
    pos = [[1.0, 2.0, 0.5], [1.2, 2.0, 0.5]]  # 0.20 apart, flying at each other: setpoints 0.14 apart
    d = shield(tick(pos, setpoint=[[1.03, 2.0, 0.5], [1.17, 2.0, 0.5]]), CFG)
    assert list(d.action) == [Action.HOLD, Action.HOLD]
    assert rules(d) == {"separation"}
    np.testing.assert_allclose(d.setpoint, pos)
    # the same distance, flying apart: no conflict
    d = shield(tick(pos, setpoint=[[0.97, 2.0, 0.5], [1.23, 2.0, 0.5]]), CFG)
    assert list(d.action) == [Action.TRACK, Action.TRACK]
    # converging by velocity: 0.25 apart closing at 0.5 m/s each -> 0.05 apart in 0.2 s
    vel = np.array([[0.5, 0, 0], [-0.5, 0, 0]])
    d = shield(tick([[1.0, 2.0, 0.5], [1.25, 2.0, 0.5]], vel=vel), CFG)
    assert list(d.action) == [Action.HOLD, Action.HOLD]


def test_virtual_drones_are_ignored_by_separation_and_fence() -> None:
    pos = [[1.0, 2.0, 0.5], [1.05, 2.0, 0.5]]
    d = shield(tick(pos, physical=np.array([True, False])), CFG)
    assert d.action[0] == Action.TRACK


@pytest.mark.parametrize(
    ("pos", "age", "expect"),
    [
        ([np.nan, 1.0, 0.5], 0.01, Action.LAND),  # NaN pose
        ([1.0, 1.0, 0.5], np.inf, Action.LAND),  # never seen
        ([1.0, 1.0, 0.5], 0.25, Action.TRACK),  # a burst of stale frames shorter than stale_pose
        ([1.0, 1.0, 0.5], 0.35, Action.LAND),  # longer
    ],
)
def test_stale_or_missing_pose_of_one_drone(pos: list[float], age: float, expect: Action) -> None:
    d = shield(tick([pos, [2.5, 3.0, 0.5]], pose_age=np.array([age, 0.01])), CFG)
    assert d.action[0] == expect and d.action[1] == Action.TRACK
    assert ("stale_pose" in rules(d, "cf0")) == (expect == Action.LAND)


def test_every_pose_stale_lands_all_then_stops_all() -> None:
    d = shield(tick(TWO_APART, pose_age=np.array([0.5, 0.6])), CFG)
    assert list(d.action) == [Action.LAND, Action.LAND] and rules(d) == {"all_stale"}
    d = shield(tick(TWO_APART, pose_age=np.array([1.2, 1.5])), CFG)  # the freshest 1.2 s > stop_after 1.0
    assert list(d.action) == [Action.STOP, Action.STOP] and rules(d) == {"mocap_lost"}


def test_link_loss_reports_the_drone_and_lands_the_others() -> None:
    d = shield(tick(TWO_APART, link_age=np.array([0.7, 0.05])), CFG)
    assert d.action[0] == Action.LOST and d.action[1] == Action.LAND
    assert d.lost() == ["cf0"] and np.isnan(d.setpoint).all()


@pytest.mark.parametrize(
    ("changes", "rule"),
    [
        ({"policy_latency": 0.6}, "policy_stall"),
        ({"stop_requested": True}, "signal"),
    ],
)
def test_whole_flight_rules_land_everyone(changes: dict[str, Any], rule: str) -> None:
    d = shield(tick(TWO_APART, **changes), CFG)
    assert list(d.action) == [Action.LAND, Action.LAND] and rules(d) == {rule}


def test_low_battery_lands_that_drone() -> None:
    d = shield(tick(TWO_APART, battery=np.array([3.3, np.nan])), CFG)
    assert d.action[0] == Action.LAND and rules(d, "cf0") == {"battery"}
    assert d.action[1] == Action.TRACK  # unknown voltage is not a fault by itself


def test_the_most_severe_rule_wins() -> None:
    # cf0: low battery (LAND) and converging (HOLD) -> LAND; every pose stale for long -> STOP beats LAND
    pos = [[1.0, 2.0, 0.5], [1.2, 2.0, 0.5]]
    d = shield(tick(pos, setpoint=[[1.03, 2.0, 0.5], [1.17, 2.0, 0.5]], battery=np.array([3.0, 4.0])), CFG)
    assert list(d.action) == [Action.LAND, Action.HOLD]
    d = shield(tick(pos, battery=np.array([3.0, 4.0]), pose_age=np.array([2.0, 2.0])), CFG)
    assert list(d.action) == [Action.STOP, Action.STOP]


def test_inputs_are_not_modified() -> None:
    inp = tick([[3.3, 2.0, 0.5]], setpoint=[[3.5, 2.0, 0.5]])
    before = inp.setpoint.copy()
    shield(inp, CFG)
    np.testing.assert_array_equal(inp.setpoint, before)


def test_config_is_validated_with_the_field_named() -> None:
    assert parse_document(ShieldConfig, {"margin": 0.3}).margin == 0.3
    with pytest.raises(ConfigError, match=r"^min_separation: must be > 0"):
        parse_document(ShieldConfig, {"min_separation": 0})
    with pytest.raises(ConfigError, match=r"^z_limits: must be \[low, high\]"):
        parse_document(ShieldConfig, {"z_limits": [1.0, 0.5]})


coord = st.floats(-1.0, 6.0, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.tuples(coord, coord, st.floats(0, 2)), min_size=1, max_size=6),
    st.lists(st.tuples(coord, coord, st.floats(-1, 3)), min_size=6, max_size=6),
)
def test_properties_on_random_ticks(pos: list[tuple[float, float, float]], sp: list[tuple[float, ...]]) -> None:
    D = len(pos)
    p = np.array(pos)
    d = shield(tick(p, setpoint=np.array(sp[:D]), prev_setpoint=np.full((D, 3), np.nan)), CFG)
    assert d.action.shape == (D,) and d.setpoint.shape == (D, 3)
    lo, hi = geofence(ARENA, CFG.margin)
    sent = (d.action == Action.TRACK) | (d.action == Action.HOLD)
    assert np.isfinite(d.setpoint[sent]).all()
    assert (d.setpoint[sent, :2] >= lo - 1e-9).all() and (d.setpoint[sent, :2] <= hi + 1e-9).all()
    track = np.flatnonzero(d.action == Action.TRACK)
    for a in range(len(track)):
        for b in range(a + 1, len(track)):
            i, j = track[a], track[b]
            assert np.hypot(*(d.setpoint[i, :2] - d.setpoint[j, :2])) >= CFG.min_separation - 1e-9
