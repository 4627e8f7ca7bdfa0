"""What the deploy flights share (tests/test_deploy.py, tests/test_deploy_faults.py, tests/test_deploy_backup.py).

The shipped sim config and the registry member every flight flies, a flight of it with a
test's changes, the flight log's ticks, the drones' end states and closest approach, and
the busy host the fault flights run beside. A test module imports the fixtures by name
(``_mlflow_db`` is autouse: every flight's MLflow store); a test that takes one as an
argument redefines the name for ruff (F811: ignored for the flight modules in
pyproject.toml, ``# noqa: F811`` in tests/test_deploy_backup.py).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from atdrone.deploy.config import load_deploy
from atdrone.deploy.job import run_deploy
from atdrone.deploy.loop import StopRequest

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


# ---------------------------------------------------------------- the fault flights'
IMPACT = 0.5  # m/s: the fastest a drone may meet the floor to count as landed
FAULT_AT = 6.0  # s into the flight: after the takeoff, on the way to the spawn or in the episode


@pytest.fixture
def busy_host() -> Iterator[None]:
    """A process spinning beside the flight on the ground station's core: the ground station (this process and what
    it starts) is pinned to one core with a busy loop, half of that core at best, on any machine. That is harsher
    than two busy loops on a 2-core host (two thirds of a core for the ground station's GIL-bound threads) and
    leaves the other cores to the suite's other tests, which loops there would starve. A third of a core (two loops
    on its core) lost flights on a loaded host (arming late, links silent). The simulated fleet, the drones' own
    hardware, leaves the core for any (atdrone.deploy.simproc)."""
    allowed = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else set()
    if allowed:
        os.sched_setaffinity(0, {max(allowed)})  # inherited by the loop and everything the flight starts
    loop = subprocess.Popen([sys.executable, "-c", "while True: pass"])
    try:
        yield
    finally:
        loop.kill()
        loop.wait()
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
