"""The deploy job end to end on the sim backend: real cflib over UDP against the simulated fleet.

Each flight runs on a scaled clock (several simulated seconds per wall second). The
checks read the flight log the job wrote, the fleet's packet counters and the
preflight's findings.
"""

from __future__ import annotations

import json
import os
import signal
import threading
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from atdrone.cli import main as cli_main
from atdrone.config import ConfigError
from atdrone.deploy.config import load_deploy
from atdrone.deploy.job import run_deploy
from atdrone.deploy.loop import StopRequest
from atdrone.deploy.shield import geofence

ROOT = Path(__file__).resolve().parent.parent
CHECKPOINT = ROOT / "configs" / "zoos" / "checkpoints" / "sp_high.pt"


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
    doc = json.loads((ROOT / "configs" / "deploy" / "sim_4p2e1o.json").read_text())
    doc.update(
        member={"registry": db, "id": member},
        horizon=40,
        out_dir=str(tmp_path / "flights"),
        sim={"clock_rate": 4.0, "mocap_rate": 50.0, "mocap_noise": 0.002, "mocap_latency": 0.01},
    )
    doc.update(changes)
    return doc


def fly(
    tmp_path: Path, registry_member: tuple[str, str], arm: bool = True, stop: StopRequest | None = None, **changes: Any
):
    cfg = load_deploy(sim_doc(tmp_path, registry_member, **changes))
    return run_deploy(cfg, arm=arm, tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}", say=lambda _: None, stop=stop)


def ticks(result: Any) -> pd.DataFrame:
    return pd.read_parquet(result.log_dir / "flight.parquet")


def end_states(frame: pd.DataFrame) -> dict[str, str]:
    physical = frame[frame.state != "virtual"]
    return physical.groupby("drone")["state"].last().to_dict()


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


# ---------------------------------------------------------------- a whole flight
def test_sim_flight_of_4p2e1o_with_evader_drones(tmp_path: Path, registry_member: tuple[str, str]) -> None:
    result = fly(tmp_path, registry_member)
    assert result.preflight.ok, result.preflight.text()
    frame = ticks(result)
    cfg = load_deploy(sim_doc(tmp_path, registry_member))
    names = [d.name for d in cfg.drones]
    assert set(end_states(frame)) == set(names)
    assert set(end_states(frame).values()) == {"landed"}, end_states(frame)
    # every tick of the episode has a row for every drone
    flying = frame[frame.step >= 0]
    per_step = flying.groupby("step")["drone"].nunique()
    assert (per_step == len(names)).all()
    assert list(per_step.index) == list(range(len(per_step)))
    episodes = pd.read_parquet(result.log_dir / "episodes.parquet")
    assert len(episodes) == 1 and episodes.steps.iloc[0] == len(per_step)
    # no setpoint outside the geofence; no two drones closer than the shield's separation
    lo, hi = geofence((3.6, 5.0), cfg.shield.margin)
    sp = frame[["setpoint_x", "setpoint_y"]].dropna().to_numpy()
    assert len(sp) > 0 and (sp >= lo - 1e-9).all() and (sp <= hi + 1e-9).all()
    assert result.summary["min_separation"] >= cfg.shield.min_separation
    assert result.sent["arming"] >= 1


def test_no_arm_sends_no_arming_packet(tmp_path: Path, registry_member: tuple[str, str]) -> None:
    result = fly(tmp_path, registry_member, arm=False)
    assert result.preflight.ok and not result.flown and result.log_dir is None
    assert result.sent.get("arming", 0) == 0
    assert result.sent.get("takeoff", 0) == 0 and result.sent.get("setpoint", 0) == 0


# ---------------------------------------------------------------- faults
def test_whole_system_mocap_loss_lands_or_stops_everyone_within_1_5_s(
    tmp_path: Path, registry_member: tuple[str, str]
) -> None:
    result = fly(
        tmp_path, registry_member, horizon=200, faults=[{"kind": "mocap_dropout", "at": 9.0, "duration": 30.0}]
    )
    frame = ticks(result)
    fault = frame[frame.events.map(lambda e: "fault:mocap_dropout" in e)].t.min()
    assert np.isfinite(fault)
    states = end_states(frame)
    assert set(states.values()) <= {"landed", "stopped"}, states
    settled = frame[frame.state.isin(["landed", "stopped"])].groupby("drone").t.min()
    assert (settled - fault <= 1.5).all(), settled - fault


def test_one_link_lost_is_reported_and_the_others_land(tmp_path: Path, registry_member: tuple[str, str]) -> None:
    result = fly(tmp_path, registry_member, horizon=200, faults=[{"kind": "link_loss", "at": 9.0, "drone": "cf3"}])
    frame = ticks(result)
    assert frame[(frame.drone == "cf3")].events.map(lambda e: "link_lost" in e).any()
    states = end_states(frame)
    assert states.pop("cf3") == "lost"
    assert set(states.values()) == {"landed"}, states


def test_sigint_lands_everyone(tmp_path: Path, registry_member: tuple[str, str]) -> None:
    stop = StopRequest()
    timer = threading.Timer(1.5, lambda: os.kill(os.getpid(), signal.SIGINT))  # 6 s of flight after arming

    def say(message: str) -> None:
        if "arming" in message:
            timer.start()

    cfg = load_deploy(sim_doc(tmp_path, registry_member, horizon=400))
    try:
        result = run_deploy(cfg, arm=True, tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}", say=say, stop=stop)
    finally:
        timer.cancel()
    assert stop.signal == "SIGINT"
    frame = ticks(result)
    assert frame.events.map(lambda e: "signal" in e).any()
    assert set(end_states(frame).values()) == {"landed"}


# ---------------------------------------------------------------- the frame check
@pytest.mark.parametrize(
    "true_frame",
    [{"axes": ["-y", "x", "z"]}, {"yaw_offset_deg": 90.0}],
    ids=["swapped-axes", "yaw-off-90"],
)
def test_wrong_frame_is_caught_by_the_dry_run(
    tmp_path: Path, registry_member: tuple[str, str], true_frame: dict[str, Any]
) -> None:
    sim = {"clock_rate": 4.0, "mocap_rate": 50.0, "true_frame": true_frame}
    result = fly(tmp_path, registry_member, arm=True, sim=sim)
    assert not result.preflight.ok and not result.flown
    failed = {c.name for c in result.preflight.checks if not c.ok}
    assert failed & {"spawn", "heading", "observation"}, result.preflight.text()
    assert result.sent.get("arming", 0) == 0


# ---------------------------------------------------------------- the CLI
def test_cli_dry_run_and_report(
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
    bad = dict(doc, episodes=0)
    path.write_text(json.dumps(bad))
    assert cli_main(["deploy", str(path)]) == 2
    assert "episodes: must be > 0" in capsys.readouterr().err
