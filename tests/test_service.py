"""The Ray population service on a real local Ray (num_cpus=2), a real MLflow store and sqlite: the algorithms.

HOLA's generations in the registry and MLflow and the partner profiles its training draws, a rollout worker
killed mid-collect, a zoo with a missing checkpoint, PBT and a best response, and an algorithm defined in a
test. A run's selection, the driver's pool, resume and one driver per run: tests/test_service_runs.py.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import mlflow
import numpy as np
import pandas as pd
import pytest
import ray
from service_helpers import HOLA, TINY, _cfg, _check_budget, _check_hola_generation

from atdrone.config import ConfigError, load_task
from atdrone.models.checkpoint import load_checkpoint, read_header
from atdrone.policies.neural import load_policy
from atdrone.policies.zoo import load_zoo
from atdrone.population import ALGORITHMS
from atdrone.population.base import Algorithm, GenerationReport, record
from atdrone.registry import Registry
from atdrone.service.driver import run_experiment
from atdrone.teams.evaluation import metrics, run_episodes


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
    and MLflow carry the events' metrics (MLflow's keys with ``+`` as ``_``). It trains with a protocol that draws
    the split of the team, one of its two learner slots in every episode: its updates use half of the learner
    drone-steps, and each member's registry tags and the MLflow run record the protocol."""
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # Ray ships this module's classes by value
    monkeypatch.setitem(ALGORITHMS, "fixed", FixedPartners)
    split = {"name": "one-of-two", "zoo": "zoo3", "learners": [1, 1]}
    (tmp_path / "split.json").write_text(json.dumps(split))
    cfg = _cfg(
        tmp_path,
        "fixed_t",
        algorithm="fixed",
        generations=2,
        fixed={"member": "greedy"},
        final_zoo="zoo3+drop",
        protocol=str(tmp_path / "split.json"),
    )
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
        assert trained.samples == trained.env_steps  # 1 of the 2 learner slots trained on, every episode
    members = Registry(tmp_path / "fixed_t" / "registry.db").members(run="fixed_t")
    assert list(members["algorithm"]) == ["fixed", "fixed"]
    assert all(tags["protocol"] == {**split, "description": "", "events": []} for tags in members["tags"])
    population = pd.read_csv(tmp_path / "fixed_t" / "population.csv")
    assert {"zoo3+drop_SUC", "zoo3+drop_EVT", "zoo3+drop_SUC_post", "zoo3+drop_REC"} <= set(population.columns)
    assert population["zoo3+drop_EVT"].max() > 0  # episodes lived to their drop: the events were played
    assert all("zoo3+drop/EVT" in m for m in members["metrics"])
    client = mlflow.MlflowClient(uri)
    keys = {
        k for r in client.search_runs([client.get_experiment_by_name("fixed_t").experiment_id]) for k in r.data.metrics
    }
    assert any(k.startswith("zoo3_drop_") for k in keys), sorted(keys)
    (run,) = [
        r
        for r in client.search_runs([client.get_experiment_by_name("fixed_t").experiment_id])
        if not r.data.tags.get("mlflow.parentRunId")
    ]
    assert run.data.tags["atdrone.protocol"] == "one-of-two"
    assert json.loads(Path(client.download_artifacts(run.info.run_id, "protocol.json", str(tmp_path))).read_text())[
        "learners"
    ] == [1, 1]
    with pytest.raises(ConfigError, match=r"fixed\.colour"):
        _cfg(tmp_path, "fixed_bad", algorithm="fixed", fixed={"colour": "red"})
