"""A researcher with two runs of one algorithm in one runs folder: every member named by its run-qualified id
everywhere (README and docs commands), the short id refused where it is ambiguous, and each run's champion its own.

Two real (tiny) self-play runs on the session's Ray, a real registry each and one real MLflow store.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from atdrone.cli import main
from atdrone.service.driver import run_experiment
from atdrone.service.experiment import load_experiment

TINY: dict[str, Any] = {
    "name": "alpha",
    "algorithm": "sp",
    "task": "4p2e1o",
    "generations": 1,
    "updates_per_generation": 1,
    "num_workers": 1,
    "eval_episodes": 4,
    "final_zoo": "zoo1",
    "final_episodes": 4,
    "gif": False,
    "ppo": {"epochs": 1, "entity_dim": 8, "hidden": 16, "minibatch_size": 64, "num_envs": 8, "rollout_steps": 16},
}


@pytest.fixture(scope="module")
def two_runs(_ray_session: str, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Path, str]]:
    """runs/alpha and runs/beta (the same config document, renamed with --name's override), one MLflow store."""
    root = tmp_path_factory.mktemp("many_runs")
    uri = f"sqlite:///{root / 'mlflow.db'}"
    for overrides in ({}, {"name": "beta", "seed": 1}):
        cfg = load_experiment({**TINY, "out_dir": str(root / "runs")}, **overrides)
        run_experiment(cfg, tracking_uri=uri, progress=False)
    yield root, uri


@pytest.fixture
def in_runs(two_runs: tuple[Path, str], monkeypatch: pytest.MonkeyPatch) -> tuple[Path, str]:
    root, uri = two_runs
    monkeypatch.chdir(root)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv("COLUMNS", "200")
    monkeypatch.delenv("ATDRONE_REGISTRY", raising=False)
    return root, uri


def _ok(capsys: pytest.CaptureFixture[str], argv: list[str]) -> str:
    code = main(argv)
    out, err = capsys.readouterr()
    assert code == 0, f"atdrone {' '.join(argv)}: {err}"
    assert "Downloading artifacts" not in err and "%|" not in err, err  # no library progress bars
    return out


# what README.md and docs/registry.md tell a user to type, with a member named by its run
COMMANDS = [
    ["registry", "show", "{id}"],
    ["registry", "lineage", "{id}"],
    ["registry", "matches", "--member", "{id}"],
    ["render", "--policy", "{id}", "--zoo", "zoo1", "--max-steps", "4", "--out", "{short}.gif"],
    ["evaluate", "--policy", "{id}", "--zoo", "zoo1", "--episodes", "4", "--no-progress"],
    ["evaluate", "--policy", "models:/atdrone-{run}@champion", "--zoo", "zoo1", "--episodes", "4", "--no-progress"],
    ["registry", "show", "models:/atdrone-{run}@champion"],
    ["registry", "crossplay", "--run", "{run}"],
    ["registry", "export", "--run", "{run}", "--format", "parquet", "--table", "matches", "--out", "{run}.parquet"],
]


@pytest.mark.timeout(300)
def test_every_command_takes_a_run_qualified_member_of_either_run(
    in_runs: tuple[Path, str], capsys: pytest.CaptureFixture[str]
) -> None:
    runs = _ok(capsys, ["registry", "runs", "--format", "csv"])
    assert {line.split(",")[0] for line in runs.splitlines()[1:]} == {"alpha", "beta"}
    for run in ("alpha", "beta"):
        member = f"{run}/sp-g0-0"
        for argv in COMMANDS:
            out = _ok(capsys, [a.format(id=member, run=run, short="sp-g0-0") for a in argv])
            if argv[:2] == ["registry", "show"]:
                assert f"run: {run}" in out and "trained against:" in out and "training env steps: 128" in out
            if argv[0] == "evaluate":
                assert "SUC %" in out
        # the same member by its short id and --run, before or after the query
        assert f"run: {run}" in _ok(capsys, ["registry", "--run", run, "show", "sp-g0-0"])
        assert f"run: {run}" in _ok(capsys, ["registry", "show", "sp-g0-0", "--run", run])
        _ok(capsys, ["render", "--policy", "sp-g0-0", "--run", run, "--max-steps", "4", "--out", "short.gif"])
        _ok(capsys, ["evaluate", "--policy", "sp-g0-0", "--run", run, "--episodes", "4", "--no-progress"])


def test_a_short_id_two_runs_hold_is_refused_naming_the_qualified_ids(
    in_runs: tuple[Path, str], capsys: pytest.CaptureFixture[str]
) -> None:
    for argv in (["registry", "show", "sp-g0-0"], ["render", "--policy", "sp-g0-0", "--max-steps", "4"]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "alpha/sp-g0-0, beta/sp-g0-0" in err, err
    assert main(["registry", "show", "gamma/sp-g0-0"]) == 2
    assert "runs there: alpha, beta" in capsys.readouterr().err


def test_a_second_run_never_moves_the_first_runs_champion(in_runs: tuple[Path, str]) -> None:
    import mlflow

    from atdrone.tracking import Tracker

    _, uri = in_runs
    client = mlflow.MlflowClient(uri)
    alpha = client.get_model_version_by_alias("atdrone-alpha", "champion")
    beta = client.get_model_version_by_alias("atdrone-beta", "champion")  # --name renamed the model too
    assert alpha.tags["run"] == "alpha" and beta.tags["run"] == "beta"
    assert client.get_experiment_by_name("beta") is not None  # and the experiment
    parent = client.get_run(alpha.run_id)  # the population in the runs table: main numbers and a description
    assert {"validation_SUC_best", "validation_SUC_mean", "zoo1_SUC_champion"} <= set(parent.data.metrics)
    assert "| member |" in parent.data.tags["mlflow.note.content"]
    # a later run that registers a better member under the first run's model does not take its alias
    tracker = Tracker(uri)
    checkpoint = Path(in_runs[0]) / "runs" / "beta" / "members" / "sp-g0-0.pt"
    with tracker.run("alpha", "intruder"):
        tracker.register_checkpoint(checkpoint, "atdrone-alpha", 100.0, {"member": "sp-g0-0", "run": "beta"})
    assert tracker.champion_version("atdrone-alpha") == str(alpha.version)
