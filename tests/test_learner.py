"""The one Learner: local and in the service's learner actor, its state, and every PPO field in the service."""

from __future__ import annotations

import dataclasses
import pickle
from collections import Counter
from typing import Any

import numpy as np
import pytest
import ray
import torch

from atdrone.config import load_task
from atdrone.learn.learner import Learner, LearnerSpec
from atdrone.learn.ppo import PPOConfig, ppo_config
from atdrone.learn.rollout import RolloutWorker
from atdrone.policies.zoo import build_policy, load_zoo
from atdrone.service.actors import LearnerActor, RolloutJob, RolloutWorkerActor, run_updates, update_seed
from atdrone.teams.partners import Uniform, as_sampler

TASK = load_task("4p2e1o")
SMALL = {"entity_dim": 8, "hidden": 16, "num_envs": 4, "rollout_steps": 24, "minibatch_size": 64}


def _spec(ppo: PPOConfig, seed: int = 3, total_updates: float = 2) -> LearnerSpec:
    return LearnerSpec(
        ppo=ppo, num_e=TASK.players.num_e, num_p=TASK.players.num_p, seed=seed, total_updates=total_updates
    )


def _fragments(ppo: PPOConfig, n: int = 2) -> list:
    learner = Learner(_spec(ppo))
    worker = RolloutWorker(TASK, 7, learner.model.architecture(), ppo)
    worker.set_weights(learner.get_weights())
    return [worker.collect(ppo.rollout_steps) for _ in range(n)]


def _flat(weights: dict[str, torch.Tensor]) -> torch.Tensor:
    return torch.cat([v.reshape(-1).float() for v in weights.values()])


def test_local_learner_and_learner_actor_give_bitwise_equal_parameters(local_ray):
    ppo = ppo_config(SMALL)
    fragments = _fragments(ppo)
    torch.set_num_threads(1)  # the actor updates on one thread, as rollout workers do
    local = Learner(_spec(ppo))
    remote = LearnerActor.remote(_spec(ppo))
    for frag in fragments:
        local_stats = local.update(frag)
        remote_stats = ray.get(remote.update.remote(frag))
        assert local_stats["train/policy_loss"] == remote_stats["train/policy_loss"]
    theirs = ray.get(remote.get_weights.remote())
    for name, value in local.get_weights().items():
        assert torch.equal(value, theirs[name]), name
    ray.kill(remote)


def test_learner_state_round_trips_through_a_file_without_pickle(tmp_path, monkeypatch):
    ppo = ppo_config(SMALL)
    f1, f2 = _fragments(ppo)
    first = Learner(_spec(ppo))
    first.set_hparams(lr=1e-3)
    first.update(f1)
    first.save(tmp_path / "state.safetensors", {"note": "x"})

    def refuse(*args, **kwargs):
        raise AssertionError("the learner state must load without unpickling")

    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(pickle, "Unpickler", refuse)
    monkeypatch.setattr(torch, "load", refuse)
    second = Learner(_spec(ppo, seed=99))  # another seed: everything must come from the file
    assert second.load(tmp_path / "state.safetensors") == {"note": "x"}
    assert second.updates == 1 and second.hparams == first.hparams
    first.update(f2)
    second.update(f2)
    for name, value in first.get_weights().items():
        assert torch.equal(value, second.get_weights()[name]), name


def test_linear_schedule_uses_the_position_in_the_learner_budget():
    ppo = ppo_config({**SMALL, "lr": 1e-3, "lr_schedule": "linear"})
    learner = Learner(_spec(ppo, total_updates=4))
    lrs = [learner.update(f)["train/lr"] for f in _fragments(ppo, 3)]
    assert lrs == pytest.approx([1e-3, 0.75e-3, 0.5e-3])


# --------------------------------------------------------- every PPO field in the service
CHANGES = {
    "num_envs": 8,
    "rollout_steps": 16,
    "epochs": 1,
    "minibatch_size": 32,
    "lr": 2e-4,
    "lr_schedule": "constant",
    "gamma": 0.9,
    "gae_lambda": 0.5,
    "clip": 0.001,
    "vf_coef": 0.1,
    "ent_coef": 0.1,
    "max_grad_norm": 100.0,
    "normalize_advantages": False,
    "entity_dim": 4,
    "hidden": 8,
    "init_log_std": -1.0,
    "proximity": 0.0,
    "collision_credit": "own",
    "collision_scale": 3.0,
    "history": 1,
}


def test_every_ppo_field_is_listed():
    # teammate_coef weighs a teammate model's decoder loss: test_teammate.py pins it on a NAHT-D update
    assert set(CHANGES) | {"teammate_coef"} == {f.name for f in dataclasses.fields(PPOConfig)}


@pytest.fixture(scope="module")
def service_workers(_ray_session):
    """Two rollout workers and a learner actor, used by every case of the module."""
    workers = [RolloutWorkerActor.remote(TASK) for _ in range(2)]
    learner = LearnerActor.remote()
    yield workers, learner
    for actor in (*workers, learner):
        ray.kill(actor)


def _service_update(actors: tuple[list, Any], ppo: PPOConfig) -> torch.Tensor:
    """Two updates of a best response to Zoo 1 through the service's actors; the flat parameters.

    The learner actor is reset with the new spec, as the coordinator's pool does between trainings."""
    workers, learner = actors
    zoo = tuple(load_zoo("zoo1").spec.members)
    partners = Uniform(tuple(m.name for m in zoo))
    spec = _spec(ppo)
    ray.get(learner.reset.remote(spec))
    arch = spec.model_architecture()
    jobs = [
        RolloutJob(11 + i, ppo, ppo.num_envs // 2, TASK.players.num_ctrl, arch, zoo, partners)
        for i in range(len(workers))
    ]
    run_updates(learner, workers, jobs, 2, ppo.rollout_steps)
    return _flat(ray.get(learner.get_weights.remote()))


def _local_update(ppo: PPOConfig) -> torch.Tensor:
    """The same two updates in this process: plain RolloutWorkers and a Learner, the service's seeds and
    protocol (job seeds 11 and 12, half the environments each, fragment u's action noise from (job, u))."""
    zoo = tuple(load_zoo("zoo1").spec.members)
    partners = Uniform(tuple(m.name for m in zoo))
    spec = _spec(ppo)
    torch.set_num_threads(1)  # as the learner actor
    learner = Learner(spec)
    num_ctrl = TASK.players.num_ctrl
    workers = [
        RolloutWorker(
            TASK,
            11 + i,
            spec.model_architecture(),
            ppo,
            partners=[build_policy(m) for m in zoo],
            num_ctrl=num_ctrl,
            sampler=as_sampler(partners, TASK.players.num_p - num_ctrl),
            num_envs=ppo.num_envs // 2,
        )
        for i in range(2)
    ]
    for u in range(2):
        weights = learner.get_weights()
        fragments = []
        for i, worker in enumerate(workers):
            worker.set_weights(weights)
            worker.generator.manual_seed(update_seed(11 + i, u))
            fragments.append(worker.collect(ppo.rollout_steps))
        learner.update(tuple(fragments))
    return _flat(learner.get_weights())


@pytest.fixture(scope="module")
def baseline(service_workers):
    base = ppo_config({**SMALL, "rollout_steps": 48, "lr_schedule": "linear"})
    flat = _service_update(service_workers, base)
    assert torch.equal(_service_update(service_workers, base), flat)  # the service update is deterministic
    assert torch.equal(_local_update(base), flat)
    return base, flat


@pytest.mark.parametrize("name", sorted(CHANGES))
def test_a_changed_ppo_field_gives_the_service_update_the_local_learner_gets(service_workers, baseline, name):
    """Every PPO field reaches the service's workers and learner: with the field changed, the service's two
    updates equal, bit for bit, those of a local Learner given the same change, and differ from the
    baseline's (so a field the service dropped or took from the preset would fail here)."""
    base, flat = baseline
    assert getattr(base, name) != CHANGES[name], f"{name}: the change is the baseline's value"
    ppo = dataclasses.replace(base, **{name: CHANGES[name]})
    changed = _service_update(service_workers, ppo)
    assert changed.shape != flat.shape or not torch.equal(changed, flat)
    local = _local_update(ppo)
    assert changed.shape == local.shape and torch.equal(changed, local)


def test_experiment_refuses_ppo_num_envs_that_workers_cannot_split():
    from atdrone.config import ConfigError
    from atdrone.service.experiment import load_experiment

    doc = {"name": "x", "algorithm": "sp", "task": "4p2e1o", "num_workers": 3, "ppo": {"num_envs": 64}}
    with pytest.raises(ConfigError, match=r"ppo\.num_envs"):
        load_experiment(doc)
    with pytest.raises(ConfigError, match="envs_per_worker: moved"):
        load_experiment({**doc, "num_workers": 2, "envs_per_worker": 32})
    with pytest.raises(ConfigError, match=r"hola\.population_size"):
        load_experiment({**doc, "num_workers": 2, "algorithm": "hola", "hola": {"population_size": 1}})


def test_rollout_records_partner_draws_and_executed_turns():
    ppo = ppo_config(SMALL)
    zoo = load_zoo("zoo1")
    learner = Learner(_spec(ppo))
    worker = RolloutWorker(TASK, 5, learner.model.architecture(), ppo, partners=zoo.policies())
    worker.set_weights(learner.get_weights())
    frag = worker.collect(200)
    members = frag.extras["partner_members"]
    assert members.shape == (200, 4, 2) and set(np.unique(members)) <= set(range(len(zoo)))
    assert np.all(np.abs(frag.extras["partner_actions"]) <= 1.0)
    slots = frag.extras["learner_slots"]
    assert slots.shape == (200, 4, 2) and np.all(np.sort(slots, -1)[..., 0] != np.sort(slots, -1)[..., 1])
    ended = [e for e in frag.episodes]
    assert ended and all(len(e["partners"]) == 2 for e in ended)
    # drawn: the profile (ids sorted) of every episode started, the 4 first ones and one after each end
    assert sum(worker.drawn.values()) == len(ended) + 4
    ends: Counter[str] = Counter("|".join(sorted(e["partners"])) for e in ended)
    assert all(worker.drawn[profile] >= n for profile, n in ends.items())
    flat = frag.batch(ppo.gamma, ppo.gae_lambda, extras=True)
    assert flat["partner_members"].shape == (200 * 4 * 2, 2)
