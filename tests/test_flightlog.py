"""The flight log: a hand-built flight, its files, its summary computed by hand, its MLflow run."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from PIL import Image

from atdrone.deploy.flightlog import FILES, GIF_FRAMES, FlightLog, format_summary, log_to_mlflow, summarize

DRONES = {"a": "learner", "b": "learner", "c": "partner"}
META = {
    "name": "hand",
    "task": "4p2e1o",
    "member": "m1",
    "backend": "sim",
    "evaders": "virtual",
    "dt": 0.1,
    "arena": [3.6, 5.0],
    "drones": DRONES,
}
RNG = np.random.default_rng(0)
LATENCY = RNG.uniform(0.001, 0.02, size=(9, 2))  # per flying tick: policy, tick seconds


def hand_log() -> FlightLog:
    """Two episodes of three drones, a virtual evader, and two ground ticks.

    Airborne, a stands at (1, 1), b at (2, 1) and c at (3, 4), all at z 0.5, except at
    episode 1 step 2 where b is at (1.3, 1.4): 0.5 m from a, the closest airborne pair.
    On the ground (idle) a and b stand 0.2 m apart and the virtual evader flies 0.1 m
    from a: neither counts for the separation.
    """
    log = FlightLog(META)
    ground = {"a": (1.0, 1.0, 0.0), "b": (1.2, 1.0, 0.0), "c": (3.0, 4.0, 0.0)}
    for t in (-0.2, -0.1):
        for n, p in ground.items():
            log.tick(t, 0, -1, n, DRONES[n], np.array(p), 1.5, np.full(3, np.nan), "idle", [], 4.2, {})
    ticks = [(0, s) for s in range(5)] + [(1, s) for s in range(4)]
    for k, (episode, step) in enumerate(ticks):
        t = episode + 0.1 * step
        pos = {"a": (1.0, 1.0, 0.5), "b": (2.0, 1.0, 0.5), "c": (3.0, 4.0, 0.5)}
        if (episode, step) == (1, 2):
            pos["b"] = (1.3, 1.4, 0.5)
        events: dict[str, list[str]] = {n: [] for n in DRONES}
        if (episode, step) == (0, 2):
            events["a"], events["b"] = ["separation"], ["separation", "fence"]
        if (episode, step) == (1, 1):
            events["c"] = ["fault:link_loss", "stale_pose"]
        latency = {"policy": LATENCY[k, 0], "tick": LATENCY[k, 1]}
        for i, (n, p) in enumerate(pos.items()):
            battery = 4.1 - 0.01 * k - 0.1 * i
            setpoint = np.array(p) + 0.05
            log.tick(t, episode, step, n, DRONES[n], np.array(p), 1.5, setpoint, "flying", events[n], battery, latency)
        log.tick(t, episode, step, "virtual_e0", "evader", np.array([1.0, 1.1, 0.5]), math.nan, np.full(3, np.nan),
                 "virtual", [], math.nan, {})  # fmt: skip
    log.episode(0, "captured", 5, 2, 12.5, virtual_evaders=True)
    log.episode(1, "collision", 4, 0, -8.0, virtual_evaders=True)
    log.overrun()
    log.overrun(2)
    return log


def test_frame_columns_and_rows() -> None:
    log = hand_log()
    frame = log.frame()
    assert len(frame) == 2 * 3 + 9 * 4
    assert list(frame.columns[:15]) == [
        *("t", "episode", "step", "drone", "role", "x", "y", "z", "yaw"),
        *("setpoint_x", "setpoint_y", "setpoint_z", "state", "events", "battery"),
    ]
    assert list(frame.columns[15:]) == ["latency_policy", "latency_tick"]
    assert frame.loc[frame.state == "idle", "latency_tick"].isna().all()
    assert frame.events.map(lambda e: "separation" in e).sum() == 2
    assert list(log.episodes().columns) == ["episode", "outcome", "steps", "captured", "reward", "virtual_evaders"]
    with pytest.raises(ValueError, match="unknown flight state 'hovering'"):
        log.tick(0.0, 0, 0, "a", "learner", np.zeros(3), 0.0, np.zeros(3), "hovering", [], 4.0, {})
    with pytest.raises(ValueError, match="unknown episode outcome"):
        log.episode(2, "won", 3, 2, 1.0, False)


def test_summary_matches_hand_computed_values(tmp_path: Path) -> None:
    directory = hand_log().write(tmp_path / "flight")
    s = summarize(directory)
    assert s["ticks"] == 11 and s["episodes"] == 2 and s["flight_time"] == pytest.approx(1.5)
    assert s["outcomes"] == {"captured": 1, "collision": 1}
    assert s["SUC"] == 50.0 and s["COL"] == 50.0 and s["AST"] == 5.0 and s["REW"] == pytest.approx(2.25)
    assert math.isnan(s["AST_std"])  # one successful episode
    assert s["interventions"] == {"fence": 1, "separation": 2, "stale_pose": 1} and s["interventions_total"] == 4
    assert s["faults"] == {"link_loss": 1}
    assert s["overruns"] == 3
    assert s["min_separation"] == pytest.approx(0.5) and s["min_separation_pair"] == ["a", "b"]
    assert s["min_separation_t"] == pytest.approx(1.2)
    assert s["battery_min"] == pytest.approx({"a": 4.1 - 0.08, "b": 4.0 - 0.08, "c": 3.9 - 0.08})
    for j, stage in enumerate(("policy", "tick")):
        expected = np.percentile(LATENCY[:, j], [50, 95, 99])
        got = s["latency"][stage]
        assert [got["p50"], got["p95"], got["p99"]] == pytest.approx(expected)
        assert got["n"] == 9 and got["max"] == pytest.approx(LATENCY[:, j].max())
    # summary.json holds the same, non-finite numbers as null
    stored = json.loads((directory / "summary.json").read_text())
    assert stored["SUC"] == 50.0 and stored["AST_std"] is None and stored["latency"] == s["latency"]
    text = format_summary(s)
    for needle in ("SUC 50.0 %", "COL 50.0 %", "AST 5.0 steps", "separation 2", "min separation 0.500 m", "p99"):
        assert needle in text, text


def test_write_is_repeatable_atomic_and_complete(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    log = hand_log()
    first, second = log.write(tmp_path / "one"), log.write(tmp_path / "two")
    assert sorted(p.name for p in first.iterdir()) == sorted(FILES)  # no temp names left behind
    for name in ("flight.parquet", "episodes.parquet", "meta.json", "summary.json"):
        assert (first / name).read_bytes() == (second / name).read_bytes(), name
    pd.testing.assert_frame_equal(pd.read_parquet(first / "flight.parquet"), log.frame())
    meta = json.loads((first / "meta.json").read_text())
    assert meta["overruns"] == 3 and meta["member"] == "m1"
    assert len(meta["geometry"]["boxes"]) + len(meta["geometry"]["discs"]) == 1  # 4p2e1o's one obstacle

    with Image.open(first / "trajectories.png") as png:
        png.verify()
    with Image.open(first / "flight.gif") as gif:
        assert gif.format == "GIF" and 2 <= getattr(gif, "n_frames", 1) <= GIF_FRAMES

    # a write that fails half-way leaves the old file whole and no temp file
    def broken(self: pd.DataFrame, f, **_: object) -> None:
        f.write(b"PAR1 half a file")
        raise OSError("disk full")

    before = (first / "flight.parquet").read_bytes()
    monkeypatch.setattr(pd.DataFrame, "to_parquet", broken)
    with pytest.raises(OSError, match="disk full"):
        log.write(first)
    assert (first / "flight.parquet").read_bytes() == before
    assert sorted(p.name for p in first.iterdir()) == sorted(FILES)


def test_empty_log_writes_and_summarizes(tmp_path: Path) -> None:
    directory = FlightLog({"name": "empty", "arena": [3.6, 5.0]}).write(tmp_path / "empty")
    s = summarize(directory)
    assert s["ticks"] == 0 and s["episodes"] == 0 and math.isnan(s["SUC"]) and math.isnan(s["min_separation"])
    assert "SUC -" in format_summary(s)


def test_log_to_mlflow_records_a_deploy_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mlflow_store: Callable[[Path], str]
) -> None:
    from mlflow import MlflowClient

    monkeypatch.chdir(tmp_path)  # MLflow's default artifact root is relative to the working directory
    directory = hand_log().write(tmp_path / "flight")
    uri = mlflow_store(tmp_path / "mlflow.db")
    run_id = log_to_mlflow(directory, uri, "hand-flight")
    run = MlflowClient(tracking_uri=uri).get_run(run_id)
    assert run.info.run_name == "hand-flight" and run.data.tags["kind"] == "deploy"
    assert run.data.params["member"] == "m1" and run.data.params["backend"] == "sim"
    assert run.data.params["drones.a"] == "learner"
    m = run.data.metrics
    assert m["deploy/SUC"] == 50.0 and m["deploy/COL"] == 50.0 and m["deploy/AST"] == 5.0
    assert m["deploy/interventions"] == 4 and m["deploy/interventions/separation"] == 2
    assert m["deploy/min_separation"] == pytest.approx(0.5) and m["deploy/overruns"] == 3
    assert m["deploy/latency/tick_p99"] == pytest.approx(np.percentile(LATENCY[:, 1], 99))
    artifacts = {a.path for a in MlflowClient(tracking_uri=uri).list_artifacts(run_id)}
    assert artifacts == set(FILES)


def test_ground_speed_is_the_median_while_tracking_by_hand() -> None:
    """Pursuer p moves 0.03 m per 0.1 s tick (0.30 m/s) for 4 ticks, then is held 3 ticks (separation) and
    does not move; pursuer q moves 0.02 m per tick (0.20 m/s); the evader's 0.06 m per tick never counts."""
    from atdrone.deploy.flightlog import ground_speed

    rows = []
    for k in range(8):
        held = "separation" if k >= 5 else ""
        x_p = 0.03 * min(k, 4)
        rows.append(
            dict(t=0.1 * k, episode=0, step=k, drone="p", role="learner", x=x_p, y=1.0, state="flying", events=held)
        )
        rows.append(
            dict(t=0.1 * k, episode=0, step=k, drone="q", role="partner", x=0.02 * k, y=2.0, state="flying", events="")
        )
        rows.append(
            dict(t=0.1 * k, episode=0, step=k, drone="e", role="evader", x=0.06 * k, y=3.0, state="flying", events="")
        )
    flight = pd.DataFrame(rows)
    # p: 4 tracking intervals at 0.30 and one (4 -> 5, the second tick held) excluded, the rest held;
    # q: 7 intervals at 0.20 -> the median of [0.3] * 4 + [0.2] * 7 is 0.20
    assert ground_speed(flight) == pytest.approx(0.20)
    assert ground_speed(flight[flight.drone != "q"]) == pytest.approx(0.30)
    assert math.isnan(ground_speed(flight[flight.role == "evader"]))


def test_how_each_drone_ended_is_in_the_summary_and_its_text(tmp_path: Path) -> None:
    log = hand_log()
    log.meta["endings"] = {"a": "landed", "b": "cut in the air at 0.42 m (flying)", "c": "lost (last seen at 0.50 m)"}
    s = summarize(log.write(tmp_path / "flight"))
    assert s["endings"] == log.meta["endings"]
    text = format_summary(s)
    assert "drones: a landed, b cut in the air at 0.42 m (flying), c lost (last seen at 0.50 m)" in text, text
    assert summarize(hand_log().write(tmp_path / "older"))["endings"] == {}  # logs written before keep working
