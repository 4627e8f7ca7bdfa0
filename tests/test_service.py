"""The Ray population service on a real local Ray (num_cpus=2), a real MLflow store and sqlite."""

from __future__ import annotations

import itertools
import json
import re
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mlflow
import numpy as np
import pandas as pd
import pytest
import ray
import torch

from atdrone.config import ConfigError, load_task
from atdrone.models.checkpoint import load_checkpoint, read_header
from atdrone.policies.neural import load_policy
from atdrone.policies.zoo import load_zoo
from atdrone.population import ALGORITHMS
from atdrone.population.base import Algorithm, GenerationReport, record
from atdrone.registry import Registry
from atdrone.resolve import resolve
from atdrone.rundir import RunError
from atdrone.service import results
from atdrone.service.driver import STATE_FILE, run_experiment, select_best
from atdrone.service.experiment import load_experiment
from atdrone.teams.evaluation import metrics, run_episodes

TINY: dict[str, Any] = {
    "task": "4p2e1o",
    "updates_per_generation": 1,
    "num_workers": 2,
    "eval_episodes": 4,
    "final_zoo": "zoo1",
    "final_episodes": 4,
    "gif": False,
    "ppo": {"epochs": 2, "entity_dim": 16, "hidden": 32, "minibatch_size": 64, "num_envs": 8, "rollout_steps": 16},
}


def _cfg(tmp_path, name, **kw):
    return load_experiment({**TINY, "name": name, "out_dir": str(tmp_path), **kw})


# a small HOLA run: Pi_0 is one self-play seed frozen at 3 skill levels (one update each), then 3 updates a generation
HOLA = {"pi0_seeds": 1, "pi0_levels": 3, "min_episodes": 4, "max_episodes": 8}


def _check_budget(cfg, reports) -> None:
    """Every training took updates x num_envs x rollout_steps env steps; the budget is the running total."""
    steps = samples = eval_steps = 0
    for report in reports:
        for t in report.training:
            assert t.env_steps == len(t.history) * cfg.ppo["num_envs"] * cfg.ppo["rollout_steps"]
            assert t.samples == sum(h["train/samples"] for h in t.history) > 0
        steps += sum(t.env_steps for t in report.training)
        samples += sum(t.samples for t in report.training)
        eval_steps += sum(int(m.metrics["steps"]) for m in report.matches)
        assert report.budget == {"env_steps": steps, "learner_samples": samples, "eval_env_steps": eval_steps}


def _check_hola_generation(report, learner: str, others: list[str]) -> dict:
    """Generation t of HOLA with N_t = [learner]: G'_t, rho over Pi minus N_t, training on draws from its profiles."""
    graph = report.documents["hypergraph.json"]
    g_t = {(learner, learner, *pair) for pair in itertools.combinations(others, 2)}
    assert {m.team for m in report.matches} == g_t  # every match is a hyperedge of G'_t, and each was played
    assert graph["learners"] == [learner]
    assert {tuple(e["team"]) for e in graph["hyperedges"]} == g_t
    assert all(4 <= e["episodes"] <= 8 for e in graph["hyperedges"]) and graph["rounds"] >= 1
    assert list(graph["rho"]) == others and abs(sum(graph["rho"].values()) - 1) < 1e-9  # never N_t
    assert set(graph["eta"]) == {learner, *others}
    assert set(graph["profiles"]) == {"|".join(sorted(p)) for p in itertools.combinations(others, 2)}
    assert abs(sum(graph["profiles"].values()) - 1) < 1e-9
    (trained,) = report.training
    assert report.learners == [trained.member] and report.population[-1] == trained.member
    assert trained.parent == learner  # learner_start "last": N_t's member, continued
    assert trained.partners["kind"] == "Profiles" and set(trained.partners["members"]) == set(others)
    # the rollout's counts of the profiles it drew: rho's members only, and what hypergraph.json reports
    assert sum(trained.drawn.values()) > 0
    assert all(set(profile.split("|")) <= set(others) for profile in trained.drawn)
    assert set(trained.drawn) <= set(graph["profiles"])
    assert graph["drawn_profiles"] == trained.drawn
    slots = {m: sum(n for profile, n in trained.drawn.items() if m in profile.split("|")) for m in others}
    assert graph["drawn_members"] == {m: n for m, n in sorted(slots.items()) if n}
    return graph


def test_hola_generations_fill_the_registry_and_mlflow(local_ray, tmp_path, mlflow_store):
    uri = mlflow_store(tmp_path / "mlflow.db")
    cfg = _cfg(tmp_path, "hola_t", algorithm="hola", generations=3, updates_per_generation=3, hola=HOLA)
    summary = run_experiment(cfg, tracking_uri=uri, progress=False)
    reg = Registry(tmp_path / "hola_t" / "registry.db")
    members = reg.members(run="hola_t").sort_values(["generation", "id"])
    # generation 0 registers Pi_0: the seed's snapshots, each continuing the last; then one learner a generation
    assert list(members["generation"]) == [0, 0, 0, 1, 2]
    assert list(members["status"]) == ["active"] * 5  # no cap: the population only grows
    p0, p1, p2, g1, g2 = members["id"]
    assert list(members["parents"]) == [[], [p0], [p1], [p2], [g1]]
    for _, m in members.iterrows():
        assert read_header(m["checkpoint"])["sha256"] == m["sha256"]
    r0, r1, r2 = summary["reports"]
    assert r0.learners == [p2] and r0.population == [p0, p1, p2]  # N_0: the final snapshot
    assert [t.member for t in r0.training] == [p0, p1, p2] and [t.parent for t in r0.training] == [None, p0, p1]
    assert r0.documents["pi0.json"] == {"seeds": 1, "levels": [1, 1, 1], "members": [p0, p1, p2]}
    assert all(t.partners == {"kind": "self-play"} and not t.drawn for t in r0.training) and not r0.matches
    # generation t >= 1 plays exactly G'_t: N_t's learner in its 2 slots with each 2-subset of Pi minus N_t
    matches = reg.matches(run="hola_t")
    assert set(matches["generation"]) == {1, 2}
    assert {tuple(t) for t in matches.loc[matches["generation"] == 1, "team"]} == {(p2, p2, p0, p1)}
    graph1 = _check_hola_generation(r1, p2, [p0, p1])
    assert graph1["profiles"] == {"|".join(sorted([p0, p1])): pytest.approx(1.0)}
    assert {tuple(t) for t in matches.loc[matches["generation"] == 2, "team"]} == {
        (g1, g1, p0, p1),
        (g1, g1, p0, p2),
        (g1, g1, p1, p2),
    }
    graph2 = _check_hola_generation(r2, g1, [p0, p1, p2])
    assert r2.population == [p0, p1, p2, g1, g2] and not r2.removed
    # the budget grows: training env steps summed over every training, evaluation steps from generation 1 on
    _check_budget(cfg, summary["reports"])
    assert [len(t.history) for r in summary["reports"] for t in r.training] == [1, 1, 1, 3, 3]
    assert r0.budget["eval_env_steps"] == 0 < r1.budget["eval_env_steps"] < r2.budget["eval_env_steps"]
    assert summary["budget"] == r2.budget
    # the final population table: eta and rho of the last generation, and the partner slots drawn from it
    table = summary["population"]
    assert list(table["member"]) == [p0, p1, p2, g1, g2]
    assert {"member", "eta", "rho", "drawn", "zoo1_SUC", "zoo1_COL", "zoo1_AST", "zoo1_REW"} <= set(table.columns)
    rows = table.set_index("member")
    assert [rows.loc[m, "rho"] for m in (p0, p1, p2)] == pytest.approx([graph2["rho"][m] for m in (p0, p1, p2)])
    registered = Registry(tmp_path / "hola_t" / "registry.db").members(run="hola_t").set_index("id")["metrics"]
    for m in (p0, p1, p2, g1):  # `atdrone registry list` shows the same eta (and rho) as the table
        assert registered[m]["eta"] == pytest.approx(rows.loc[m, "eta"])
    assert rows.loc[[g1, g2], "rho"].isna().all()  # N_t and the new learner are never partners
    assert [rows.loc[m, "drawn"] for m in (p0, p1, p2, g1, g2)] == [
        *(graph2["drawn_members"].get(m, 0) for m in (p0, p1, p2)),
        0,
        0,
    ]

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
        **{f"learner-{m}": "generation-0" for m in (p0, p1, p2)},
        f"learner-{g1}": "generation-1",
        f"learner-{g2}": "generation-2",
    }
    learner = next(r for r in runs if r.info.run_name == f"learner-{g2}")
    assert "train/policy_loss" in learner.data.metrics
    assert [a.path for a in client.list_artifacts(learner.info.run_id, "checkpoints")] == [f"checkpoints/{g2}.pt"]
    gen2 = next(r for r in children if r.info.run_name == "generation-2")
    assert gen2.data.metrics["pop/rho_entropy"] == pytest.approx(r2.metrics["pop/rho_entropy"])
    assert gen2.data.metrics["budget/env_steps"] == r2.budget["env_steps"]
    assert gen2.data.metrics["budget/eval_env_steps"] == r2.budget["eval_env_steps"]
    assert {a.path for a in client.list_artifacts(gen2.info.run_id)} >= {"hypergraph.json", "hypergraph.png"}
    gen0 = next(r for r in children if r.info.run_name == "generation-0")
    assert "pi0.json" in {a.path for a in client.list_artifacts(gen0.info.run_id)}
    top = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert {"config.json", "population.csv", "best_member_header.json"} <= top
    version = client.get_model_version_by_alias("atdrone-hola_t", "champion")
    assert version.tags["member"] == summary["best"]


def test_hola_trains_on_partner_profiles_drawn_from_rho(local_ray, tmp_path):
    """The profiles the rollout drew for the learner's episodes follow hypergraph.json's profile distribution."""
    from scipy.stats import chisquare

    from atdrone.registry_ray import registry_actor
    from atdrone.service.coordinator import Coordinator
    from atdrone.service.experiment import registry_name

    # Pi_0: 4 self-play seeds, so Pi_1 minus N_1 has 3 members and 3 profiles; one short update on many
    # environments starts many episodes (every environment draws a profile at reset)
    ppo = {**TINY["ppo"], "num_envs": 256, "rollout_steps": 8, "minibatch_size": 1024}
    # the reciprocal-of-eta rule, whose rho is far from uniform at this seed (softmin: test_hola_signal.py)
    hola = {"pi0_seeds": 4, "pi0_levels": 1, "min_episodes": 4, "max_episodes": 8, "rho": "reciprocal"}
    cfg = _cfg(tmp_path, "draws_t", algorithm="hola", hola=hola, ppo=ppo)
    registry = registry_actor(tmp_path / "draws.db", name=registry_name(cfg.name))
    coordinator = Coordinator.remote(cfg, ALGORITHMS["hola"], str(tmp_path / "draws_t"), None, registry)
    first = ray.get(coordinator.run_generation.remote(), timeout=240)
    report = ray.get(coordinator.run_generation.remote(), timeout=240)
    ray.get(coordinator.release.remote())  # its workers' CPUs (a placement group it made) freed
    ray.kill(coordinator)
    seed0, seed1, seed2, seed3 = first.population
    assert [t.parent for t in first.training] == [None] * 4
    assert first.learners == [seed0]  # N_0: the first seed's final snapshot
    graph = _check_hola_generation(report, seed0, [seed1, seed2, seed3])
    (trained,) = report.training
    assert all(seed0 not in profile.split("|") for profile in trained.drawn)  # never a member of N_t
    names = list(graph["profiles"])
    observed = np.array([trained.drawn.get(name, 0) for name in names])
    expected = np.array([graph["profiles"][name] for name in names]) * observed.sum()
    assert observed.sum() == sum(trained.drawn.values()) >= 250 and expected.min() >= 5
    # chi-square goodness of fit (2 degrees of freedom) at this fixed seed: the draws follow the profiles...
    assert chisquare(observed, expected).pvalue > 0.001
    # ...which rho made far from uniform here (eta 0.75, 0.5, 0): uniform draws would be told apart
    assert max(graph["rho"].values()) > 2 * min(graph["rho"].values())
    assert chisquare(observed).pvalue < 0.001


def test_killed_rollout_worker_is_restarted_and_the_run_completes(local_ray, tmp_path):
    """A worker killed inside a collect call is restarted and the call redone: every update of the
    generation gets both workers' fragments.

    The kill is aimed at a collect in flight: a pid() call sent to the worker waits behind the running
    collect (an actor runs one call at a time), so the worker is killed only once such a probe has gone
    unanswered; the probe, retried on the restarted worker, then answers with the new pid, which shows the
    old process never got to it: it was busy until it died. The coordinator had not finished the update
    whose fragments the worker was collecting (its progress still names the one before), so that call was
    a collect."""
    from atdrone.population import ALGORITHMS
    from atdrone.registry_ray import registry_actor
    from atdrone.service.coordinator import Coordinator
    from atdrone.service.experiment import registry_name

    updates = 4
    ppo = {**TINY["ppo"], "rollout_steps": 256, "minibatch_size": 512}  # a collect of ~1 s, a short update
    kw = {"generations": 1, "updates_per_generation": updates, "ppo": ppo, "final_zoo": ""}
    cfg = _cfg(tmp_path, "kill_t", algorithm="sp", **kw)
    registry = registry_actor(tmp_path / "kill.db", name=registry_name(cfg.name))
    coordinator = Coordinator.options(max_concurrency=2).remote(
        cfg, ALGORITHMS["sp"], str(tmp_path / "kill_t"), None, registry
    )
    pids = ray.get(coordinator.worker_pids.remote())
    workers = ray.get(coordinator.workers_handles.remote())
    pending = coordinator.run_generation.remote()
    training = [f"train: learner 1, update {k}/{updates}" for k in range(1, updates - 1)]  # more collects to come
    deadline = time.monotonic() + 180
    while True:
        assert time.monotonic() < deadline and not ray.wait([pending], timeout=0)[0], "no collect in flight seen"
        if ray.get(coordinator.progress.remote()) in training:  # after update k: update k + 1's collects
            probe = workers[0].pid.remote()
            if not ray.wait([probe], timeout=0.3)[0]:  # worker 0 is inside a call
                break
        time.sleep(0.01)
    ray.kill(workers[0], no_restart=False)
    during = ray.get(coordinator.progress.remote())
    assert during in training, during  # the update the worker was collecting for had not finished
    report = ray.get(pending, timeout=240)
    new_pids = ray.get(coordinator.worker_pids.remote())
    assert new_pids[0] != pids[0] and new_pids[1] == pids[1]  # worker 0 restarted, worker 1 untouched
    assert ray.get(probe, timeout=60) == new_pids[0]  # the old process was busy from the probe to the kill
    ray.get(coordinator.release.remote())  # its workers' CPUs (a placement group it made) freed
    assert ray.get(coordinator.kept.remote())["workers"] == [workers[1]]  # a restarted worker is not kept
    ray.kill(coordinator)
    (trained,) = report.training
    # the learner's update count is complete, each update on both workers' fragments: every worker's
    # num_envs / workers environments x rollout_steps steps x 4 learner drones (self-play)
    assert len(trained.history) == updates
    fragment = cfg.ppo["num_envs"] // cfg.num_workers * ppo["rollout_steps"] * 4
    assert [h["train/samples"] for h in trained.history] == [cfg.num_workers * fragment] * updates
    assert trained.samples == updates * cfg.num_workers * fragment
    assert trained.env_steps == updates * cfg.ppo["num_envs"] * ppo["rollout_steps"] == report.budget["env_steps"]


def test_the_coordinator_skips_a_zoo_evaluation_whose_checkpoint_is_missing(local_ray, tmp_path):
    """A zoo whose checkpoint file is absent (a zoo document in tmp_path): evaluate_population returns no
    results and sends nothing to the workers, where the same call with a complete zoo plays (and here,
    with a member that has no checkpoint, fails on the worker)."""
    from atdrone.registry_ray import registry_actor
    from atdrone.service.coordinator import Coordinator
    from atdrone.service.experiment import registry_name

    ghosts = tmp_path / "ghosts.json"
    members = [{"name": "greedy", "kind": "greedy"}, {"name": "ghost", "kind": "checkpoint", "checkpoint": "no.pt"}]
    ghosts.write_text(json.dumps({"name": "ghosts", "members": members}))
    assert load_zoo(ghosts).missing == ["ghost"]
    cfg = _cfg(tmp_path, "ghost_t", algorithm="sp", num_workers=1, final_zoo="")
    registry = registry_actor(tmp_path / "ghost.db", name=registry_name(cfg.name))
    coordinator = Coordinator.remote(cfg, ALGORITHMS["sp"], str(tmp_path / "ghost_t"), None, registry)
    try:
        assert ray.get(coordinator.evaluate_population.remote(str(ghosts), 4, members=["sp-g0-0"])) == {}
        with pytest.raises(ray.exceptions.RayTaskError, match="no checkpoint file"):
            ray.get(coordinator.evaluate_population.remote("zoo1", 4, members=["sp-g0-0"]))
    finally:
        ray.get(coordinator.release.remote())  # its workers' CPUs (a placement group it made) freed
        ray.kill(coordinator)


def test_resume_continues_from_the_last_completed_generation_wherever_the_run_directory_now_is(
    local_ray, tmp_path, mlflow_store
):
    """A stopped run resumes from its last completed generation; moved to another folder first, it resumes
    there, and nothing reads or writes the old tree."""
    uri = mlflow_store(tmp_path / "mlflow.db")
    first_home, home = tmp_path / "first", tmp_path / "second"
    # the "w/o g" ablation: HOLA's generations with partners drawn uniformly from Pi minus N_t
    kw = {"algorithm": "hola_no_g", "generations": 3, "updates_per_generation": 3, "hola_no_g": HOLA}
    cfg = _cfg(first_home, "resume_t", **kw)
    first = run_experiment(cfg, tracking_uri=uri, progress=False, stop_after=2)
    assert first["stopped"]
    home.mkdir()
    shutil.move(first_home / "resume_t", home / "resume_t")
    first_home.rmdir()
    cfg = _cfg(home, "resume_t", **kw)
    run_dir = (home / "resume_t").resolve()
    saved = json.loads((run_dir / STATE_FILE).read_text())
    reg = Registry(run_dir / "registry.db")
    before = reg.members(run="resume_t").set_index("id")
    assert saved["coordinator"]["generation"] == 2
    assert saved["coordinator"]["algorithm"]["population"] == list(before.index)
    assert saved["coordinator"]["algorithm"]["learners"] == [before.index[-1]]
    assert saved["coordinator"]["budget"] == first["reports"][-1].budget
    # generation 0's every new member (Pi_0's three snapshots, not only N_0) has its zoo SUC for the curves
    gen0 = before[before["generation"] == 0]
    assert len(gen0) == 3 and all("zoo1/SUC" in m for m in gen0["metrics"])
    client = mlflow.MlflowClient(tracking_uri=uri)
    history = {
        k: {m.step: m.value for m in client.get_metric_history(first["mlflow_run_id"], k)}
        for k in ("gen/zoo1_SUC_best_4ep", "gen/population_size")
    }
    assert history["gen/zoo1_SUC_best_4ep"][0] == max(m["zoo1/SUC"] for m in gen0["metrics"])  # 4 episodes each
    assert history["gen/population_size"] == {0: 3, 1: 4}
    # only as itself: not as a new run of that name, nor as another experiment
    with pytest.raises(FileExistsError):
        run_experiment(cfg, tracking_uri=uri, progress=False)
    config = (run_dir / "config.json").read_bytes()
    other = {**TINY, "name": "resume_t", "out_dir": str(home), "algorithm": "sp", "task": "4p2e3o", "sp": {}}
    with pytest.raises(RunError, match=r"algorithm: 'hola_no_g' -> 'sp'.*task: '4p2e1o' -> '4p2e3o'"):
        run_experiment(load_experiment(other), tracking_uri=uri, resume=True, progress=False)
    assert (run_dir / "config.json").read_bytes() == config
    second = run_experiment(cfg, tracking_uri=uri, resume=True, progress=False)
    assert [r.generation for r in second["reports"]] == [2]
    assert not first_home.exists()  # nothing was written to the old tree
    after = reg.members(run="resume_t").set_index("id")
    for member, checkpoint in after["checkpoint"].items():  # every checkpoint where the run now is, found by id
        assert Path(checkpoint).parent == run_dir / "members"
        assert resolve(member, runs_dir=home).checkpoint == Path(checkpoint)
    # what was saved is untouched: same members, same checkpoints byte for byte
    assert len(before) == 4 and list(after.index[:4]) == list(before.index)
    for member in before.index:
        assert after.loc[member, "sha256"] == before.loc[member, "sha256"]
        assert read_header(after.loc[member, "checkpoint"])["sha256"] == before.loc[member, "sha256"]
    # the resumed generation warm-started from the saved learner and continued its lineage
    (report,) = second["reports"]
    (g2,) = report.learners
    assert after.loc[g2, "parents"] == [before.index[-1]]
    assert second["mlflow_run_id"] == first["mlflow_run_id"]
    # w/o g: rho is uniform over Pi minus N_t, so every profile is equally likely
    p0, p1, p2, g1 = before.index
    graph = _check_hola_generation(report, g1, [p0, p1, p2])
    assert graph["rho"] == pytest.approx(dict.fromkeys([p0, p1, p2], 1 / 3))
    assert list(graph["profiles"].values()) == pytest.approx([1 / 3] * 3)
    # the budget continued from the saved one
    _check_budget(cfg, [*first["reports"], report])
    assert second["budget"] == report.budget
    assert {"rho", "drawn"} <= set(second["population"].columns)


def test_pbt_exploits_and_explores_and_br_trains_against_the_zoo(local_ray, tmp_path, mlflow_store):
    uri = mlflow_store(tmp_path / "mlflow.db")
    cfg = _cfg(tmp_path, "pbt_t", algorithm="pbt", generations=2, pbt={"population_size": 2}, final_zoo="")
    summary = run_experiment(cfg, tracking_uri=uri, progress=False)
    first, second = summary["reports"]
    pbt = first.documents["pbt.json"]
    # generation 0 spreads the learning rates (lr x 1.25^(i - 1/2), as its one update used them); the worst
    # member then continues from the best one's weights
    used = {t.member: t.history[0]["train/lr"] for r in (first, second) for t in r.training}  # schedule at 1
    lr = cfg.ppo["lr"]
    assert [used[m] for m in first.learners] == pytest.approx([lr / 1.25**0.5, lr * 1.25**0.5])
    ((loser, winner),) = pbt["exploited"].items()
    assert pbt["fitness"][loser] < pbt["fitness"][winner] or loser == first.learners[0]  # ties: order kept
    reg = Registry(tmp_path / "pbt_t" / "registry.db")
    members = reg.members(run="pbt_t").set_index("id")
    assert len(members) == 4 and sorted(members["generation"]) == [0, 0, 1, 1]
    # the exploited member's child names the winner as parent and started from the winner's weights ...
    child = second.learners[first.learners.index(loser)]
    heir = second.learners[first.learners.index(winner)]
    assert members.loc[child, "parents"] == [winner] and members.loc[heir, "parents"] == [winner]
    assert next(t.parent for t in second.training if t.member == child) == winner
    weights = {m: load_checkpoint(members.loc[m, "checkpoint"])[0].state_dict() for m in members.index}

    def distance(a: str, b: str) -> float:
        return float(sum((weights[a][k] - weights[b][k]).norm() ** 2 for k in weights[a]) ** 0.5)

    assert distance(child, winner) < 0.2 * distance(child, loser)  # one small update away from the winner
    # ... with the winner's hyperparameters perturbed: each multiplied or divided by perturb (pbt.json files
    # them under the loser's id: what its successor takes), and the child's update ran at that learning rate
    hp, winner_hp = pbt["hparams"][loser], pbt["hparams"][winner]
    assert set(hp) == set(winner_hp) == {"lr", "ent_coef"} and winner_hp["lr"] == pytest.approx(used[winner])
    for name, value in winner_hp.items():
        assert hp[name] / value == pytest.approx(1.25) or hp[name] / value == pytest.approx(1 / 1.25), name
    assert used[child] == pytest.approx(hp["lr"]) and used[heir] == pytest.approx(winner_hp["lr"])

    # a best response to a zoo of two rule drones (a zoo document of its own); the final evaluation on zoo1
    pair = tmp_path / "pair.json"
    pair.write_text(json.dumps({"name": "pair", "members": [{"name": n, "kind": n} for n in ("greedy", "vicsek")]}))
    br = _cfg(tmp_path, "br_t", algorithm="br", br={"zoo": str(pair)}, generations=1, final_zoo="zoo1")
    summary = run_experiment(br, tracking_uri=uri, progress=False)
    (member,) = summary["reports"][0].learners
    # it trained against exactly the configured partners: uniform over the zoo's two members, both of which
    # the rollout drew into the 2 partner slots of its episodes, and nothing else
    (trained,) = summary["reports"][0].training
    assert trained.parent is None and trained.partners == {"kind": "Uniform", "members": ["pair:greedy", "pair:vicsek"]}
    assert sum(trained.drawn.values()) >= cfg.ppo["num_envs"]  # a profile per episode started
    slots = [p for profile, n in trained.drawn.items() for p in profile.split("|") * n]
    assert len(slots) == 2 * sum(trained.drawn.values()) and set(slots) == {"pair:greedy", "pair:vicsek"}
    header = read_header(tmp_path / "br_t" / "members" / f"{member}.pt")
    assert header["algorithm"] == "br" and header["partners"] == trained.partners and header["parents"] == []
    # the reported zoo1 numbers are the member's own episodes with zoo1 partners (final evaluation seed 4242)
    policy = load_policy(tmp_path / "br_t" / "members" / f"{member}.pt")
    records = run_episodes(policy, load_task("4p2e1o"), load_zoo("zoo1").policies(), br.final_episodes, seed=4242)
    expected = metrics(records)
    row = summary["population"].iloc[0]
    for key in ("SUC", "COL", "AST", "REW"):
        assert row[f"zoo1_{key}"] == pytest.approx(expected[key], nan_ok=True), key


# ------------------------------------------------------------------ an algorithm from outside the package
@dataclass(frozen=True)
class FixedPartnersConfig:
    """zoo and member: the one partner every slot gets."""

    zoo: str = "zoo1"
    member: str = "vicsek"


@dataclass(frozen=True)
class FixedList:
    """Partners from a fixed list: partner slot i of every episode gets members[i % len(members)]."""

    members: tuple[str, ...]

    def draw(self, rng: np.random.Generator, n: int, slots: int) -> np.ndarray:
        return np.tile(np.arange(slots) % len(self.members), (n, 1))


class FixedPartners(Algorithm):
    """Each generation continues the last member against one fixed zoo partner."""

    name = "fixed"
    Config = FixedPartnersConfig

    def generation(self, oracle):
        parent = self.population[-1] if self.population else None
        (partner,) = [m for m in oracle.zoo_members(self.config.zoo) if m.endswith(f":{self.config.member}")]
        trained = oracle.train(parent, FixedList((partner,)))
        member = oracle.register(trained, [parent] if parent else [])
        self.population.append(member)
        return GenerationReport(
            oracle.generation, self.name, [member], list(self.population), [record(member, trained)]
        )


def test_an_algorithm_defined_in_a_test_plugs_into_the_table(local_ray, tmp_path, monkeypatch, mlflow_store):
    """A test's own algorithm runs in the service. Its final zoo is a protocol of team events, "zoo3+drop": the
    population is played with zoo3's drones and the drop of every episode, and the population table, the registry
    and MLflow carry the events' metrics (MLflow's keys with ``+`` as ``_``)."""
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # Ray ships this module's classes by value
    monkeypatch.setitem(ALGORITHMS, "fixed", FixedPartners)
    cfg = _cfg(tmp_path, "fixed_t", algorithm="fixed", generations=2, fixed={"member": "greedy"}, final_zoo="zoo3+drop")
    assert cfg.algorithm_config() == FixedPartnersConfig(member="greedy")
    uri = mlflow_store(tmp_path / "mlflow.db")
    summary = run_experiment(cfg, tracking_uri=uri, progress=False)
    first, second = summary["reports"]
    assert second.population == [first.learners[0], second.learners[0]]
    assert second.training[0].parent == first.learners[0]
    for report in (first, second):
        (trained,) = report.training
        assert trained.partners == {"kind": "FixedList", "members": ["zoo1:greedy"]}
        assert set(trained.drawn) == {"zoo1:greedy|zoo1:greedy"}  # what the rollout drew, per episode
    members = Registry(tmp_path / "fixed_t" / "registry.db").members(run="fixed_t")
    assert list(members["algorithm"]) == ["fixed", "fixed"]
    population = pd.read_csv(tmp_path / "fixed_t" / "population.csv")
    assert {"zoo3+drop_SUC", "zoo3+drop_EVT", "zoo3+drop_SUC_post", "zoo3+drop_REC"} <= set(population.columns)
    assert population["zoo3+drop_EVT"].max() > 0  # episodes lived to their drop: the events were played
    assert all("zoo3+drop/EVT" in m for m in members["metrics"])
    client = mlflow.MlflowClient(uri)
    keys = {
        k for r in client.search_runs([client.get_experiment_by_name("fixed_t").experiment_id]) for k in r.data.metrics
    }
    assert any(k.startswith("zoo3_drop_") for k in keys), sorted(keys)
    with pytest.raises(ConfigError, match=r"fixed\.colour"):
        _cfg(tmp_path, "fixed_bad", algorithm="fixed", fixed={"colour": "red"})


# ------------------------------------------------------------------ selection never looks at the test zoos
def test_a_learners_matches_are_dealt_round_its_workers_and_a_repeated_team_waits_for_a_later_batch():
    from atdrone.service.coordinator import match_batches

    a1, a2, a3, b1 = ("a", "a", "p", "q"), ("a", "a", "p", "r"), ("a", "a", "q", "r"), ("b", "b", "p", "q")
    assert match_batches([a1, a2, b1, a3], 2) == [[0, 3], [1], [2]]
    assert match_batches([a1, a2, a3], 1) == [[0, 1, 2]]
    assert match_batches([a1, a1, a2], 2) == [[0], [2], [1]]  # a1 twice: its second copy in a batch of its own
    with pytest.raises(ValueError, match="at least one worker"):
        match_batches([a1], 0)


def test_the_best_member_is_read_off_the_selection_zoo_alone():
    table = pd.DataFrame(
        {
            "member": ["a", "b", "c", "d"],
            "validation_SUC": [40.0, 55.0, 55.0, 55.0],  # a tie on SUC: the higher return, then the later member
            "validation_REW": [9.0, 3.0, 5.0, 5.0],
            "zoo3_SUC": [90.0, 10.0, 20.0, 0.0],
        }
    )
    members = ["a", "b", "c", "d"]
    assert select_best(table, "validation", members) == ("d", 55.0)
    assert select_best(table.assign(validation_REW=[9.0, 6.0, 5.0, 5.0]), "validation", members) == ("b", 55.0)
    for zoo3 in ([0.0] * 4, [100.0, 0.0, 0.0, 0.0], [float("nan")] * 4):  # any test-zoo result: the same choice
        assert select_best(table.assign(zoo3_SUC=zoo3), "validation", members) == ("d", 55.0)
    assert select_best(table, "", members) == ("d", None)  # no selection zoo: the last member
    assert select_best(table.assign(validation_SUC=float("nan")), "validation", members) == ("d", None)


@pytest.mark.parametrize("zoo", ["zoo1", "zoo3"])
def test_a_selection_zoo_sharing_drones_with_a_test_zoo_is_refused(tmp_path, zoo):
    with pytest.raises(ConfigError, match=r"select_zoo: .*shares drones with the test zoos \(greedy = zoo1:greedy"):
        _cfg(tmp_path, "sel", algorithm="sp", select_zoo=zoo)
    assert _cfg(tmp_path, "sel", algorithm="sp").select_zoo == "validation"


def test_the_champion_never_depends_on_a_test_zoo_evaluation(local_ray, tmp_path, monkeypatch, mlflow_store):
    """A run whose test-zoo results are replaced by planted ones that rank every member above the one the
    (real) validation results choose: the best member and the MLflow champion are still the validation's."""
    real = results._evaluate_population
    seen: dict[str, dict[str, dict[str, float]]] = {}
    planted: dict[str, float] = {}

    def evaluate(coordinator, zoo, episodes):
        results = seen[zoo] = real(coordinator, zoo, episodes)
        if zoo == "zoo3":  # the test zoo prefers every member but the validation's choice
            assert "validation" in seen, "the selection zoo is evaluated before the test zoo"
            table = pd.DataFrame(
                [
                    {"member": m, "validation_SUC": r["SUC"], "validation_REW": r["REW"]}
                    for m, r in seen["validation"].items()
                ]
            )
            best, _ = select_best(table, "validation", list(seen["validation"]))
            planted.update({m: (5.0 if m == best else 95.0) for m in results})
            for member, row in results.items():
                row["SUC"], row["REW"] = planted[member], planted[member]
        return results

    monkeypatch.setattr(results, "_evaluate_population", evaluate)
    uri = mlflow_store(tmp_path / "mlflow.db")
    cfg = _cfg(tmp_path, "sel", algorithm="sp", generations=3, final_zoo="zoo3", final_episodes=16)
    summary = run_experiment(cfg, tracking_uri=uri, progress=False)
    population = pd.read_csv(tmp_path / "sel" / "population.csv")
    assert population["member"].tolist() == ["sp-g0-0", "sp-g1-0", "sp-g2-0"]
    assert population["zoo3_SUC"].tolist() == [planted[m] for m in population["member"]]  # the plant took
    assert sorted(planted.values()) == [5.0, 95.0, 95.0]
    expected, score = select_best(population.drop(columns=["zoo3_SUC", "zoo3_REW"]), "validation", list(planted))
    champion = mlflow.MlflowClient(uri).get_model_version_by_alias("atdrone-sel", "champion")
    assert summary["best"] == champion.tags["member"] == expected
    assert planted[expected] == 5.0  # the test zoo's last choice
    assert champion.tags["score_metric"] == "validation_SUC" and float(champion.tags["score"]) == score


def test_a_drivers_runs_share_one_coordinator_and_learner_that_run_as_new_ones_would(
    local_ray, tmp_path, monkeypatch, mlflow_store
):
    """The driver's pool: a second run in the same process is run by the first run's coordinator, trains on
    its learner actor and collects on its rollout worker (no new process), and every member it trains has the
    weights of the first run's (on new ones), bit for bit. A coordinator handed back, and the rollout worker it
    keeps, hold no CPU. A learner that died while idle is not used again; a kept worker serves only its task."""
    from atdrone.service import pool

    coordinators = pool.CoordinatorPool()
    monkeypatch.setattr(pool, "COORDINATORS", coordinators)
    uri = mlflow_store(tmp_path / "mlflow.db")
    kw = {"algorithm": "sp", "generations": 1, "updates_per_generation": 2, "final_zoo": "", "num_workers": 1}
    weights, kept = {}, []
    for name in ("pool_a", "pool_b"):
        run_experiment(_cfg(tmp_path, name, **kw), tracking_uri=uri, progress=False)
        members = sorted((tmp_path / name / "members").glob("*.pt"))
        weights[name] = {p.name: load_checkpoint(p)[0].state_dict() for p in members}
        assert coordinators.created == 1 and coordinators.idle() == 1  # the second run started no coordinator
        deadline = time.monotonic() + 30  # the idle coordinator and its idle rollout worker hold no CPU (the run's
        while ray.available_resources().get("CPU", 0.0) < ray.cluster_resources()["CPU"]:  # placement group freed)
            assert time.monotonic() < deadline, "the idle coordinator's rollout worker still holds its CPU"
            time.sleep(0.05)
        coordinator = coordinators.take()
        kept.append(ray.get(coordinator.kept.remote()))
        coordinators.give_back([coordinator])
    assert len(kept[0]["learners"]) == len(kept[0]["workers"]) == 1
    assert kept[1] == kept[0]  # nor a learner, nor a rollout worker
    assert list(weights["pool_a"]) == list(weights["pool_b"]) == ["sp-g0-0.pt"]
    for member, state in weights["pool_a"].items():
        other = weights["pool_b"][member]
        assert all(torch.equal(state[k], other[k]) for k in state), member
    (learner,) = kept[0]["learners"]
    ray.kill(learner)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:  # the kill lands asynchronously: a call may still be answered first
        try:
            ray.get(learner.ping.remote(), timeout=30)
        except ray.exceptions.RayActorError:
            break
        time.sleep(0.05)
    coordinator = coordinators.take()
    ray.get(coordinator.start.remote(_cfg(tmp_path, "pool_c", **kw), ALGORITHMS["sp"], str(tmp_path), None, "registry"))
    assert ray.get(coordinator.kept.remote())["learners"] == []  # the dead learner dropped: the next training makes one
    coordinators.give_back([coordinator])
    assert coordinators.idle() == 1
    # a worker serves one task for life (Ray would restart it with its first task): another task gets a new one
    coordinator = coordinators.take()
    other = _cfg(tmp_path, "pool_d", **{**kw, "task": "4p2e3o"})
    ray.get(coordinator.start.remote(other, ALGORITHMS["sp"], str(tmp_path), None, "registry"))
    coordinators.give_back([coordinator])
    (worker,) = ray.get(coordinator.kept.remote())["workers"]
    assert worker not in kept[0]["workers"]


def test_runs_of_one_name_never_mix_one_driver_holds_a_run_and_a_resume_checks_what_it_trusts(
    local_ray, tmp_path, monkeypatch, capsys
):
    """With one registry folder for every run (the cluster's recipe): while run A's driver runs, a second driver
    on A is refused in one line naming the holder; a new run of the same name in another out dir gets a registry
    of its own and leaves A's byte-identical. Then, before Ray starts and in one line (exit 2), leaving A as it
    was (its config.json too, though each resume asks for another generation count): a member checkpoint swapped
    for another valid one, a registry file of the other run, a file that is no registry and a state file whose
    generation count is -3 are refused."""
    import os
    import signal
    import threading

    from atdrone.cli import main
    from atdrone.service import driver
    from atdrone.service.runstate import REGISTRY_DIR_ENV

    monkeypatch.setenv(REGISTRY_DIR_ENV, str(tmp_path / "registries"))
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}  # main() installs its own
    doc = {**TINY, "algorithm": "sp", "generations": 2, "num_workers": 1, "sp": {}, "name": "same"}
    a_doc, b_doc = {**doc, "out_dir": str(tmp_path / "a")}, {**doc, "out_dir": str(tmp_path / "b")}
    config = tmp_path / "same.json"
    config.write_text(json.dumps(a_doc))
    run_dir = tmp_path / "a" / "same"

    def train(*extra: str) -> tuple[int, str]:
        try:
            code = main(["train", str(config), "--no-progress", *extra])
        finally:
            for s, h in handlers.items():
                signal.signal(s, h)
        return code, capsys.readouterr().err.strip().splitlines()[-1]

    first = threading.Thread(target=run_experiment, args=(load_experiment(a_doc),), kwargs={"progress": False})
    first.start()
    try:
        while not (run_dir / STATE_FILE).exists():  # born: its driver holds it from here on
            time.sleep(0.02)
        code, line = train("--resume")
    finally:
        first.join()
    assert code == 2
    assert re.fullmatch(
        rf"atdrone train: error: run {re.escape(str(run_dir))} is in use by driver pid {os.getpid()} on \S+ since "
        r"\S+: one driver per run; wait for it to end \(or stop it\) before resuming",
        line,
    ), line
    a_registry = Path(json.loads((run_dir / STATE_FILE).read_text())["registry"])
    assert a_registry.parent.parent == tmp_path / "registries" / "same"  # keyed by the run's identifier
    with Registry(a_registry, create=False) as reg:
        assert len(reg.members()) == 2
    a_files = {p: p.read_bytes() for p in a_registry.parent.iterdir()}  # after this test's own read of it

    b = run_experiment(load_experiment(b_doc), progress=False, stop_after=1)  # same name, same registry folder
    b_registry = Path(json.loads((Path(b["run_dir"]) / STATE_FILE).read_text())["registry"])
    assert b_registry != a_registry
    assert {p: p.read_bytes() for p in a_registry.parent.iterdir()} == a_files

    def ray_started(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("Ray was started before the run was checked")

    monkeypatch.setattr(driver, "init_ray", ray_started)
    state, config_json = (run_dir / STATE_FILE).read_bytes(), (run_dir / "config.json").read_bytes()
    first_member, second_member = sorted((run_dir / "members").glob("*.pt"))
    kept = first_member.read_bytes()
    shutil.copyfile(second_member, first_member)  # a valid checkpoint, of another member
    code, line = train("--resume", "--generations", "3")
    assert code == 2 and re.fullmatch(
        rf"atdrone train: error: member {first_member.stem}: \S+ has sha256 \w+\.\.\., its registry row \w+\.\.\.: "
        "the checkpoint was replaced, so the run cannot be resumed",
        line,
    ), line
    first_member.write_bytes(kept)
    shutil.copyfile(a_registry, tmp_path / "a.db")
    shutil.copyfile(b_registry, a_registry)  # the other run's registry in A's place
    code, line = train("--resume", "--generations", "3")
    assert code == 2 and re.fullmatch(
        rf"atdrone train: error: {re.escape(str(a_registry))} is the registry of same \(run id \w+\), not of this "
        r"run \(run id \w+\)",
        line,
    ), line
    a_registry.write_bytes(b"not a registry at all")
    code, line = train("--resume", "--generations", "3")
    assert code == 2 and line == (
        f"atdrone train: error: {a_registry} is not a sqlite database, so not an atdrone registry; the run cannot be "
        "resumed"
    ), line
    shutil.copyfile(tmp_path / "a.db", a_registry)
    edited = json.loads(state)
    edited["coordinator"]["generation"] = -3
    (run_dir / STATE_FILE).write_text(json.dumps(edited))
    code, line = train("--resume", "--generations", "3")
    assert code == 2 and "-3 completed and" in line and "the run cannot be resumed" in line, line
    (run_dir / STATE_FILE).write_bytes(state)
    assert (run_dir / "config.json").read_bytes() == config_json  # every refused --generations 3 wrote nothing
    assert {p: p.read_bytes() for p in a_registry.parent.iterdir() if p.suffix == ".db"} == {
        p: b for p, b in a_files.items() if p.suffix == ".db"
    }
