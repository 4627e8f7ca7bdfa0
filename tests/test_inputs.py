"""Every bad input is answered at once with one line naming the cause (exit 2), never a traceback or a hang."""

from __future__ import annotations

import json
import shutil
import warnings
from pathlib import Path

import pytest
import torch

from atdrone.cli import main
from atdrone.config import CONFIG_DIR, ConfigError, load_task
from atdrone.learn.trainer import load_train_config
from atdrone.models import architectures
from atdrone.models.checkpoint import MAGIC, CheckpointError, load_checkpoint, save_checkpoint, sign_header
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
        ({"seed": -1}, "seed: must be between 0 and 2**32 - 1, got -1"),
        ({"seed": 10**30}, "seed: must be between 0 and 2**32 - 1"),
        ({"total_env_steps": 10**15}, "total_env_steps: must be <= 1,000,000,000,000"),
        ({"init_checkpoint": "nowhere/gone.pt"}, "init_checkpoint: nowhere/gone.pt: no such file"),
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


def test_evaluate_refuses_a_policy_of_another_team_size_unless_asked(tmp_path, capsys):
    task = _task(**{"players.num_p": 3, "players.num_unctrl": 1})
    task["task"]["task_name"] = "3p2e1o"
    argv = ["evaluate", "--policy", _policy(tmp_path), "--task", _file(tmp_path, task, "t.json"), "--zoo", "zoo1"]
    _one_line_error(capsys, [*argv, "--out-dir", str(tmp_path)], "trained on 4p2e1o, not on 3p2e1o")


def test_evaluate_refuses_a_policy_of_another_task_unless_asked_and_then_labels_it(tmp_path, capsys):
    argv = ["evaluate", "--policy", _policy(tmp_path), "--task", "4p3e5o", "--zoo", "zoo1", "--episodes", "2"]
    _one_line_error(capsys, [*argv, "--out-dir", str(tmp_path)], "trained on 4p2e1o, not on 4p3e5o")
    assert main([*argv, "--cross-task", "--out-dir", str(tmp_path), "--no-progress"]) == 0
    err = capsys.readouterr().err
    assert "warning: policy was trained on 4p2e1o (4p2e) and plays 4p3e5o (4p3e)" in err
    report = json.loads(next(tmp_path.glob("*_4p3e5o_zoo1.json")).read_text())
    assert "policy@4p2e1o" in json.dumps(report)  # the record names the task it was trained on


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
    with pytest.raises(ConfigError, match=r"^seed: must be between 0 and 2\*\*32 - 1"):
        load_experiment({**EXPERIMENT, "seed": -1})
    with pytest.raises(ConfigError, match=r"^seed: must be between 0 and 2\*\*32 - 1"):
        load_experiment({**EXPERIMENT, "seed": 2**40})
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
    assert main([*argv, "--zoo", missing]) == 2  # nothing left to evaluate: the user's zoo, one line
    err = capsys.readouterr().err
    assert (
        err == "atdrone evaluate: error: no zoo has all its members (zoo broken is missing gone); nothing to evaluate\n"
    )
    with pytest.raises(ZooError, match=r"zoo 'broken' is incomplete: 'gone' needs nowhere/gone\.pt"):
        load_zoo(missing).policies()


def test_a_best_response_experiment_zoo_with_a_missing_checkpoint_is_refused_when_loaded(tmp_path):
    br = {**EXPERIMENT, "algorithm": "br", "br": {"zoo": _missing_zoo(tmp_path)}}
    with pytest.raises(ConfigError, match=r"^br\.zoo: zoo 'broken' is incomplete: 'gone'"):
        load_experiment(br)


def test_an_init_checkpoint_is_checked_when_the_train_config_is_loaded(tmp_path, capsys):
    policy = _policy(tmp_path)
    with pytest.raises(ConfigError, match=r"^init_checkpoint: .*trained on task '4p2e1o', expected '4p3e5o'"):
        load_train_config({**TRAIN, "task": "4p3e5o", "init_checkpoint": policy})
    doc = {**TRAIN, "out_dir": str(tmp_path / "runs"), "init_checkpoint": str(tmp_path)}
    _one_line_error(capsys, ["train", _file(tmp_path, doc)], "init_checkpoint: ")
    assert not (tmp_path / "runs").exists()


@pytest.mark.parametrize("content", [b"[1, 2]", b"7"])
def test_configs_that_are_not_objects_are_refused_by_every_loader(tmp_path, capsys, content):
    path = _file(tmp_path, content)
    with pytest.raises(ConfigError, match="must hold one JSON object"):
        load_experiment(path)
    with pytest.raises(ConfigError, match="must hold one JSON object"):
        load_train_config(path)
    _one_line_error(capsys, ["deploy", path], "must hold one JSON object")


# ------------------------------------------------------------------ checkpoint files
def _header_line(path: Path) -> tuple[bytes, bytes, bytes]:
    """(magic, header line, newline and payload) of a checkpoint file."""
    data = path.read_bytes()
    end = data.index(b"\n", len(MAGIC))
    return data[: len(MAGIC)], data[len(MAGIC) : end], data[end:]


def _rewrite_header(path: Path, header: bytes) -> None:
    magic, _, rest = _header_line(path)
    path.write_bytes(magic + header + rest)


@pytest.mark.parametrize(
    "edit",
    [
        lambda h: {**h, "task": "4p2e3o"},
        lambda h: {**h, "metrics": {"eval/SUC": 99.0}},
        lambda h: {**h, "num_e": 3},
    ],
    ids=["task", "metrics", "num_e"],
)
def test_an_edited_checkpoint_header_is_refused(tmp_path, capsys, edit):
    path = Path(_policy(tmp_path))
    sign_header(path, metrics={"eval/SUC": 10.0})
    _rewrite_header(path, json.dumps(edit(json.loads(_header_line(path)[1]))).encode())
    with pytest.raises(CheckpointError, match=r"header was changed after it was written \(header_sha256 mismatch\)"):
        load_checkpoint(path)
    argv = ["evaluate", "--policy", str(path), "--zoo", "zoo1", "--out-dir", str(tmp_path / "o")]
    _one_line_error(capsys, argv, "header_sha256 mismatch")


def test_a_legacy_header_without_its_digest_loads_with_a_warning(tmp_path):
    path = Path(_policy(tmp_path))
    header = json.loads(_header_line(path)[1])
    del header["header_sha256"]
    _rewrite_header(path, json.dumps(header).encode())
    with pytest.warns(UserWarning, match="not covered by a digest"):
        _, loaded = load_checkpoint(path)
    assert loaded["task"] == "4p2e1o"


def test_the_committed_zoo_checkpoints_carry_the_header_digest():
    for path in sorted((CONFIG_DIR / "zoos" / "checkpoints").glob("*/*.pt")):
        header = json.loads(_header_line(path)[1])
        assert "header_sha256" in header, path
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # no legacy warning
            load_checkpoint(path)


@pytest.mark.parametrize(
    "header, expect",
    [
        (b"[" * 100_000 + b"]" * 100_000, "corrupted header: nested too deeply"),
        (b'{"task": "a", "task": "b"}', "corrupted header: key 'task' appears twice"),
        (b"[1]", "corrupted header: not a JSON object"),
        (b"\xff{}", "corrupted header"),
    ],
)
def test_a_checkpoint_header_that_is_not_one_json_object_is_refused(tmp_path, capsys, header, expect):
    path = Path(_policy(tmp_path))
    _rewrite_header(path, header)
    with pytest.raises(CheckpointError, match=expect):
        load_checkpoint(path)
    argv = ["evaluate", "--policy", str(path), "--zoo", "zoo1", "--out-dir", str(tmp_path / "o")]
    _one_line_error(capsys, argv, expect)


@pytest.mark.parametrize(
    "change, expect",
    [
        ({"num_p": "four"}, "header field num_p must be a pursuer count in 1..64, got 'four'"),
        ({"num_e": 10**9}, "header field num_e must be an evader count in 1..64, got 1000000000"),
        ({"task": ["4p2e1o"]}, "header field task must be a task name"),
        ({"architecture": "ActorCritic"}, "header field architecture must be a JSON object"),
    ],
)
def test_checkpoint_header_fields_are_typed_and_bounded(tmp_path, capsys, change, expect):
    path = Path(_policy(tmp_path))
    sign_header(path, **change)  # as a stale or foreign tool would write it, digest and all
    argv = ["evaluate", "--policy", str(path), "--zoo", "zoo1", "--out-dir", str(tmp_path / "o")]
    _one_line_error(capsys, argv, expect)


def _crafted(tmp_path: Path, architecture: dict) -> Path:
    """A tiny checkpoint whose (re-signed) header declares ``architecture``, with a few bytes of weights."""
    path = tmp_path / "crafted.pt"
    save_checkpoint(path, ActorCritic(NetConfig(entity_dim=1, hidden=1)), {"task": "4p2e1o", "num_p": 4, "num_e": 2})
    sign_header(path, architecture={"class": "ActorCritic", **architecture})
    return path


@pytest.mark.parametrize(
    "architecture, expect",
    [
        ({"hidden": 10**6}, "hidden must be an integer between 1 and 4096"),
        ({"entity_dim": 10**6}, "entity_dim must be an integer between 1 and 1024"),
        ({"history": 10**6}, "history must be an integer between 0 and 64"),
        ({"hidden": 4096, "entity_dim": 1024, "history": 64, "centralised_critic": True}, "weights do not match"),
    ],
)
def test_a_crafted_checkpoint_declaring_a_huge_network_is_refused_before_allocating(
    tmp_path, monkeypatch, architecture, expect
):
    path = _crafted(tmp_path, architecture)
    assert path.stat().st_size < 20_000

    def no_real_network(*args: object, **kwargs: object) -> None:
        raise AssertionError("a network was built before the header and weights were checked")

    monkeypatch.setattr("atdrone.models.checkpoint.build_model", no_real_network)
    with pytest.raises(CheckpointError, match=expect):
        load_checkpoint(path)


def test_a_network_over_the_parameter_cap_is_refused_on_the_meta_device(tmp_path, monkeypatch):
    monkeypatch.setattr(architectures, "MAX_PARAMETERS", 1_000)
    with pytest.raises(CheckpointError, match=r"has 85,123 parameters, over 1,000"):
        architectures.build_model(ActorCritic.header(NetConfig()))
    with pytest.raises(CheckpointError, match=r"parameters, over 1,000"):
        load_checkpoint(_crafted(tmp_path, {"hidden": 64}))


def test_an_oversized_file_is_not_read_as_a_checkpoint(tmp_path, monkeypatch):
    path = Path(_policy(tmp_path))
    monkeypatch.setattr("atdrone.models.checkpoint.MAX_FILE_BYTES", 1_000)
    with pytest.raises(CheckpointError, match=r"more than any checkpoint \(1,000\): not one"):
        load_checkpoint(path)


def test_a_checkpoint_with_non_finite_weights_is_refused_when_loaded(tmp_path, capsys):
    """A diverged update saved NaN weights: loading refuses them (evaluate: one line, exit 2), instead of a policy
    that acts on NaN and fails later."""
    torch.manual_seed(0)
    model = ActorCritic(NetConfig(entity_dim=8, hidden=16))
    with torch.no_grad():
        next(model.parameters())[0] = float("nan")
    path = tmp_path / "nan.pt"
    save_checkpoint(path, model, {"task": "4p2e1o", "num_p": 4, "num_e": 2})
    with pytest.raises(CheckpointError, match=r"non-finite weights \(NaN or inf\) in "):
        load_checkpoint(path)
    argv = ["evaluate", "--policy", str(path), "--zoo", "zoo1", "--episodes", "1", "--out-dir", str(tmp_path)]
    _one_line_error(capsys, argv, "non-finite weights")


@pytest.mark.parametrize(
    "change, expect",
    [
        ({"ppo": {"lr": 1e308}}, r"^ppo\.lr: must be in \(0, 1\], got 1e\+308"),
        ({"hola": {"max_episodes": 10**12}}, r"^hola\.max_episodes: must be at most 1,000,000"),
    ],
)
def test_experiment_learning_rates_and_episode_counts_are_bounded(change, expect):
    with pytest.raises(ConfigError, match=expect):
        load_experiment({**EXPERIMENT, "algorithm": "hola", **change})


def test_weights_names_and_model_version_tags_never_reach_outside_their_folders(tmp_path, monkeypatch, mlflow_store):
    """``weights:../x`` would read x.json and x.pt one level above a results folder's weights; a model version
    whose checkpoint_file tag is ``../../x.pt`` would read a file outside the model cache. Both are planted with a
    valid checkpoint and both are refused."""
    import hashlib

    import mlflow

    from atdrone.fileio import user_cache
    from atdrone.policies.base import PolicyError
    from atdrone.resolve import WEIGHTS_ENV, resolve
    from atdrone.tracking import Tracker

    planted = Path(_policy(tmp_path))
    results = tmp_path / "results" / "bench"
    (results / "weights").mkdir(parents=True)
    shutil.copyfile(planted, results / "x.pt")
    manifest = {"sha256": hashlib.sha256(planted.read_bytes()).hexdigest(), "task": "4p2e1o"}
    (results / "x.json").write_text(json.dumps(manifest))
    monkeypatch.setenv(WEIGHTS_ENV, str(results))
    with pytest.raises(PolicyError, match=r"no '\.\.'"):
        resolve("weights:../x")

    uri = mlflow_store(tmp_path / "mlflow.db")
    tracker = Tracker(uri)
    with tracker.run("tags", "run"):
        version = tracker.register_checkpoint(planted, "atdrone-tags", None, {"member": "m"})
    mlflow.MlflowClient(tracking_uri=uri).set_model_version_tag(
        "atdrone-tags", version, "checkpoint_file", "../../x.pt"
    )
    shutil.copyfile(planted, user_cache("x.pt"))
    with pytest.raises(PolicyError, match="outside the model cache"):
        resolve(f"models:/atdrone-tags/{version}", tracking_uri=uri)


def test_a_number_of_5000_digits_in_a_config_is_refused_in_one_line(tmp_path, capsys, load_script):
    config = tmp_path / "big.json"
    config.write_text('{"name": "big", "algorithm": "sp", "task": "4p2e1o", "seed": ' + "9" * 5000 + "}")
    _one_line_error(capsys, ["train", str(config)], "is not a config: Exceeds the limit (4300 digits)")
    train_job = load_script(Path(__file__).resolve().parent.parent / "jobs" / "train.py")  # every loader alike
    assert train_job.main([str(config)]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        f"jobs/train.py: error: {config} is not a config: Exceeds the limit (4300 digits) for integer string "
        "conversion: value has 5000 digits"
    ]
