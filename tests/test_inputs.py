"""Every bad input is answered at once with one line naming the cause (exit 2), never a traceback or a hang."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from atdrone.cli import main
from atdrone.config import CONFIG_DIR, ConfigError, load_task
from atdrone.learn.trainer import load_train_config
from atdrone.models.checkpoint import save_checkpoint
from atdrone.models.networks import ActorCritic, NetConfig
from atdrone.policies.zoo import ZooError, load_zoo
from atdrone.service.experiment import load_experiment

TRAIN = {"name": "tiny", "task": "4p2e1o", "total_env_steps": 256, "eval_every": 1000, "eval_episodes": 2}
EXPERIMENT = {"name": "exp", "algorithm": "sp", "task": "4p2e1o", "final_zoo": "zoo1", "gif": False}


def _one_line_error(capsys: pytest.CaptureFixture[str], argv: list[str], expect: str) -> None:
    """``atdrone argv`` exits 2 with a single stderr line (after any warnings) that contains ``expect``."""
    code = main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    errors = [line for line in err if ": error: " in line]
    assert code == 2, err
    assert len(errors) == 1 and expect in errors[0], err
    assert not any("Traceback" in line for line in err)


def _file(tmp_path: Path, content: bytes | object, name: str = "c.json") -> str:
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else json.dumps(content).encode())
    return str(path)


@pytest.mark.parametrize(
    "content, expect",
    [
        (b'{"name": "\xff\xfe"}', "is not UTF-8 text"),
        (b"[1, 2]", "must hold a JSON object"),
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (b'{"name": "a", "name": "b", "task": "4p2e1o"}', "name: appears twice in one JSON object"),
        (b'{"name": ', "is not valid JSON"),
    ],
)
def test_train_refuses_a_file_that_is_not_a_config(tmp_path, capsys, content, expect):
    _one_line_error(capsys, ["train", _file(tmp_path, content)], expect)


def test_train_refuses_a_directory_and_a_missing_file(tmp_path, capsys):
    _one_line_error(capsys, ["train", str(tmp_path)], "is a directory")
    _one_line_error(capsys, ["train", str(tmp_path / "nope.json")], "cannot read")


@pytest.mark.parametrize(
    "change, expect",
    [
        ({"seed": -1}, "seed: must be >= 0, got -1"),
        ({"device": "banana"}, "device: must be auto, cpu, cuda or cuda:N, got 'banana'"),
        ({"eval_episodes": 10**9}, "eval_episodes: must be <= 100,000"),
        ({"ppo": {"hidden": 10**6}}, "ppo.hidden: must be between 1 and 4,096"),
        ({"ppo": {"num_envs": 10**9}}, "ppo.num_envs: must be between 1 and 65,536"),
        ({"ppo": {"num_envs": 65_536, "rollout_steps": 100_000}}, "num_envs x rollout_steps must be <="),
        ({"zoo": "zoo1"}, "zoo: only best_response trains with zoo partners"),
        ({"name": "../escaped"}, "'../escaped' is not a run name"),
        ({"name": "a/b"}, "is not a run name"),
        ({"name": "a:b"}, "is not a run name"),
        ({"name": ".hidden"}, "is not a run name"),
    ],
)
def test_train_config_values_are_checked_when_loaded(tmp_path, capsys, change, expect):
    doc = {**TRAIN, "out_dir": str(tmp_path / "runs"), **change}
    _one_line_error(capsys, ["train", _file(tmp_path, doc)], expect)
    assert not (tmp_path / "escaped").exists() and not (tmp_path / "runs").exists()


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the message on a machine without CUDA")
def test_cuda_without_a_gpu_is_refused():
    with pytest.raises(ConfigError, match="torch sees no GPU"):
        load_train_config({**TRAIN, "device": "cuda"})


def _task(**changes: object) -> dict:
    doc = json.loads((CONFIG_DIR / "tasks" / "4p2e1o.json").read_text())
    for key, value in changes.items():
        section, leaf = key.split(".")
        doc[section][leaf] = value
    return doc


@pytest.mark.parametrize(
    "changes, expect",
    [
        ({"task.task_horizon": 10**12}, "task.task_horizon: must be between 1 and 100,000"),
        ({"players.num_e": 10**9}, "players.num_e: must be between 1 and 64"),
        ({"players.num_p": 10**6}, "players.num_p: must be between 2 and 64"),
        ({"players.num_ctrl": 0, "players.num_unctrl": 4}, "players.num_ctrl: must be between 1 and 64, got 0"),
        ({"task.fps": 10**7}, "task.fps: must be between 1 and 1,000"),
    ],
)
def test_task_sizes_are_bounded_before_anything_is_allocated(tmp_path, capsys, changes, expect):
    path = _file(tmp_path, _task(**changes), "task.json")
    with pytest.raises(ConfigError, match=expect.split(": ", 1)[1].replace("(", r"\(")):
        load_task(path)
    _one_line_error(capsys, ["render", "--task", path, "--out", str(tmp_path / "x.gif")], expect)


def test_too_many_obstacles_are_refused(tmp_path):
    doc = _task()
    doc["site"]["obstacles"] = {f"b{i}": {"type": "box", "x": [1.0, 1.1], "y": [1.0, 1.1]} for i in range(300)}
    with pytest.raises(ConfigError, match="at most 256 obstacles, got 300"):
        load_task(doc)


@pytest.mark.parametrize(
    "extra, expect",
    [
        (["--episodes", str(10**9)], "--episodes: must be <= 1,000,000"),
        (["--seeds", "-1"], "--seeds: must be between 0 and 2**32 - 1, got -1"),
        (["--seeds", "0", "0"], "--seeds: each seed once, got [0, 0]"),
    ],
)
def test_evaluate_arguments_are_bounded(tmp_path, capsys, extra, expect):
    argv = ["evaluate", "--policy", "greedy", "--zoo", "zoo1", "--out-dir", str(tmp_path), "--no-progress", *extra]
    if extra[0] == "--seeds" and extra[1:] == ["0", "0"]:
        _one_line_error(capsys, [*argv, "--episodes", "2"], expect)
        return
    with pytest.raises(SystemExit) as exit_info:  # argparse's own answer: usage and one error line
        main(argv)
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and expect.split(": ", 1)[1] in err and "Traceback" not in err


def _policy(tmp_path: Path, task: str = "4p2e1o", num_p: int = 4, num_e: int = 2) -> str:
    torch.manual_seed(0)
    path = tmp_path / "policy.pt"
    save_checkpoint(
        path, ActorCritic(NetConfig(entity_dim=8, hidden=16)), {"task": task, "num_p": num_p, "num_e": num_e}
    )
    return str(path)


def test_evaluate_refuses_a_policy_whose_observation_layout_does_not_fit(tmp_path, capsys):
    task = _task(**{"players.num_p": 3, "players.num_unctrl": 1})
    task["task"]["task_name"] = "3p2e1o"
    argv = ["evaluate", "--policy", _policy(tmp_path), "--task", _file(tmp_path, task, "t.json"), "--zoo", "zoo1"]
    _one_line_error(capsys, [*argv, "--out-dir", str(tmp_path)], "trained on 4p2e1o (4 pursuers): its observation")


def test_evaluate_warns_when_a_policy_plays_another_task(tmp_path, capsys):
    argv = ["evaluate", "--policy", _policy(tmp_path), "--task", "4p3e5o", "--zoo", "zoo1", "--episodes", "2"]
    assert main([*argv, "--out-dir", str(tmp_path), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "warning: policy was trained on 4p2e1o (4p2e) and plays 4p3e5o (4p3e)" in err


def test_evaluate_refuses_a_directory_as_policy(tmp_path, capsys):
    argv = ["evaluate", "--policy", str(tmp_path), "--zoo", "zoo1", "--out-dir", str(tmp_path / "o")]
    _one_line_error(capsys, argv, "is a directory, not a checkpoint file")


# ------------------------------------------------------------------ experiment configs
def _missing_zoo(tmp_path: Path) -> str:
    zoo = {"name": "broken", "members": [{"name": "gone", "kind": "checkpoint", "checkpoint": "nowhere/gone.pt"}]}
    return _file(tmp_path, zoo, "zoo.json")


def test_an_experiment_is_refused_when_loaded_not_after_training(tmp_path):
    with pytest.raises(ConfigError, match=r"^final_zoo: .*gone"):
        load_experiment({**EXPERIMENT, "final_zoo": _missing_zoo(tmp_path)})
    with pytest.raises(ConfigError, match=r"^name: '\.\./x' is not a run name"):
        load_experiment({**EXPERIMENT, "name": "../x"})
    with pytest.raises(ConfigError, match=r"^seed: must be >= 0"):
        load_experiment({**EXPERIMENT, "seed": -1})
    with pytest.raises(ConfigError, match=r"^eval_episodes: must be <= 100,000"):
        load_experiment({**EXPERIMENT, "eval_episodes": 10**9})
    with pytest.raises(ConfigError, match=r"^zoo: moved"):  # a zoo in a self-play experiment
        load_experiment({**EXPERIMENT, "zoo": "zoo1"})
    with pytest.raises(ConfigError, match=r"^sp.zoo: unknown key"):
        load_experiment({**EXPERIMENT, "sp": {"zoo": "zoo1"}})
    hola = {"pi0_seeds": 1, "pi0_levels": 1, "learners_per_generation": 1, "population_size": 1}
    with pytest.raises(ConfigError, match=r"^hola.population_size"):
        load_experiment({**EXPERIMENT, "algorithm": "hola", "hola": hola})


def test_a_best_response_zoo_with_a_missing_checkpoint_is_refused_when_loaded(tmp_path):
    with pytest.raises(ConfigError, match=r"^zoo: .*gone"):
        load_train_config({**TRAIN, "mode": "best_response", "zoo": _missing_zoo(tmp_path)})


def test_evaluate_with_a_zoo_missing_a_checkpoint_skips_it_and_says_so(tmp_path, capsys):
    missing = _missing_zoo(tmp_path)
    argv = ["evaluate", "--policy", "greedy", "--episodes", "2", "--out-dir", str(tmp_path / "o"), "--no-progress"]
    assert main([*argv, "--zoo", missing]) == 1  # nothing left to evaluate
    err = capsys.readouterr().err
    assert "warning: zoo broken is missing gone; its cells are skipped" in err
    assert "error: no zoo has all its members; nothing to evaluate" in err
    with pytest.raises(ZooError, match=r"zoo 'broken' is incomplete: 'gone' needs nowhere/gone\.pt"):
        load_zoo(missing).policies()
