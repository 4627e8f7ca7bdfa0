"""benchmarks/grid_episodes.py: an older cell record gets its episode summaries by its evaluation played again, only
when the replay gives the record's own metrics."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

from atdrone.benchmark.cells import EVAL_SEED, cells, load_benchmark
from atdrone.policies.neural import load_policy
from atdrone.policies.zoo import checkpoint_path, load_zoo
from atdrone.teams.evaluation import evaluate

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def script(load_script) -> ModuleType:
    return load_script(ROOT / "benchmarks" / "grid_episodes.py")


def _grid(tmp_path: Path) -> tuple[Path, list[Path]]:
    """A one-task grid (sp, seeds 0 and 1, Zoo 1, 4 episodes) whose records are as run_cell wrote them before it
    kept episode summaries; the learner is a zoo drone's checkpoint."""
    doc = {
        "name": "older", "tasks": ["4p2e1o"], "seeds": [0, 1], "zoos": ["zoo1"], "env_steps": 1024,
        "updates_per_generation": 2, "eval_episodes": 4, "best_response": False,
        "methods": {"sp": {"experiment": "sp_quick"}}, "out_dir": str(tmp_path / "bench"),
    }  # fmt: skip
    path = tmp_path / "older.json"
    path.write_text(json.dumps(doc))
    cfg = load_benchmark(path)
    spec = next(m for m in load_zoo("zoo2", "4p2e1o").spec.members if m.kind == "checkpoint")
    written = []
    for cell in [c for c in cells(cfg) if c.kind == "method"]:
        learner = cfg.folder / "runs" / cell.name / "members" / "m.pt"
        learner.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(checkpoint_path(spec), learner)
        policy = load_policy(learner)
        metrics = {
            zoo: evaluate(policy, "4p2e1o", zoo, episodes=4, seeds=[EVAL_SEED + cell.seed]).mean
            for zoo in ["zoo1", "validation"]
        }
        record: dict[str, Any] = {"cell": cell.to_dict(), "name": cell.name, "metrics": metrics}
        digest = hashlib.sha256(learner.read_bytes()).hexdigest()
        record |= {"checkpoint": str(learner.relative_to(cfg.folder)), "sha256": digest}
        written.append(cfg.folder / "cells" / f"{cell.name}.json")
        written[-1].parent.mkdir(parents=True, exist_ok=True)
        written[-1].write_text(json.dumps(record))
    return path, written


def test_a_record_gets_its_summaries_from_a_replay_that_equals_it_and_a_differing_one_is_left_alone(script, tmp_path):
    config, (s0, s1) = _grid(tmp_path)
    kept = json.loads(s1.read_text())
    kept["metrics"]["zoo1"]["REW"] += 1e-9  # not this evaluation's to the last bit
    s1.write_text(json.dumps(kept))
    assert script.main(["--config", str(config), "sp-*-s1", "sp-*-s0"]) == 1
    assert json.loads(s1.read_text()) == kept  # left as it was
    got = json.loads(s0.read_text())
    assert set(got["episodes"]) == {"zoo1", "validation"}
    for zoo, summary in got["episodes"].items():
        metrics = got["metrics"][zoo]
        assert summary["learner_crash"] + summary["partner_only_crash"] == pytest.approx(metrics["COL"])
        parts = summary["return_capture"] + summary["return_collision"] + summary["return_rest"]
        assert parts == pytest.approx(metrics["REW"])
    before = s0.read_bytes()
    assert script.main(["--config", str(config), "sp-*-s0"]) == 0  # already there: not played again
    assert s0.read_bytes() == before
