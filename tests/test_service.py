"""The Ray population service on a real local Ray (num_cpus=2), a real MLflow store and sqlite."""

from __future__ import annotations

import json
import time

import mlflow
import pytest
import ray

from atdrone.models.checkpoint import read_header
from atdrone.registry import Registry
from atdrone.service.driver import STATE_FILE, run_experiment
from atdrone.service.experiment import load_experiment

TINY = {
    "task": "4p2e1o",
    "updates_per_generation": 1,
    "num_workers": 2,
    "eval_episodes": 4,
    "final_zoo": "zoo1",
    "final_episodes": 4,
    "gif": False,
    "ppo": {"entity_dim": 16, "hidden": 32, "minibatch_size": 64, "num_envs": 8, "rollout_steps": 16},
}


@pytest.fixture(scope="module")
def local_ray():
    ray.init(num_cpus=2, include_dashboard=False, namespace="atdrone", log_to_driver=False)
    yield
    ray.shutdown()


def _cfg(tmp_path, name, **kw):
    return load_experiment({**TINY, "name": name, "out_dir": str(tmp_path), **kw})


def test_hola_generations_fill_the_registry_and_mlflow(local_ray, tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    cfg = _cfg(tmp_path, "hola_t", algorithm="hola", generations=3, hola={"population_size": 3})
    summary = run_experiment(cfg, tracking_uri=uri, progress=False)
    reg = Registry(tmp_path / "hola_t" / "registry.db")
    members = reg.members(run="hola_t")
    # generation 0 bootstraps with a self-play learner, then one best-response learner per generation
    assert sorted(members["generation"]) == [0, 1, 2]
    assert list(members["status"]) == ["active"] * 3
    g0, g1, g2 = members.sort_values("generation")["id"]
    assert list(members.sort_values("generation")["parents"]) == [[], [g0], [g1]]
    for _, m in members.iterrows():
        assert read_header(m["checkpoint"])["sha256"] == m["sha256"]
    # generation 2 played the hyperedges touching generation 1's learner: only (g1, g1, g0, g0)
    matches = reg.matches(run="hola_t")
    assert [sorted(t) for t in matches["team"]] == [sorted([g1, g1, g0, g0])]
    assert set(matches["generation"]) == {2}
    report = summary["reports"][2]
    graph = report.documents["hypergraph.json"]
    assert set(graph["rho"]) == {g0, g1} and abs(sum(graph["rho"].values()) - 1) < 1e-9
    # the learner trained with exactly the draws the rollout recorded: profiles of rho's members only
    (trained,) = report.training
    assert trained.partners["members"] == list(graph["rho"]) and sum(trained.drawn.values()) > 0
    assert all(set(profile.split("|")) <= {g0, g1} for profile in trained.drawn)
    assert graph["drawn_profiles"] == trained.drawn
    assert list(summary["population"]["member"]) == [g0, g1, g2]
    assert {"zoo1_SUC", "zoo1_COL", "zoo1_AST", "zoo1_REW"} <= set(summary["population"].columns)

    client = mlflow.MlflowClient(uri)
    parent = client.get_run(summary["mlflow_run_id"])
    assert parent.data.params["experiment.algorithm"] == "hola"
    runs = client.search_runs([parent.info.experiment_id])
    by_id = {r.info.run_id: r for r in runs}
    children = [r for r in runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    assert {r.info.run_name for r in children} == {"generation-0", "generation-1", "generation-2"}
    # one nested run per learner, inside its generation's run
    learners = {
        r.info.run_name: by_id[r.data.tags["mlflow.parentRunId"]].info.run_name
        for r in runs
        if r.info.run_name.startswith("learner-")
    }
    assert learners == {
        f"learner-{g0}": "generation-0",
        f"learner-{g1}": "generation-1",
        f"learner-{g2}": "generation-2",
    }
    learner = next(r for r in runs if r.info.run_name == f"learner-{g2}")
    assert "train/policy_loss" in learner.data.metrics
    assert [a.path for a in client.list_artifacts(learner.info.run_id, "checkpoints")] == [f"checkpoints/{g2}.pt"]
    gen2 = next(r for r in children if r.info.run_name == "generation-2")
    assert "pop/rho_entropy" in gen2.data.metrics
    assert {a.path for a in client.list_artifacts(gen2.info.run_id)} >= {"hypergraph.json", "hypergraph.png"}
    top = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"config.json", "population.csv", "best_member_header.json"} <= top
    version = client.get_model_version_by_alias("atdrone-hola_t", "champion")
    assert version.tags["member"] == summary["best"]


def test_killed_rollout_worker_is_restarted_and_the_run_completes(local_ray, tmp_path):
    from atdrone.population import ALGORITHMS
    from atdrone.registry import registry_actor
    from atdrone.service.coordinator import Coordinator
    from atdrone.service.experiment import registry_name

    ppo = {**TINY["ppo"], "rollout_steps": 64}
    cfg = _cfg(tmp_path, "kill_t", algorithm="sp", generations=1, updates_per_generation=6, ppo=ppo)
    registry = registry_actor(tmp_path / "kill.db", name=registry_name(cfg.name))
    coordinator = Coordinator.remote(cfg, ALGORITHMS["sp"], str(tmp_path / "kill_t"), None, registry)
    pids = ray.get(coordinator.worker_pids.remote())
    workers = ray.get(coordinator.workers_handles.remote())
    pending = coordinator.run_generation.remote()
    time.sleep(4.0)
    ray.kill(workers[0], no_restart=False)
    report = ray.get(pending, timeout=240)
    assert len(report.training[0].history) == 6  # every update got its fragments
    new_pids = ray.get(coordinator.worker_pids.remote())
    assert new_pids[0] != pids[0] and new_pids[1] == pids[1]


def test_resume_continues_from_the_last_completed_generation(local_ray, tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    cfg = _cfg(tmp_path, "resume_t", algorithm="hola", generations=3, hola={"population_size": 3})
    first = run_experiment(cfg, tracking_uri=uri, progress=False, stop_after=2)
    assert first["stopped"]
    run_dir = tmp_path / "resume_t"
    saved = json.loads((run_dir / STATE_FILE).read_text())
    reg = Registry(run_dir / "registry.db")
    before = reg.members(run="resume_t").set_index("id")
    assert saved["coordinator"]["generation"] == 2
    assert saved["coordinator"]["algorithm"]["population"] == list(before.index)
    with pytest.raises(FileExistsError):
        run_experiment(cfg, tracking_uri=uri, progress=False)
    second = run_experiment(cfg, tracking_uri=uri, resume=True, progress=False)
    assert [r.generation for r in second["reports"]] == [2]
    after = reg.members(run="resume_t").set_index("id")
    # what was saved is untouched: same members, same checkpoints byte for byte
    assert list(after.index[:2]) == list(before.index)
    for member in before.index:
        assert after.loc[member, "sha256"] == before.loc[member, "sha256"]
        assert read_header(after.loc[member, "checkpoint"])["sha256"] == before.loc[member, "sha256"]
    # the resumed generation warm-started from the saved learner and continued its lineage
    (g2,) = second["reports"][0].learners
    assert after.loc[g2, "parents"] == [before.index[-1]]
    assert second["mlflow_run_id"] == first["mlflow_run_id"]


def test_pbt_exploits_and_explores_and_br_trains_against_the_zoo(local_ray, tmp_path):
    uri = f"sqlite:///{tmp_path}/mlflow.db"
    cfg = _cfg(tmp_path, "pbt_t", algorithm="pbt", generations=2, pbt={"population_size": 2}, final_zoo="")
    summary = run_experiment(cfg, tracking_uri=uri, progress=False)
    first, second = summary["reports"]
    pbt = first.documents["pbt.json"]
    # generation 0 spreads the hyperparameters; the worst member then continues from the best one's weights
    lrs = sorted(pbt["hparams"][m]["lr"] for m in first.learners)
    assert lrs[0] < lrs[1]
    ((loser, winner),) = pbt["exploited"].items()
    assert pbt["fitness"][loser] <= pbt["fitness"][winner]
    reg = Registry(tmp_path / "pbt_t" / "registry.db")
    members = reg.members(run="pbt_t").set_index("id")
    assert len(members) == 4 and sorted(members["generation"]) == [0, 0, 1, 1]
    # every generation-1 member descends from a generation-0 member
    assert all(members.loc[m, "parents"][0] in first.learners for m in second.learners)

    br = _cfg(tmp_path, "br_t", algorithm="br", br={"zoo": "zoo1"}, generations=1, final_zoo="zoo1")
    summary = run_experiment(br, tracking_uri=uri, progress=False)
    (member,) = summary["reports"][0].learners
    # the best response trained with zoo partners, as the rollout recorded them
    (trained,) = summary["reports"][0].training
    assert all(p.startswith("zoo1:") for profile in trained.drawn for p in profile.split("|"))
    assert read_header(tmp_path / "br_t" / "members" / f"{member}.pt")["algorithm"] == "br"
    assert summary["population"].loc[0, "zoo1_SUC"] >= 0.0
