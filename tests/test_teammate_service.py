"""MAPPO, NAHT-D, NAHT-D w/o Dec and FCP through the real service: Ray actors, the sqlite registry, MLflow."""

from __future__ import annotations

import itertools
import json
from typing import Any

import mlflow
import pytest

from atdrone.models.checkpoint import read_header
from atdrone.registry import Registry
from atdrone.service.driver import STATE_FILE, run_experiment
from atdrone.service.experiment import load_experiment
from atdrone.teams.pools import UNSEEN_LABEL, load_pool

TINY: dict[str, Any] = {
    "task": "4p2e1o",
    "updates_per_generation": 2,
    "num_workers": 1,  # one rollout worker process per run: splitting over workers is tested in test_service.py
    "eval_episodes": 4,
    "final_zoo": "zoo1",
    "final_episodes": 4,
    "gif": False,
    "ppo": {"epochs": 2, "entity_dim": 16, "hidden": 32, "minibatch_size": 64, "num_envs": 8, "rollout_steps": 16},
}
POOL_IDS = {f"train_pool:{m}" for m in load_pool("train_pool").names}


def _doc(tmp_path, name: str, algorithm: str, **kw: Any) -> dict[str, Any]:
    return {**TINY, "name": name, "algorithm": algorithm, "out_dir": str(tmp_path), "generations": 2, **kw}


def _members(run_dir, run: str) -> list[dict[str, Any]]:
    frame = Registry(run_dir / "registry.db").members(run=run).drop(columns=["created", "mlflow_run_id"])
    return json.loads(frame.to_json(orient="records"))


def _check_pool_run(result: dict[str, Any], run_dir, name: str, algorithm: str, uri: str) -> list[dict[str, Any]]:
    """One lineage trained against the default pool, tagged an unseen-partner result, with its network."""
    reports = result["reports"]
    for before, after in itertools.pairwise(reports):
        assert after.training[0].parent == before.learners[0]  # one lineage, continued
    for report in reports:
        (trained,) = report.training
        # the number of partners drawn too: a slot without a partner is flown by the learner's copy
        assert trained.partners["kind"] == "VariableCount" and trained.partners["min_partners"] == 1
        assert set(trained.partners["members"]) == POOL_IDS | {"self"}
        assert set("|".join(trained.drawn).split("|")) <= POOL_IDS | {"self"}
        with_copy = sum(n for profile, n in trained.drawn.items() if "self" in profile.split("|"))
        assert 0 < with_copy < sum(trained.drawn.values())
        assert all(profile != "self|self" for profile in trained.drawn)  # at least one partner
        decoded = ["train/decoder_loss" in h for h in trained.history]
        assert all(decoded) if algorithm == "naht_d" else not any(decoded)
    rows = _members(run_dir, name)
    assert [r["tags"].get("zoo_version", "")[:3] for r in rows] == ["zv-"] * len(reports)  # the partners' version
    tags = [{k: v for k, v in r["tags"].items() if k != "zoo_version"} for r in rows]
    assert tags == [{"partners": UNSEEN_LABEL, "pool": "train_pool"}] * len(reports)
    arch = read_header(run_dir / "members" / f"{rows[-1]['id']}.pt")["architecture"]
    if algorithm == "mappo":
        assert arch["class"] == "ActorCritic" and arch["centralised_critic"] is True
    else:
        assert arch["class"] == "TeammateActorCritic" and arch["decoder"] is (algorithm == "naht_d")
        assert (arch["history"], arch["embed_dim"], arch["num_p"], arch["num_e"]) == (1, 16, 4, 2)
    parent = mlflow.MlflowClient(uri).get_run(result["mlflow_run_id"])
    assert parent.data.tags["atdrone.partners"] == UNSEEN_LABEL
    return rows


def _split_run_equals(tmp_path, doc: dict[str, Any], uri: str, rows: list[dict[str, Any]], reference) -> None:
    """The run stopped after generation 0 and resumed registers the same members, byte for byte."""
    split = load_experiment({**doc, "out_dir": str(tmp_path / "split")})
    assert run_experiment(split, tracking_uri=uri, progress=False, stop_after=1)["stopped"]
    run_experiment(split, tracking_uri=uri, resume=True, progress=False)
    resumed = _members(tmp_path / "split" / split.name, split.name)
    for row in (*rows, *resumed):
        row["checkpoint"] = row["checkpoint"].split("/members/")[1]
    assert resumed == rows
    state = json.loads((tmp_path / "split" / split.name / STATE_FILE).read_text())["coordinator"]
    assert state == json.loads((reference / STATE_FILE).read_text())["coordinator"]


@pytest.mark.parametrize("algorithm", ["mappo", "naht_d_no_dec"])
def test_mappo_and_the_ablation_train_against_the_pool(local_ray, tmp_path, algorithm, mlflow_store):
    uri = mlflow_store(tmp_path / "mlflow.db")
    doc = _doc(tmp_path, f"{algorithm}_t", algorithm, generations=1)
    result = run_experiment(load_experiment(doc), tracking_uri=uri, progress=False)
    _check_pool_run(result, tmp_path / doc["name"], doc["name"], algorithm, uri)


def test_naht_d_trains_against_the_pool_and_resumes_exactly(local_ray, tmp_path, mlflow_store):
    uri = mlflow_store(tmp_path / "mlflow.db")
    doc = _doc(tmp_path, "naht_d_t", "naht_d")
    result = run_experiment(load_experiment(doc), tracking_uri=uri, progress=False)
    rows = _check_pool_run(result, tmp_path / "naht_d_t", "naht_d_t", "naht_d", uri)
    _split_run_equals(tmp_path, doc, uri, rows, tmp_path / "naht_d_t")


def test_fcp_registers_its_frozen_pool_with_lineage_resumes_exactly_and_a_second_run_reuses_it(
    local_ray, tmp_path, mlflow_store
):
    uri = mlflow_store(tmp_path / "mlflow.db")
    doc = _doc(tmp_path, "fcp_t", "fcp", fcp={"seeds": 2, "levels": 2})
    first = run_experiment(load_experiment(doc), tracking_uri=uri, progress=False)
    run_dir = tmp_path / "fcp_t"
    rows = {r["id"]: r for r in _members(run_dir, "fcp_t")}
    frozen = [m for m, r in rows.items() if r["tags"].get("role") == "fcp partner"]
    learners = [m for m, r in rows.items() if r["tags"].get("role") == "fcp learner"]
    assert len(frozen) == 4 and len(learners) == 2
    # two self-play runs, each frozen early and final: a chain of parents per run
    assert [rows[m]["parents"] for m in frozen] == [[], [frozen[0]], [], [frozen[2]]]
    assert rows[learners[0]]["parents"] == [] and rows[learners[1]]["parents"] == [learners[0]]
    assert first["reports"][-1].population == learners  # what the run ranks: the learner's lineage only
    for report in first["reports"]:
        trained = report.training[-1]
        assert set(trained.partners["members"]) == set(frozen)
        assert set("|".join(trained.drawn).split("|")) <= set(frozen)
    pool = run_dir / "generations" / "000" / "fcp_pool.json"
    document = json.loads(pool.read_text())
    assert [m["name"] for m in document["members"]] == frozen
    for m in document["members"]:
        assert read_header(m["checkpoint"])["sha256"] == rows[m["name"]]["sha256"]

    reuse = _doc(tmp_path, "fcp_reuse_t", "fcp", generations=1, fcp={"reuse": str(pool)})
    second = run_experiment(load_experiment(reuse), tracking_uri=uri, progress=False)
    (report,) = second["reports"]
    (trained,) = report.training  # no frozen pool trained again: only the learner
    assert set(trained.partners["members"]) == {f"fcp_pool:{m}" for m in frozen}
    assert set("|".join(trained.drawn).split("|")) <= {f"fcp_pool:{m}" for m in frozen}
    assert len(_members(tmp_path / "fcp_reuse_t", "fcp_reuse_t")) == 1
    # stopped after the pool's generation and resumed: the learner continues against the saved pool
    _split_run_equals(tmp_path, doc, uri, list(rows.values()), run_dir)
