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

from atdrone.benchmark import report, report_figures
from atdrone.benchmark.cells import Cell, cells, experiment_document, load_benchmark
from atdrone.benchmark.report import write_report
from atdrone.benchmark.weights import card_text, keep_weights
from atdrone.config import ConfigError
from atdrone.hostinfo import float_kernels
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
    "smoke_test": True,  # HOLA at 1,024 env steps: one generation, allowed in a smoke test only
}


@pytest.fixture(autouse=True)
def _zoos_unchecked(monkeypatch: pytest.MonkeyPatch) -> None:
    """The report reads cell records and never plays a partner, so these tests do not need every task's zoo
    drones on disk (tests/test_missing_zoo.py checks the zoos): the config's zoo check is skipped here."""
    from atdrone.benchmark import config

    monkeypatch.setattr(config, "_check_zoo", lambda zoo, path, tasks: None)


# ------------------------------------------------------------------ the report on made-up records
def _records(cfg: Any, tmp_path: Path) -> list[dict[str, Any]]:
    """Records as run_cell writes them; every method's checkpoint is a real zoo checkpoint."""
    spec = next(m for m in load_zoo("zoo2", "4p2e1o").spec.members if m.kind == "checkpoint")  # a real drone file
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
        timing = {"wall_s": 1.0, "cpu_s": 2.0, "machine": float_kernels()}  # evaluated here
        record.update(metrics=metrics, budget=budget, timing=timing, generations=1)
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
    assert (agg.runs == 3).all() and (agg.tasks == 2).all() and (agg.zoos == 2).all()  # 3 seeds x 2 tasks x 2 zoos
    poi = pd.read_csv(files["improvement.csv"])
    assert poi.iloc[0]["P(method > reference)"] > 0.5  # hola's made-up SUC is 10 points higher
    text = files["report.md"].read_text()
    n = len(records)  # every made-up record: 1,024 env steps, 99 evaluation env steps, 2 CPU-s, 1 s of wall time
    assert (
        f"In all: {n} cells, {1024 * n:,} training env steps, {99 * n:,} evaluation env steps, {2 * n} CPU-s, " in text
    )
    assert f"{n} s of cell wall time" in text
    for part in ("Table 2", "Paired differences", "Normalised SUC", "Aggregates (rliable)", "1,024", "CPU-s"):
        assert part in text
    assert files["suc_4p2e5o.png"].read_bytes()[:4] == b"\x89PNG"
    assert "fig3_without_teammate_modelling.png" in files and "fig4_with_teammate_modelling.png" not in files
    again = write_report(cfg, list(reversed(records)))  # the order the cells finished in does not matter
    assert again["report.md"].read_text() == text


def test_protocol_results_make_their_own_table_and_leave_the_others_as_they_were(made_up) -> None:
    """Records with ``protocols`` (a config's team-change protocols): protocols.csv and its report section hold
    each method's mean and std over seeds; Table 2 and the aggregates are the same as without them."""
    cfg, records = made_up
    before = {k: p.read_bytes() for k, p in write_report(cfg, records).items() if k.endswith(".csv")}
    with_events = []
    for r in records:
        r = dict(r)
        if r["cell"]["kind"] == "method":
            suc = 20.0 + r["cell"]["seed"]
            r["protocols"] = {
                "zoo3+swap": {"SUC": suc, "SUC_post": suc - 5, "REC": 40.0 + r["cell"]["seed"], "EVT": 90.0}
            }
        with_events.append(r)
    files = write_report(cfg, with_events)
    for name, data in before.items():
        assert files[name].read_bytes() == data, name
    table = pd.read_csv(files["protocols.csv"])
    row = table[(table.method == "hola") & (table.task == "4p2e5o")].iloc[0]
    seeds = [r["cell"]["seed"] for r in records if r["name"].startswith("hola-4p2e5o")]
    assert row["n"] == len(seeds) and row["SUC_mean"] == pytest.approx(20.0 + np.mean(seeds))
    assert row["REC_std"] == pytest.approx(np.std(seeds, ddof=1))
    assert "## Team changes" in files["report.md"].read_text()


def test_a_weight_measured_on_other_float_kernels_is_played_again_for_its_card(made_up) -> None:
    """The card's metrics are what the weight plays on the host writing it; the record's stay as cell_metrics."""
    from atdrone.benchmark.weights import play_as_cell

    cfg, records = made_up
    # sp's 4p2e1o cell (the made-up learners are 4p2e1o drones); each replay plays cfg.eval_episodes (8)
    easy = [r for r in records if r["cell"]["task"] == "4p2e1o" and r["cell"]["method"] == "sp"]
    elsewhere = {**float_kernels(), "cpu": "another CPU"}
    for r in easy:
        r["timing"]["machine"] = elsewhere
    said: list[str] = []
    (m,) = keep_weights(cfg, easy, said.append)
    assert len(said) == 1  # played again, and said so
    record = next(r for r in easy if r["cell"]["seed"] == m["seed"])
    assert m["cell_metrics"] == record["metrics"] and m["cell_measured_on"] == elsewhere
    assert m["measured_on"] == float_kernels() and set(m["metrics"]) == set(record["metrics"])
    for got in m["metrics"].values():
        assert got["SUC"] != 0.0 or got["REW"] != 0.0  # played, not zeros
    zoo = cfg.zoos[0]
    assert m["metrics"][zoo] == play_as_cell(
        cfg.folder / record["checkpoint"], "4p2e1o", zoo, m["seed"], cfg.eval_episodes
    )
    assert m["metrics"][zoo]["SUC"] != record["metrics"][zoo]["SUC"]  # the made-up numbers are not what it plays
    text = (cfg.results / "weights" / "sp" / "4p2e1o.md").read_text()
    assert "cpu another CPU" in text and f"cpu {float_kernels()['cpu']}" in text
    assert "played again here, SUC, COL and REW differ from them by at most" in text
    same = {**m, "cell_metrics": m["metrics"], "cell_measured_on": None}  # a record without its kernels, equal
    assert "a host its record does not name" in card_text(same) and "equal them to the last bit" in card_text(same)


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
        ({"protocols": ["zoo3"]}, "protocols[0]"),
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
    save = report_figures._save

    def keep_labels(fig: Any, path: Path) -> Path:  # each figure's legend, per panel that has one
        drawn[path.stem] = [{t.get_text() for t in ax.get_legend().get_texts()} for ax in fig.axes if ax.get_legend()]
        return save(fig, path)

    monkeypatch.setattr(report_figures, "_save", keep_labels)
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


# ------------------------------------------------------------------ smoke tests, HOLA's generations, extra seeds
def _hola_update_env_steps(cfg: Any) -> int:
    from atdrone.learn.ppo import ppo_config

    doc = experiment_document(cfg, Cell("method", "hola", "4p2e1o", 0))
    ppo = ppo_config(doc.get("ppo", {}), doc.get("preset", "default"))
    return ppo.num_envs * ppo.rollout_steps


def test_a_hola_method_planned_under_three_hypergraph_generations_is_refused(tmp_path: Path) -> None:
    """At 1,024 env steps HOLA plans one generation (Pi_0 alone): refused naming the method unless the benchmark
    is a smoke test; at the budget of Pi_0 plus three generations it loads."""
    doc = {k: v for k, v in DOC.items() if k != "smoke_test"} | {"out_dir": str(tmp_path)}
    with pytest.raises(ConfigError, match="0 hypergraph generation") as info:
        load_benchmark(doc)
    assert info.value.path == "methods.hola"
    smoke = load_benchmark({**doc, "smoke_test": True})
    per_update = _hola_update_env_steps(smoke)
    pi0 = 2 * doc["updates_per_generation"]  # hola_quick trains two self-play seeds in generation 0
    three = per_update * (pi0 + 3 * doc["updates_per_generation"])
    cfg = load_benchmark({**doc, "env_steps": three})
    assert experiment_document(cfg, Cell("method", "hola", "4p2e1o", 0))["generations"] == 4
    with pytest.raises(ConfigError, match="2 hypergraph generation"):
        load_benchmark({**doc, "env_steps": three - per_update * doc["updates_per_generation"]})


def test_the_smoke_test_report_says_it_ranks_nothing_and_marks_the_short_hola(made_up, tmp_path: Path) -> None:
    cfg, records = made_up
    text = write_report(cfg, records)["report.md"].read_text()
    assert "**A smoke test: it ranks nothing.**" in text
    assert "**Marked: hola.** hola is planned for 1 generation(s) at 1,024 env steps: 0 hypergraph" in text
    assert "Marked: sp" not in text
    folders = {"out_dir": str(cfg.folder.parent), "results_dir": str(tmp_path / "plain")}
    plain = load_benchmark({**DOC, **folders, "smoke_test": False, "methods": {"sp": {"experiment": "sp_quick"}}})
    plain_records = [r for r in records if r["cell"]["method"] != "hola"]
    assert "smoke test" not in write_report(plain, plain_records)["report.md"].read_text()


def test_extra_seeds_join_the_pairs_but_not_the_aggregates(tmp_path: Path) -> None:
    """Seeds 3 and 4 of hola and sp on 4p2e5o: cells of their own, five pairs in the ordering on Zoo 3, and
    the aggregates over the benchmark's three seeds (every task must have the same runs)."""
    doc = {
        **DOC,
        "zoos": ["zoo1", "zoo3"],
        "extra_seeds": [{"methods": ["hola", "sp"], "tasks": ["4p2e5o"], "seeds": [3, 4]}],
        "out_dir": str(tmp_path / "bench"),
        "results_dir": str(tmp_path / "results"),
    }
    cfg = load_benchmark(doc)
    names = {c.name for c in cells(cfg)}
    assert {"hola-4p2e5o-s4", "sp-4p2e5o-s3"} <= names and "hola-4p2e1o-s3" not in names
    assert cfg.digest() != load_benchmark({**doc, "extra_seeds": []}).digest()
    assert (
        load_benchmark({**doc, "extra_seeds": []}).digest()
        == load_benchmark({**DOC, "zoos": ["zoo1", "zoo3"]}).digest()
    )
    # the learner's threads are a resource (how fast, not what): a grid may resume with another count
    assert cfg.digest() == load_benchmark({**doc, "experiment": {"learner_threads": 1}}).digest()
    assert cfg.digest() != load_benchmark({**doc, "experiment": {"num_workers": 1}}).digest()
    files = write_report(cfg, _records(cfg, tmp_path))
    claims = pd.read_csv(files["orderings.csv"])
    hola = claims[claims.better == "hola"].iloc[0]
    assert (hola.task, hola.zoo, hola.worse, hola.n) == ("4p2e5o", "zoo3", "sp", 5)
    assert hola.paper == "REW +12.4, COL -12.0, AST +19.4"  # Table 2, 4p2e5o Zoo 3: HOLA - SP
    agg = pd.read_csv(files["aggregate.csv"])
    assert (agg.runs == 3).all()


def test_the_paper_side_by_side_sets_ours_with_its_interval_beside_table_2(made_up) -> None:
    """REW of hola on 4p2e5o Zoo 2 planted at 120, 125, 131 against the paper's 128.45 +- 3.79: the t interval
    of the mean by hand (2 degrees of freedom); AST with one seed without a success: n 2, 1 degree of freedom."""
    cfg, records = made_up
    for r in records:
        c = r["cell"]
        if (c["method"], c["task"]) == ("hola", "4p2e5o"):
            r["metrics"]["zoo2"]["REW"] = [120.0, 125.0, 131.0][c["seed"]]
            r["metrics"]["zoo2"]["AST"] = [300.0, float("nan"), 310.0][c["seed"]]
    files = write_report(cfg, records)
    side = pd.read_csv(files["paper.csv"])
    assert len(side) == 2 * 2 * 2 * 3  # tasks x zoos x methods of Table 2 x COL, AST, REW
    rew = side[(side.method == "hola") & (side.task == "4p2e5o") & (side.zoo == "zoo2") & (side.metric == "REW")]
    row = rew.iloc[0]
    values = np.array([120.0, 125.0, 131.0])
    half = scipy.stats.t.ppf(0.975, 2) * values.std(ddof=1) / np.sqrt(3)
    assert (row.paper_mean, row.paper_std, row.n) == (128.45, 3.79, 3)
    assert row["mean"] == pytest.approx(values.mean()) and row["std"] == pytest.approx(values.std(ddof=1))
    assert [row.ci95_low, row.ci95_high] == pytest.approx([values.mean() - half, values.mean() + half])
    assert row["diff"] == pytest.approx(values.mean() - 128.45) and bool(row.paper_in_interval)
    ast = side[(side.method == "hola") & (side.task == "4p2e5o") & (side.zoo == "zoo2") & (side.metric == "AST")]
    half = scipy.stats.t.ppf(0.975, 1) * np.std([300.0, 310.0], ddof=1) / np.sqrt(2)
    assert ast.iloc[0].n == 2 and ast.iloc[0].ci95_high == pytest.approx(305.0 + half)
    text = files["report.md"].read_text()
    assert "## Beside the paper (Table 2)" in text
    assert "| 4p2e5o | zoo2 | hola | 25.2 +- 3.4 |" in text  # COL: the paper's 25.2 +- 3.35


def test_a_bound_within_noise_of_the_floor_normalises_nothing_and_is_marked(made_up) -> None:
    cfg, records = made_up
    for r in records:
        c = r["cell"]
        if c["kind"] in ("br", "floor") and (c["task"], c["zoo"]) == ("4p2e1o", "zoo1"):
            r["metrics"]["zoo1"]["SUC"] = 12.5 if c["kind"] == "floor" else [10.0, 15.0, 12.5][c["seed"]]
    files = write_report(cfg, records)
    norm = pd.read_csv(files["normalised.csv"])
    marked = norm[(norm.task == "4p2e1o") & (norm.zoo == "zoo1")]
    assert not marked.bound_usable.any() and marked.normalised_SUC.isna().all()
    assert norm[norm.task == "4p2e5o"].bound_usable.all() and norm[norm.task == "4p2e5o"].normalised_SUC.notna().all()
    text = files["report.md"].read_text()
    assert "Bounds usable: 3 of 4 (task, zoo)." in text and "| 4p2e1o | zoo1 | 12.5 | 12.5 |" in text
    agg = pd.read_csv(files["aggregate.csv"])
    assert (agg[agg.score == "normalised SUC"].tasks == 1).all()  # 4p2e1o has a marked bound: left out


def test_the_paper_budget_preset_runs_every_method_at_the_papers_budget() -> None:
    cfg = load_benchmark("paper_budget")
    assert cfg.env_steps == 1_048_576 and cfg.eval_episodes == 500 and not cfg.smoke_test
    assert len(cfg.methods) == 8 and cfg.tasks == ("4p2e1o", "4p2e3o", "4p2e5o", "4p3e5o") and cfg.seeds == (0, 1, 2)
    assert cfg.best_response and cfg.select_zoo == "validation" and "ppo" in cfg.experiment
    grid = cells(cfg)
    method_cells = [c for c in grid if c.kind == "method"]
    # the cells of every stated ordering have five seeds
    for _, better, worse, tasks, _ in report.CLAIMS:
        if better == "br":
            continue
        for method in (better, *(worse or ())):
            for task in tasks or cfg.tasks:
                assert cfg.seeds_of(method, task) == (0, 1, 2, 3, 4), (method, task)
    assert len(method_cells) == 8 * 4 * 3 + 2 * (3 * 2 + 3 * 2 + 2 * 2)
    assert cfg.seeds_of("pbt", "4p2e5o") == (0, 1, 2) and cfg.seeds_of("hola", "4p2e1o") == (0, 1, 2)
    for method in ("hola", "hola_no_g"):
        assert experiment_document(cfg, Cell("method", method, "4p2e5o", 0))["generations"] - 1 >= 3
    docs = [experiment_document(cfg, Cell("method", m, "4p2e1o", 0)) for m in cfg.methods]
    docs.append(experiment_document(cfg, Cell("br", "br", "4p2e1o", 0, "zoo1")))
    assert len({json.dumps([d["preset"], d["ppo"]], sort_keys=True) for d in docs}) == 1  # one PPO setting for all


def test_a_benchmarks_default_results_are_its_own_and_its_weights_are_found_by_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Without results_dir the report and weights go beside the cells (never over the committed
    benchmarks/results/<name>), and weights:NAME/... finds them there from the working folder."""
    from atdrone.resolve import weights_roots

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ATDRONE_WEIGHTS", raising=False)
    cfg = load_benchmark({**DOC, "out_dir": "runs/benchmarks"})
    assert cfg.results == tmp_path / "runs" / "benchmarks" / "made_up" / "results" / "made_up"
    (cfg.results / "weights").mkdir(parents=True)
    assert cfg.results in weights_roots()


def test_first_runs_the_matching_cells_first_in_pattern_order_and_refuses_a_pattern_matching_nothing() -> None:
    from atdrone.benchmark.job import run_order

    grid = cells(load_benchmark(DOC))
    order = [c.name for c in run_order(grid, ["floor-*", "sp-4p2e5o-*"])]
    floors = [c.name for c in grid if c.kind == "floor"]
    sp = ["sp-4p2e5o-s0", "sp-4p2e5o-s1", "sp-4p2e5o-s2"]
    assert order[: len(floors)] == floors and order[len(floors) : len(floors) + 3] == sp
    assert order[len(floors) + 3 :] == [c.name for c in grid if c.name not in floors + sp]  # the rest in grid order
    assert [c.name for c in run_order(grid)] == [c.name for c in grid]
    with pytest.raises(ConfigError, match=r"--first.*'sp-4p2e1-\*' matches no cell .*sp-4p2e1o-s0.*floor-zoo1"):
        run_order(grid, ["sp-4p2e1-*"])


def test_the_time_left_counts_each_pending_cell_at_its_methods_median_wall_time() -> None:
    from atdrone.benchmark.cells import Cell
    from atdrone.benchmark.job import _progress_line

    pending = [
        Cell("method", "sp", "4p2e1o", 0),
        Cell("method", "hola", "4p2e1o", 0),
        Cell("br", "br", "4p2e1o", 0, "zoo1"),
    ]
    # sp: the median (a cell that sat out a pause, 3,000 s, is no guide); hola, br: none finished, the mean of the
    # training methods' medians (sp 360 s, br 240 s: 300 s; the floors train nothing)
    walls = {"floor": [1.0, 3.0, 2.0], "sp": [300.0, 420.0, 360.0, 3000.0, 330.0], "br": [240.0]}
    # one at a time: 360 + 300 + 240 s = 15.0 min; two at once: half of it
    assert _progress_line(4, 1, 2, walls, pending) == "cells: 4 done, 1 running, 2 left; about 15.0 min left"
    assert _progress_line(4, 2, 1, walls, pending).endswith("; about 7.5 min left")
    assert _progress_line(4, 1, 2, {"floor": [2.0]}, pending).endswith("; about 0.1 min left")  # floors alone
    assert _progress_line(0, 1, 2, {}, pending) == "cells: 0 done, 1 running, 2 left"  # nothing to go by yet
    # a method whose one cell sat out a pause (hola, 6,000 s) counts at that, but a method none finished (pbt) at
    # the median of the training methods' medians (sp 360, br 240, hola 6,000: 360 s), not at their mean (2,200 s)
    pbt = [Cell("method", "pbt", "4p2e1o", 0)]
    assert _progress_line(4, 1, 1, {**walls, "hola": [6000.0]}, pbt).endswith("; about 6.0 min left")
    # a resumed job starts from the cells finished before it: a record's every attempt, one without timing left out
    from atdrone.benchmark.job import finished_walls

    records = [
        {"cell": {"method": "sp"}, "timing": {"train_wall_s": 290.0, "eval_wall_s": 10.0, "wall_s": 60.0}},
        {"cell": {"method": "sp"}, "timing": {"wall_s": 420.0}},
        {"cell": {"method": "floor"}, "timing": {}},
    ]
    assert finished_walls(records) == {"sp": [300.0, 420.0]}


def test_a_cells_wall_time_sums_its_generations_over_every_attempt_plus_its_evaluation(tmp_path, monkeypatch):
    """Generation 0 ran 100 s, generation 1 was cut after 40 s (a kill) and then ran 60 s: 160 s of training, the
    gap between the attempts and the unfinished attempt not counted; the cell's wall adds its evaluation."""
    from atdrone import registry as registry_module
    from atdrone.benchmark.cells import cell_wall, training_wall
    from atdrone.registry import Registry

    clock = iter(["2026-11-29T00:00:00+00:00", "2026-11-29T00:01:40+00:00", "2026-11-29T00:01:40+00:00",
                  "2026-11-29T05:00:00+00:00", "2026-11-29T05:01:00+00:00"])  # fmt: skip
    monkeypatch.setattr(registry_module, "_now", lambda: next(clock))
    with Registry(tmp_path / "registry.db") as reg:
        reg.start_generation("r", 0)
        reg.finish_generation("r", 0)
        reg.start_generation("r", 1)  # killed 40 s in: never finished; the resume starts it again hours later
        reg.start_generation("r", 1)
        reg.finish_generation("r", 1)
    assert training_wall(tmp_path, "./registry.db") == 160.0
    assert cell_wall({"wall_s": 30.0, "train_wall_s": 160.0, "eval_wall_s": 25.0}) == 185.0
    assert cell_wall({"wall_s": 30.0, "cpu_s": 60.0}) == 30.0  # a record made before: its last attempt


def test_a_report_so_far_holds_the_finished_cells_and_names_the_missing_ones(made_up, tmp_path: Path) -> None:
    """Every cell but SP's on 4p2e5o is finished: ``--report-so-far`` writes the report of those to another folder,
    opening with how many cells it holds and which are missing; the results folder is refused."""
    from atdrone.benchmark.job import cell_path, report_so_far
    from atdrone.cli import main
    from atdrone.errors import UserError

    cfg, records = made_up
    with pytest.raises(UserError, match="no finished cell yet"):
        report_so_far(load_benchmark({**cfg.to_dict(), "results_dir": str(tmp_path / "none")}))
    missing = {r["name"] for r in records if r["name"].startswith("sp-4p2e5o")}
    for record in records:
        if record["name"] not in missing:
            path = cell_path(cfg, Cell(**record["cell"]))
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(json.dumps(record))
    doc = tmp_path / "made_up.json"
    doc.write_text(json.dumps(cfg.to_dict()))
    assert main(["benchmark", str(doc), "--report-so-far", str(cfg.results)]) != 0  # refused before any work
    assert main(["benchmark", str(doc), "--report-so-far", str(tmp_path / "so_far")]) == 0
    title, _, head = (tmp_path / "so_far" / "report.md").read_text().splitlines()[:3]
    assert title == "# Benchmark made_up" and f"{len(records) - 3} of the grid's {len(records)} cells" in head
    assert "Missing: sp (3: sp-4p2e5o-s0, sp-4p2e5o-s1, sp-4p2e5o-s2)" in head
    table = pd.read_csv(tmp_path / "so_far" / "table.csv")
    assert set(table[table.method == "sp"].task) == {"4p2e1o"} and not (cfg.results / "report.md").exists()
    assert not (tmp_path / "so_far" / "weights").exists()
