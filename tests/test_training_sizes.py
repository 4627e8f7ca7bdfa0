"""Team sizes drawn in training: a protocol's ``sizes`` range.

Each rollout is played at a size drawn from the range, on the task's shipped variant
with that many pursuers; the environments of a size keep their episodes between its
rollouts; the PPO update takes each size's samples in minibatches of their own. Without
sizes the update is as before, bit for bit.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from atdrone.config import ConfigError, TaskConfig, load_task
from atdrone.learn.learner import Learner, LearnerSpec
from atdrone.learn.ppo import PRESETS, architecture, minibatches, ppo_update
from atdrone.learn.rollout import RolloutWorker
from atdrone.learn.sizes import MixedSizeWorker, make_worker, size_seed, size_tasks
from atdrone.learn.trainer import load_train_config
from atdrone.policies.base import Policy
from atdrone.policies.rules import GreedyPolicy
from atdrone.service.experiment import load_experiment
from atdrone.teams.evaluation import evaluate
from atdrone.teams.partners import Uniform, profiles
from atdrone.teams.protocols import is_protocol, load_protocol, parse_protocol, zoo_of

TASK = "4p2e1o"
PPO = replace(PRESETS["default"], num_envs=8, rollout_steps=16, minibatch_size=64, epochs=2, entity_dim=8, hidden=16)
ARCH = architecture(PPO)


def _doc(tmp_path: Path, **doc: object) -> str:
    path = tmp_path / "sizes.json"
    path.write_text(json.dumps({"name": "sized", "zoo": "zoo3", **doc}))
    return str(path)


def _learner(seed: int = 0) -> Learner:
    return Learner(LearnerSpec(PPO, 2, 4, seed, 10.0, architecture=ARCH))


def test_a_protocol_may_draw_team_sizes_and_is_then_for_training_only(tmp_path: Path) -> None:
    protocol = parse_protocol({"zoo": "zoo3", "sizes": [3, 6]}, "s")
    assert protocol.sizes == (3, 6) and protocol.split is None and not len(protocol.plan)
    assert protocol.to_dict()["sizes"] == [3, 6]
    assert load_protocol("sizes3-6").sizes == (3, 6)  # the shipped one
    assert "sizes" not in load_protocol("zoo3+swap").to_dict()
    for bad in ([1, 3], [4, 3], [3], "3-6", [3, True]):
        with pytest.raises(ConfigError, match="sizes"):
            parse_protocol({"zoo": "zoo3", "sizes": bad}, "s")
    path = _doc(tmp_path, sizes=[3, 5])
    assert is_protocol(path)
    with pytest.raises(ConfigError, match=r"sizes.*only training"):
        zoo_of(path)
    with pytest.raises(ConfigError, match=r"sizes.*only training"):
        evaluate(GreedyPolicy(), TASK, "zoo1", episodes=2, protocol=path)


def test_the_sizes_are_the_tasks_shipped_variants_and_a_missing_one_is_named() -> None:
    tasks = size_tasks(load_task(TASK), (3, 6))
    assert [t.players.num_p for t in tasks] == [3, 4, 5, 6]
    assert [t.name for t in tasks] == ["3p2e1o", "4p2e1o", "5p2e1o", "6p2e1o"]
    assert {(t.players.num_e, len(t.site.obstacles)) for t in tasks} == {(2, 1)}
    with pytest.raises(ConfigError, match=r"no task variant 3p2e5o"):
        size_tasks(load_task("4p2e5o"), (3, 4))


def test_each_rollout_is_played_at_a_drawn_size_and_a_worker_repeats_from_its_seed() -> None:
    weights = _learner().get_weights()
    runs = []
    for _ in range(2):
        worker = make_worker(load_task(TASK), 3, ARCH, PPO, sizes=(3, 6))
        assert isinstance(worker, MixedSizeWorker)
        worker.set_weights(weights)
        runs.append([worker.collect(8) for _ in range(12)])
    first, again = runs
    assert {f.num_p for f in first} == {3, 4, 5, 6}  # every size drawn in 12 rollouts (this seed)
    for f, g in zip(first, again, strict=True):
        assert f.num_p == g.num_p and np.array_equal(f.obs, g.obs) and np.array_equal(f.rewards, g.rewards)
        assert f.obs.shape == (8, 8, f.num_p, 4 * (f.num_p + 2))  # every pursuer a learner; its teammates seen
        assert {len(e["partners"]) for e in f.episodes} <= {0}  # self-play: no partner drawn


def test_the_environments_of_a_size_keep_their_episodes_between_its_rollouts() -> None:
    """Two rollouts at one size continue the same episodes: their steps as one longer rollout's."""
    three = size_tasks(load_task(TASK), (3, 3))
    worker = MixedSizeWorker(three, 5, ARCH, PPO)
    single = RolloutWorker(three[0], size_seed(5, 3), ARCH, PPO)
    weights = _learner().get_weights()
    for w in (worker, single):
        w.set_weights(weights)
    single.generator = torch.Generator().manual_seed(5 + 2)  # the mixed worker's shared noise
    parts = [worker.collect(8) for _ in range(2)]
    whole = single.collect(16)
    assert np.array_equal(np.concatenate([p.obs for p in parts]), whole.obs)
    assert np.array_equal(np.concatenate([p.dones for p in parts]), whole.dones)


def test_minibatches_are_each_of_one_group_and_one_group_is_shuffled_as_before() -> None:
    g = torch.Generator().manual_seed(0)
    taken = minibatches([5, 3], 2, g)
    assert sorted(len(idx) for _, idx in taken) == [2, 2, 2]  # 5 -> 2 + 2 (one left out), 3 -> 2 (one left out)
    for group in (0, 1):
        seen = torch.cat([idx for k, idx in taken if k == group])
        assert len(set(seen.tolist())) == len(seen) and seen.max() < (5, 3)[group]
    one, old = (
        minibatches([10], 4, torch.Generator().manual_seed(1)),
        torch.randperm(10, generator=torch.Generator().manual_seed(1)),
    )
    assert [idx.tolist() for _, idx in one] == [old[0:4].tolist(), old[4:8].tolist()]


def test_an_update_over_two_sizes_trains_on_each_and_one_size_is_the_plain_update() -> None:
    worker = make_worker(load_task(TASK), 3, ARCH, PPO, sizes=(3, 6))
    learner = _learner()
    worker.set_weights(learner.get_weights())
    frags = [worker.collect(16) for _ in range(4)]
    assert len({f.num_p for f in frags}) > 1
    before = {k: v.clone() for k, v in learner.get_weights().items()}
    stats = learner.update(frags)
    assert stats["train/samples"] == sum(f.u.size for f in frags)
    assert stats["train/team_size"] == pytest.approx(sum(f.num_p * f.u.size for f in frags) / stats["train/samples"])
    assert any(not torch.equal(before[k], v) for k, v in learner.get_weights().items())
    # one size given as a (pursuers, batch) list: the same update as the plain batch, bit for bit
    frag = frags[0]
    results = []
    for batch in (frag.batch(0.99, 0.95), [(frag.num_p, frag.batch(0.99, 0.95))]):
        model = _learner(1).model
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)
        ppo_update(model, opt, batch, PPO, 2, frag.num_p, torch.Generator().manual_seed(2))  # type: ignore[arg-type]
        results.append(model.state_dict())
    assert all(torch.equal(results[0][k], results[1][k]) for k in results[0])


def test_with_partners_the_learner_keeps_its_slots_and_partners_fill_the_others() -> None:
    """Best-response style: 2 learner slots, the zoo's drones in 1 to 4 partner slots by size, each size with
    policies of its own; a team without a partner slot is refused."""
    made: list[int] = []

    def partners(task: TaskConfig) -> list[Policy | None]:
        made.append(task.players.num_p)
        return [GreedyPolicy(), None]  # a zoo drone and a copy of the learner

    worker = make_worker(
        load_task(TASK), 4, ARCH, PPO, sizes=(3, 6), partners=partners, num_ctrl=2, distribution=Uniform(("a", "b"))
    )
    assert isinstance(worker, MixedSizeWorker) and made == [3, 4, 5, 6]
    worker.set_weights(_learner().get_weights())
    frags = [worker.collect(8) for _ in range(10)]
    assert {f.num_p for f in frags} == {3, 4, 5, 6}
    for f in frags:
        assert f.u.shape == (8, 8, 2) and f.extras["partner_members"].shape == (8, 8, f.num_p - 2)
        assert f.obs.shape[-1] == 4 * (f.num_p + 2)
    with pytest.raises(ConfigError, match="no partner slot"):
        make_worker(load_task(TASK), 4, ARCH, PPO, sizes=(3, 6), partners=partners, num_ctrl=3)


def test_a_partner_profile_fills_fewer_slots_with_a_subset_of_its_members_and_more_from_its_members() -> None:
    dist = profiles({("a", "b", "c"): 0.5, ("d", "e", "f"): 0.5})
    same = dist.resized(3)(np.random.default_rng(1), 50)
    assert np.array_equal(same, dist.draw(np.random.default_rng(1), 50, 3))  # its own count: the plain draw
    fewer, more = dist.resized(2)(np.random.default_rng(2), 400), dist.resized(5)(np.random.default_rng(3), 400)
    assert fewer.shape == (400, 2) and more.shape == (400, 5)
    for team in (fewer, more):
        assert (team // 3 == team[:, :1] // 3).all()  # one profile's members alone (a, b, c: 0-2; d, e, f: 3-5)
    assert (fewer[:, 0] != fewer[:, 1]).all()  # a subset: without replacement
    assert {tuple(sorted(r)) for r in fewer} == {(0, 1), (0, 2), (1, 2), (3, 4), (3, 5), (4, 5)}  # every subset
    assert all({0, 1, 2} <= set(r) or {3, 4, 5} <= set(r) for r in more)  # the whole profile, and extras
    assert set(np.unique(more[:, 3:])) == {0, 1, 2, 3, 4, 5}


def test_hola_profiles_fill_every_size_with_their_members() -> None:
    """HOLA-Drone V2's partner profiles of 2 (a team of 4, 2 learner slots) fill 1 to 4 partner slots by size."""
    worker = make_worker(
        load_task(TASK),
        4,
        ARCH,
        PPO,
        sizes=(3, 6),
        partners=lambda task: [GreedyPolicy(), GreedyPolicy(), GreedyPolicy()],
        num_ctrl=2,
        distribution=profiles({("a", "b"): 0.5, ("a", "c"): 0.5}),
    )
    worker.set_weights(_learner().get_weights())
    frags = [worker.collect(8) for _ in range(10)]
    assert {f.num_p for f in frags} == {3, 4, 5, 6}
    for f in frags:
        teams = f.extras["partner_members"].reshape(-1, f.num_p - 2)
        assert ((teams == 0).any(1) | (f.num_p == 3)).all()  # both profiles hold "a": a team of 2+ partners has it
        assert not ((teams == 1).any(1) & (teams == 2).any(1)).any()  # never b and c: one profile per episode
        if f.num_p >= 4:
            assert ((teams == 1).any(1) | (teams == 2).any(1)).all()  # the whole profile, extras from it


def test_naht_d_trains_at_drawn_sizes_with_its_decoder() -> None:
    """NAHT-D built for 4 pursuers: rollouts at 3 to 6 record each size's teammates' actions, and one update
    over every size trains the decoder on the teammates its encoder reads (a finite, positive loss)."""
    from atdrone.models.teammate import TeammateActorCritic, TeammateConfig

    arch = TeammateActorCritic.header(TeammateConfig(decoder=True, entity_dim=8, hidden=16))
    spec = LearnerSpec(PPO, 2, 4, 0, 10.0, architecture=arch)
    learner = Learner(spec)
    worker = make_worker(
        load_task(TASK),
        5,
        spec.model_architecture(),
        PPO,
        sizes=(3, 6),
        partners=lambda task: [GreedyPolicy(), None],
        num_ctrl=2,
        distribution=Uniform(("greedy", "self")),
    )
    worker.set_weights(learner.get_weights())
    frags = [worker.collect(16) for _ in range(8)]
    assert {f.num_p for f in frags} == {3, 4, 5, 6}
    for f in frags:
        assert f.mates is not None and f.mates.shape == (16, 8, 2, f.num_p - 1, 3)
    stats = learner.update(frags)
    assert np.isfinite(stats["train/decoder_loss"]) and stats["train/decoder_loss"] > 0
    assert all(torch.isfinite(v).all() for v in learner.get_weights().values())


def test_a_centralised_critic_reads_the_global_state_of_an_updates_one_size_other_than_the_tasks() -> None:
    """MAPPO built for 4 pursuers: an update whose every rollout was played in a team of 6 (one size drawn by
    every worker) reads the global state as 6 pursuers'."""
    arch = architecture(PPO, centralised_critic=True)
    learner = Learner(LearnerSpec(PPO, 2, 4, 0, 10.0, architecture=arch))
    worker = make_worker(load_task(TASK), 3, arch, PPO, sizes=(6, 6))
    worker.set_weights(learner.get_weights())
    frags = [worker.collect(16) for _ in range(2)]
    assert {f.num_p for f in frags} == {6}
    stats = learner.update(frags)
    assert stats["train/team_size"] == 6 and np.isfinite(stats["train/value_loss"])


def test_every_algorithm_takes_sizes_and_a_missing_variant_is_refused(tmp_path: Path) -> None:
    path = _doc(tmp_path, sizes=[3, 6])
    doc = {"name": "t", "task": TASK, "out_dir": str(tmp_path), "protocol": path}
    for mode in ({}, {"mode": "mappo"}, {"mode": "best_response", "zoo": "zoo1"}):
        assert load_train_config({**doc, **mode}).protocol
    with pytest.raises(ConfigError, match=r"protocol\.sizes: no task variant"):
        load_train_config({**doc, "task": "4p2e5o"})
    experiment = {"name": "e", "task": TASK, "out_dir": str(tmp_path), "protocol": path, "gif": False}
    for algorithm in ("sp", "pbt", "mappo", "fcp", "naht_d", "naht_d_no_dec", "hola", "hola_no_g"):
        assert load_experiment({**experiment, "algorithm": algorithm}).protocol
    with pytest.raises(ConfigError, match=r"protocol\.sizes: no task variant"):
        load_experiment({**experiment, "algorithm": "hola", "task": "4p2e5o"})


def test_the_service_trains_a_best_response_at_drawn_sizes_and_records_the_protocol(
    local_ray: str, tmp_path: Path, mlflow_store: Any
) -> None:
    """A tiny best response to Zoo 1 on the session's Ray with teams of 3 to 6: its two workers' rollouts are
    played at drawn sizes, the learner in its 2 slots, Zoo 1's drones in the 1 to 4 others (each update's mean
    team size is logged); the registry's member tags and MLflow record the protocol."""
    import mlflow

    from atdrone.registry import Registry
    from atdrone.service.driver import run_experiment

    cfg = load_experiment(
        {
            "name": "sized",
            "algorithm": "br",
            "br": {"zoo": "zoo1"},
            "task": TASK,
            "generations": 1,
            "updates_per_generation": 3,
            "num_workers": 2,
            "eval_episodes": 4,
            "final_zoo": "zoo1",
            "final_episodes": 4,
            "gif": False,
            "out_dir": str(tmp_path),
            "protocol": "sizes3-6",
            "ppo": {
                "epochs": 1,
                "entity_dim": 8,
                "hidden": 16,
                "minibatch_size": 64,
                "num_envs": 8,
                "rollout_steps": 16,
            },
        }
    )
    uri = mlflow_store(tmp_path / "mlflow.db")
    (report,) = run_experiment(cfg, tracking_uri=uri, progress=False)["reports"]
    (trained,) = report.training
    assert trained.env_steps == 3 * 8 * 16
    sizes = [h["train/team_size"] for h in trained.history]  # each update's mean pursuers per sample
    assert len(set(sizes)) > 1 and all(3 <= m <= 6 for m in sizes), sizes  # drawn per rollout, 3 to 6
    assert trained.samples == 2 * trained.env_steps  # the learner's 2 slots at every size
    drawn = {len(profile.split("|")) for profile in trained.drawn}  # partners per episode: the size's free slots
    assert len(drawn) > 1 and drawn <= {1, 2, 3, 4}, trained.drawn
    (tags,) = Registry(tmp_path / "sized" / "registry.db").members(run="sized")["tags"]
    assert tags["protocol"]["sizes"] == [3, 6]
    client = mlflow.MlflowClient(uri)
    experiment = client.get_experiment_by_name("sized")
    assert experiment is not None
    runs = client.search_runs([experiment.experiment_id])
    assert {r.data.tags.get("atdrone.protocol") for r in runs if not r.data.tags.get("mlflow.parentRunId")} == {
        "sizes3-6"
    }
