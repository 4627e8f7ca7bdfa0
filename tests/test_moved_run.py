"""A population run directory moved elsewhere resumes there: nothing reads or writes the old tree."""

from __future__ import annotations

import shutil
from collections.abc import Callable
from pathlib import Path

from atdrone.models.checkpoint import read_header
from atdrone.registry import Registry
from atdrone.resolve import resolve
from atdrone.service.driver import run_experiment
from atdrone.service.experiment import load_experiment

TINY = {
    "name": "moved_t",
    "algorithm": "sp",
    "task": "4p2e1o",
    "generations": 2,
    "updates_per_generation": 1,
    "num_workers": 1,  # one rollout worker process per run: splitting over workers is tested in test_service.py
    "eval_episodes": 4,
    "final_zoo": "",
    "gif": False,
    "ppo": {"epochs": 2, "entity_dim": 16, "hidden": 32, "minibatch_size": 64, "num_envs": 8, "rollout_steps": 16},
}


def test_a_moved_run_directory_resumes_where_it_now_is(
    local_ray, tmp_path: Path, mlflow_store: Callable[[Path], str]
) -> None:
    uri = mlflow_store(tmp_path / "mlflow.db")
    first_home, second_home = tmp_path / "first", tmp_path / "second"
    cfg = load_experiment({**TINY, "out_dir": str(first_home)})
    first = run_experiment(cfg, tracking_uri=uri, progress=False, stop_after=1)
    assert first["stopped"]
    second_home.mkdir()
    shutil.move(first_home / "moved_t", second_home / "moved_t")
    first_home.rmdir()
    moved = load_experiment({**TINY, "out_dir": str(second_home)})
    second = run_experiment(moved, tracking_uri=uri, resume=True, progress=False)
    assert [r.generation for r in second["reports"]] == [1]
    assert not first_home.exists()  # nothing was written to the old tree
    run_dir = (second_home / "moved_t").resolve()
    with Registry(run_dir / "registry.db", create=False) as registry:
        members = registry.members()
    assert len(members) == 2
    for member_id, checkpoint, sha256 in zip(members["id"], members["checkpoint"], members["sha256"], strict=True):
        assert Path(checkpoint).parent == run_dir / "members"
        assert read_header(checkpoint)["sha256"] == sha256
        assert resolve(member_id, runs_dir=second_home).checkpoint == Path(checkpoint)
