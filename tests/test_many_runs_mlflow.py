"""What MLflow shows of a population: per-member values as one series each, a run description, main columns, and
the experiment's view (the key numbers as columns, charts without empty sections) that the printed link opens."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

import pytest

from atdrone.tracking import Tracker, member_series, population_columns, population_markdown, ui_link
from atdrone.tracking_views import VIEW_TAG, key_metric_columns, read_view, runs_view_state, view_tag_value


def test_per_member_metrics_become_one_series_each_in_population_order() -> None:
    metrics = {
        "pop/rho/hola-g0-0": 0.5,
        "pop/rho/hola-g0-2": 0.2,
        "pop/drawn/hola-g2-0/hola-g0-0": 3.0,
        "pop/rho_entropy": 1.0,
        "pop/eta/zoo1:greedy": 0.3,  # not a member of the population: stays a metric of its own
    }
    rest, series = member_series(metrics, ["hola-g0-0", "hola-g0-1", "hola-g0-2"])
    assert rest == {"pop/rho_entropy": 1.0, "pop/eta/zoo1:greedy": 0.3}
    assert set(series) == {"pop/rho", "pop/drawn/hola-g2-0"}
    assert series["pop/rho"][0] == 0.5 and math.isnan(series["pop/rho"][1]) and series["pop/rho"][2] == 0.2
    assert series["pop/drawn/hola-g2-0"][0] == 3.0 and all(math.isnan(v) for v in series["pop/drawn/hola-g2-0"][1:])


def test_series_description_and_main_columns_reach_the_store(
    tmp_path: Path, mlflow_store: Callable[[Path], str]
) -> None:
    import mlflow

    uri = mlflow_store(tmp_path / "mlflow.db")
    tracker = Tracker(uri)
    rows = [
        {"member": "a", "validation_SUC": 40.0, "zoo3_SUC": 35.0},
        {"member": "b", "validation_SUC": 60.0, "zoo3_SUC": 30.0},
        {"member": "c", "validation_SUC": float("nan"), "zoo3_SUC": 50.0},
    ]
    columns = population_columns(rows, "validation", "zoo3", best="b")
    assert columns == {"validation_SUC_best": 60.0, "validation_SUC_mean": 50.0, "zoo3_SUC_champion": 30.0}
    with tracker.run("population", "parent") as run_id:
        tracker.log_series({"pop/rho": [0.5, float("nan"), 0.2]})
        tracker.log_metrics(columns, step=3)
        tracker.describe(population_markdown(rows, "best member **b**"))
    client = mlflow.MlflowClient(uri)
    assert [(m.step, m.value) for m in client.get_metric_history(run_id, "pop/rho")] == [(0, 0.5), (2, 0.2)]
    run = client.get_run(run_id)
    assert run.data.metrics["zoo3_SUC_champion"] == 30.0
    note = run.data.tags["mlflow.note.content"]
    assert note.splitlines()[:4] == [
        "best member **b**",
        "",
        "| member | validation_SUC | zoo3_SUC |",
        "|---|---|---|",
    ]
    assert "| c | - | 50.00 |" in note


def test_the_view_shows_the_key_numbers_as_columns_and_charts_only_what_the_table_shows() -> None:
    top = ["validation_SUC_best", "validation_SUC_mean", "zoo3_SUC_champion", "eval/validation/best_SUC"]
    top += ["gen/zoo3_SUC_best_48ep", "gen/population_size"]
    state = runs_view_state(top, nested=["budget/env_steps", "pop/rho", "train/loss", "gen/population_size"])
    assert state["selectedColumns"] == [
        "attributes.`Models`",
        "metrics.`validation_SUC_best`",
        "metrics.`validation_SUC_mean`",
        "metrics.`zoo3_SUC_champion`",
    ]
    assert [s["name"] for s in state["compareRunSections"]] == ["Model metrics", "gen"]  # no budget, pop, train
    charts = {c["metricKey"]: c for c in state["compareRunCharts"]}
    assert {k for k, c in charts.items() if c["deleted"]} == {
        "budget/env_steps",
        "pop/rho",
        "train/loss",
        "eval/validation/best_SUC",  # validation_SUC_best again
    }
    assert not charts["validation_SUC_best"]["isGenerated"]  # a bar per run, not a one-point line
    assert charts["gen/population_size"]["isGenerated"] and not charts["gen/population_size"]["deleted"]
    # a training run's and an evaluation's numbers; never a curve nor an interval bound
    assert key_metric_columns(["eval/SUC", "eval/COL", "train/loss", "4p2e1o/zoo1/SUC_ci95_low"]) == [
        "eval/SUC",
        "eval/COL",
    ]
    created, back = read_view(view_tag_value(state, 1_000, 2_000))
    assert (created, back) == (1_000, state)


def test_every_experiment_gets_the_view_and_its_link_opens_it(
    tmp_path: Path, mlflow_store: Callable[[Path], str]
) -> None:
    import json

    import mlflow

    uri = mlflow_store(tmp_path / "mlflow.db")
    tracker = Tracker(uri)
    ident = tracker.experiment("population")
    client = mlflow.MlflowClient(uri)
    first = client.get_experiment(ident).tags[VIEW_TAG]
    assert json.loads(first)["name"] == "atdrone: key metrics" and json.loads(first)["state"].startswith("deflate;")
    with tracker.run("population", "parent") as parent:
        tracker.log_metrics({"gen/population_size": 2.0}, step=0)
        with tracker.run("population", "gen-0", nested=True):
            tracker.log_metrics({"budget/env_steps": 4096.0}, step=0)
        tracker.log_metrics({"validation_SUC_best": 55.0}, step=1, run_id=parent)
    created, state = read_view(client.get_experiment(ident).tags[VIEW_TAG])  # written again as the run ended
    assert created == read_view(first)[0]
    assert "metrics.`validation_SUC_best`" in state["selectedColumns"]
    assert [s["name"] for s in state["compareRunSections"]] == ["Model metrics", "gen"]
    assert ui_link("population", uri).endswith(
        f"/#/experiments/{ident}/runs?viewStateShareKey=atdrone&workflowType=machine_learning"
    )


def test_a_long_run_writes_the_view_again_as_its_top_level_run_logs(
    tmp_path: Path, mlflow_store: Callable[[Path], str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import mlflow

    from atdrone import tracking

    uri = mlflow_store(tmp_path / "mlflow.db")
    tracker = Tracker(uri)
    client = mlflow.MlflowClient(uri)
    with tracker.run("population", "parent") as parent:
        ident = client.get_run(parent).info.experiment_id
        with tracker.run("population", "gen-0", nested=True):
            tracker.log_metrics({"budget/env_steps": 4096.0}, step=0)
        tracker.log_metrics({"gen/population_size": 2.0}, step=0, run_id=parent)  # under a minute: not yet
        assert "compareRunCharts" not in read_view(client.get_experiment(ident).tags[VIEW_TAG])[1]
        monkeypatch.setattr(tracking, "VIEW_REFRESH_S", 0.0)
        with tracker.run("population", "gen-1", nested=True):
            tracker.log_metrics({"pop/size": 2.0}, step=1)  # a nested run's: not a reason
        assert "compareRunCharts" not in read_view(client.get_experiment(ident).tags[VIEW_TAG])[1]
        tracker.log_metrics({"gen/population_size": 3.0}, step=1, run_id=parent)
        state = read_view(client.get_experiment(ident).tags[VIEW_TAG])[1]  # the run still going
    assert [s["name"] for s in state["compareRunSections"]] == ["gen"]
    assert {c["metricKey"] for c in state["compareRunCharts"] if c["deleted"]} == {"budget/env_steps", "pop/size"}
