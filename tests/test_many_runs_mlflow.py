"""What MLflow shows of a population: per-member values as one series each, a run description, main columns."""

from __future__ import annotations

import math
from collections.abc import Callable
from pathlib import Path

from atdrone.tracking import Tracker, member_series, population_columns, population_markdown


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
