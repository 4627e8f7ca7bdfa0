"""The benchmark's report, kept weights and config checks, on made-up cell records (no Ray); the statistics
themselves: tests/test_benchmark_stats.py."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
import scipy.stats

from atdrone.benchmark import report
from atdrone.benchmark.cells import Cell, cells, experiment_document, load_benchmark
from atdrone.benchmark.report import write_report
from atdrone.benchmark.weights import keep_weights
from atdrone.config import ConfigError
from atdrone.policies.zoo import checkpoint_path, load_zoo
from atdrone.resolve import PolicyNotFound, resolve

DOC: dict[str, Any] = {
    "name": "made_up",
    "tasks": ["4p2e1o", "4p2e5o"],
    "seeds": [0, 1, 2],
    "zoos": ["zoo1", "zoo2"],
    "env_steps": 1024,
    "updates_per_generation": 2,
    "eval_episodes": 8,
    "bootstrap_reps": 300,
    "methods": {"sp": {"experiment": "sp_quick"}, "hola": {"experiment": "hola_quick"}},
}


# ------------------------------------------------------------------ the report on made-up records
def _records(cfg: Any, tmp_path: Path) -> list[dict[str, Any]]:
    """Records as run_cell writes them; every method's checkpoint is a real zoo checkpoint."""
    spec = next(m for m in load_zoo("zoo2").spec.members if m.kind == "checkpoint")
    rng = np.random.default_rng(0)
    out = []
    for cell in cells(cfg):
        zoos = [cell.zoo] if cell.kind != "method" else [*cfg.zoos, cfg.select_zoo]
        base = {"sp": 30.0, "hola": 40.0, "br": 70.0, "floor": 5.0}.get(cell.method, 35.0)
        metrics = {
            z: {"SUC": base + rng.normal(0, 5), "COL": 20.0, "AST": 300.0 + cell.seed, "REW": base / 10} for z in zoos
        }
        record: dict[str, Any] = {"cell": cell.to_dict(), "name": cell.name, "benchmark": cfg.digest()}
        if cell.kind != "floor":
            path = cfg.folder / "runs" / cell.name / "members" / "m.pt"
            path.parent.mkdir(parents=True, exist_ok=True)
            shutil.copyfile(checkpoint_path(spec), path)
            digest = hashlib.sha256(path.read_bytes()).hexdigest()
            record.update(
                algorithm=cell.method, member="m", checkpoint=str(path.relative_to(cfg.folder)), sha256=digest
            )
        budget = {"env_steps": 1024, "learner_samples": 2048, "eval_env_steps": 0, "benchmark_eval_env_steps": 99}
        record.update(metrics=metrics, budget=budget, timing={"wall_s": 1.0, "cpu_s": 2.0})
        out.append(record)
    return out


@pytest.fixture
def made_up(tmp_path: Path) -> tuple[Any, list[dict[str, Any]]]:
    cfg = load_benchmark({**DOC, "out_dir": str(tmp_path / "bench"), "results_dir": str(tmp_path / "results")})
    return cfg, _records(cfg, tmp_path)


def test_the_report_holds_table_2_paired_differences_normalised_scores_and_aggregates(made_up) -> None:
    cfg, records = made_up
    files = write_report(cfg, records)
    table = pd.read_csv(files["table.csv"])
    row = table[(table.method == "hola") & (table.task == "4p2e5o") & (table.zoo == "zoo2")].iloc[0]
    sucs = [r["metrics"]["zoo2"]["SUC"] for r in records if r["name"].startswith("hola-4p2e5o")]
    assert row["n"] == 3 and row["SUC_mean"] == pytest.approx(np.mean(sucs))
    assert row["SUC_std"] == pytest.approx(np.std(sucs, ddof=1))
    paired = pd.read_csv(files["paired.csv"])
    assert set(paired.reference) == {"sp"} and set(paired.method) == {"hola"}
    assert set(paired.zoo) == {"zoo1", "zoo2", "validation"}
    norm = pd.read_csv(files["normalised.csv"])
    one = norm.iloc[0]
    assert one["normalised_SUC"] == pytest.approx((one["SUC"] - one["floor_SUC"]) / (one["br_SUC"] - one["floor_SUC"]))
    assert set(norm.zoo) == {"zoo1", "zoo2"}  # test zoos only
    agg = pd.read_csv(files["aggregate.csv"])
    assert set(agg.score) == {"SUC", "normalised SUC"} and set(agg.statistic) == {"IQM", "mean"}
    assert (agg.runs == 3).all() and (agg.tasks == 4).all()  # 3 seeds x (2 tasks x 2 test zoos)
    poi = pd.read_csv(files["improvement.csv"])
    assert poi.iloc[0]["P(method > reference)"] > 0.5  # hola's made-up SUC is 10 points higher
    text = files["report.md"].read_text()
    for part in ("Table 2", "Paired differences", "Normalised SUC", "Aggregates", "1,024", "CPU-s"):
        assert part in text
    assert files["suc_4p2e5o.png"].read_bytes()[:4] == b"\x89PNG"
    assert "fig3_without_teammate_modelling.png" in files and "fig4_with_teammate_modelling.png" not in files
    again = write_report(cfg, list(reversed(records)))  # the order the cells finished in does not matter
    assert again["report.md"].read_text() == text


def test_weights_are_chosen_on_the_validation_zoo_and_load_by_name(made_up, monkeypatch) -> None:
    cfg, records = made_up
    for r in records:  # seed 2 is best on validation, seed 0 on every test zoo: validation decides
        if r["cell"]["kind"] == "method":
            seed = r["cell"]["seed"]
            r["metrics"]["validation"]["SUC"] = 10.0 * seed
            for z in cfg.zoos:
                r["metrics"][z]["SUC"] = 90.0 - 10.0 * seed
    manifests = keep_weights(cfg, records)
    assert {(m["method"], m["task"], m["seed"]) for m in manifests} == {
        (m, t, 2) for m in cfg.methods for t in cfg.tasks
    }
    monkeypatch.setenv("ATDRONE_WEIGHTS", str(cfg.results))
    found = resolve("weights:hola/4p2e5o")
    manifest = json.loads(found.checkpoint.with_suffix(".json").read_text())
    assert manifest["sha256"] == hashlib.sha256(found.checkpoint.read_bytes()).hexdigest()
    assert manifest["selected_on"]["zoo"] == "validation" and manifest["budget"]["env_steps"] == 1024
    assert found.policy().name == "hola-4p2e5o"
    assert resolve(f"weights:{cfg.results.name}/sp/4p2e1o").kind == "weights"
    with pytest.raises(PolicyNotFound, match="no weights"):
        resolve("weights:fcp/4p2e1o")
    found.checkpoint.write_bytes(found.checkpoint.read_bytes() + b"x")
    with pytest.raises(Exception, match="sha256"):
        resolve("weights:hola/4p2e5o")


# ------------------------------------------------------------------ config
def test_cells_cover_methods_best_responses_and_floors_at_the_budget(tmp_path: Path) -> None:
    cfg = load_benchmark({**DOC, "out_dir": str(tmp_path)})
    grid = cells(cfg)
    assert len(grid) == 2 * 2 * 3 + 2 * 2 * 3 + 2 * 2
    doc = experiment_document(cfg, Cell("br", "br", "4p2e1o", 1, "zoo2"))
    assert (doc["algorithm"], doc["br"], doc["seed"], doc["final_zoo"]) == ("br", {"zoo": "zoo2"}, 1, "")
    hola = experiment_document(cfg, Cell("method", "hola", "4p2e1o", 0))
    assert hola["generations"] == 1 and hola["updates_per_generation"] == 2  # 1024 env steps: Pi_0 alone


@pytest.mark.parametrize(
    ("change", "where"),
    [
        ({"select_zoo": "zoo1"}, "select_zoo"),
        ({"methods": {"br": {"experiment": "sp_quick"}}}, "methods.br"),
        ({"methods": {"x": {"experiment": "sp_quick", "overrides": {"sp": {"nope": 1}}}}}, "methods.x"),
        ({"references": ["fcp"]}, "references"),
        ({"experiment": {"seed": 3}}, "experiment.seed"),
        ({"seeds": [1, 1]}, "seeds"),
    ],
)
def test_a_bad_benchmark_is_refused_naming_the_key(change: dict[str, Any], where: str) -> None:
    with pytest.raises(ConfigError) as info:
        load_benchmark({**DOC, **change})
    assert info.value.path is not None and info.value.path.startswith(where)


def test_a_folder_holding_another_benchmark_is_refused(tmp_path: Path) -> None:
    from atdrone.benchmark.job import _check_folder
    from atdrone.rundir import RunError

    _check_folder(load_benchmark({**DOC, "out_dir": str(tmp_path)}))
    _check_folder(load_benchmark({**DOC, "out_dir": str(tmp_path), "max_parallel": 1}))  # placement only
    with pytest.raises(RunError, match="different benchmark"):
        _check_folder(load_benchmark({**DOC, "out_dir": str(tmp_path), "seeds": [0, 1]}))


def test_the_quick_preset_loads_with_every_method_on_the_four_tasks() -> None:
    cfg = load_benchmark("quick")  # paper.json is checked the same way by hand: each load takes seconds
    assert len(cfg.methods) == 8 and len(cfg.tasks) == 4 and len(cfg.seeds) >= 3
    assert cfg.select_zoo == "validation" and cfg.best_response


def test_the_papers_orderings_are_checked_paired_over_seeds_with_a_verdict_each(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Planted SUCs: HOLA ahead of SP on Zoo 3 in the hard task (holds), one method above the best response
    (reversed), NAHT-D against MAPPO on the easy task behind on one zoo and ahead on the other, both within
    noise (undecided); the claims whose methods the config lacks are not checked."""
    doc = {
        **DOC,
        "zoos": ["zoo1", "zoo3"],
        "pool": "train_pool",
        "methods": {m: {"experiment": f"{m}_quick"} for m in ("sp", "hola", "naht_d", "mappo")},
        "out_dir": str(tmp_path / "bench"),
        "results_dir": str(tmp_path / "results"),
    }
    cfg = load_benchmark(doc)
    records = _records(cfg, tmp_path)
    noise = [0.0, 12.0, -3.0]

    def suc(method: str, task: str, zoo: str, s: int) -> float:
        if method == "br":
            return 90.0 + 2 * s
        if (method, task, zoo) == ("hola", "4p2e1o", "zoo1"):
            return 95.0 + 3 * s  # above the best response: br - hola = -5, -6, -7
        if method == "naht_d":
            return {"zoo1": 30.0, "zoo3": 40.0}.get(zoo, 35.0) + noise[s]  # vs MAPPO's 35: -5, 7, -8 / 5, 17, 2
        if method == "mappo":
            return 35.0
        return {"sp": 30.0, "hola": 40.0, "mappo": 35.0, "floor": 5.0}[method] + s

    for r in records:
        c = r["cell"]
        for zoo, values in r["metrics"].items():
            values["SUC"] = suc(c["method"], c["task"], zoo, c["seed"])
    drawn: dict[str, list[set[str]]] = {}
    save = report._save

    def keep_labels(fig: Any, path: Path) -> Path:  # each figure's legend, per panel that has one
        drawn[path.stem] = [{t.get_text() for t in ax.get_legend().get_texts()} for ax in fig.axes if ax.get_legend()]
        return save(fig, path)

    monkeypatch.setattr(report, "_save", keep_labels)
    files = write_report(cfg, records)
    lines = {"best response", "floor (random)"}
    assert drawn["fig3_without_teammate_modelling"] == [{"sp", "hola", *lines}]  # the paper's two figures
    assert drawn["fig4_with_teammate_modelling"] == [{"mappo", "naht_d", *lines}]
    assert files["fig4_with_teammate_modelling.png"].read_bytes()[:4] == b"\x89PNG"
    got = pd.read_csv(files["orderings.csv"])
    verdicts = {(r.claim, r.task, r.zoo, r.better, r.worse): r.verdict for r in got.itertuples()}
    hola, br, naht = (claim for claim, *_ in report.CLAIMS[:3])
    assert {k: v for k, v in verdicts.items() if k[0] == hola} == {(hola, "4p2e5o", "zoo3", "hola", "sp"): "holds"}
    bounds = {k: v for k, v in verdicts.items() if k[0] == br}
    assert len(bounds) == 16 and {k for k, v in bounds.items() if v != "holds"} == {
        (br, "4p2e1o", "zoo1", "br", "hola")
    }
    assert bounds[(br, "4p2e1o", "zoo1", "br", "hola")] == "reversed"
    assert {k: v for k, v in verdicts.items() if k[0] == naht} == {
        (naht, "4p2e1o", "zoo1", "naht_d", "mappo"): "behind, undecided",
        (naht, "4p2e1o", "zoo3", "naht_d", "mappo"): "ahead, undecided",
    }
    assert set(got.claim) == {hola, br, naht}  # no NAHT-D w/o Dec in this config: its claims are not checked
    row = got[(got.claim == naht) & (got.zoo == "zoo3")].iloc[0]
    diffs = np.array([5.0, 17.0, 2.0])
    t = scipy.stats.t.ppf(0.975, 2)
    assert row["diff"] == pytest.approx(8.0) and row["ci95_high"] == pytest.approx(8.0 + t * diffs.std(ddof=1) / 3**0.5)
    text = files["report.md"].read_text()
    assert "## The paper's orderings" in text
    assert f"- {br}: 16 comparisons: 15 holds; 0 ahead, undecided; 0 behind, undecided; 1 reversed." in text
    assert "| 4p2e1o | zoo1 | br - hola | 3 | -6.0 +- 0.6 [-8.5, -3.5] | reversed |" in text
