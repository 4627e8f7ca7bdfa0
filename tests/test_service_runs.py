"""The Ray population service on a real local Ray (num_cpus=2), a real MLflow store and sqlite: a run's life.

A stopped run resumed wherever its directory now is; its best member and champion read off the selection
zoo alone; a driver's runs sharing one coordinator and learner; runs of one name never mixing, one driver
per run, and what a resume refuses to trust. The algorithms themselves: tests/test_service.py.
"""

from __future__ import annotations

import json
import re
import shutil
import time
from pathlib import Path
from typing import Any

import mlflow
import pandas as pd
import pytest
import ray
import torch
from service_helpers import HOLA, TINY, _cfg, _check_budget, _check_hola_generation

from atdrone.config import ConfigError
from atdrone.models.checkpoint import load_checkpoint, read_header
from atdrone.population import ALGORITHMS
from atdrone.registry import Registry
from atdrone.resolve import resolve
from atdrone.rundir import RunError
from atdrone.service import results
from atdrone.service.driver import STATE_FILE, run_experiment, select_best
from atdrone.service.experiment import load_experiment


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
