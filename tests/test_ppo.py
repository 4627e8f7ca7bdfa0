"""PPO pieces: GAE, tanh-Gaussian log-probs, checkpoints, resume, and a seeded learning run."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from typing import Any, cast

import numpy as np
import pandas as pd
import pytest
import torch

from atdrone.config import ConfigError
from atdrone.envs import BatchedPursuit
from atdrone.learn.ppo import PPOConfig, gae, ppo_config, ppo_update
from atdrone.learn.rollout import credited_rewards
from atdrone.learn.trainer import Trainer, load_train_config
from atdrone.models.checkpoint import CheckpointError, load_checkpoint, read_header, save_checkpoint, sign_header
from atdrone.models.networks import ActorCritic, NetConfig, action_log_prob, global_state, squash_log_prob
from atdrone.policies.base import DroneBatch
from atdrone.policies.neural import load_policy


def gae_loop(rewards, values, dones, last_values, gamma, lam):
    """Plain per-element GAE: the reference for the vectorised one."""
    T = rewards.shape[0]
    adv = np.zeros_like(rewards)
    for idx in np.ndindex(*rewards.shape[1:]):
        running = 0.0
        for t in reversed(range(T)):
            next_v = last_values[idx] if t == T - 1 else values[(t + 1, *idx)]
            live = 1.0 - dones[(t, *idx)]
            delta = rewards[(t, *idx)] + gamma * next_v * live - values[(t, *idx)]
            running = delta + gamma * lam * live * running
            adv[(t, *idx)] = running
    return adv, adv + values


def test_vectorised_gae_equals_plain_loop():
    rng = np.random.default_rng(0)
    shape = (17, 5, 3)
    rewards = rng.normal(size=shape).astype(np.float32)
    values = rng.normal(size=shape).astype(np.float32)
    dones = (rng.random(shape) < 0.15).astype(np.float32)
    last = rng.normal(size=shape[1:]).astype(np.float32)
    adv, ret = gae(rewards, values, dones, last, 0.97, 0.9)
    ref_adv, ref_ret = gae_loop(rewards, values, dones, last, 0.97, 0.9)
    np.testing.assert_allclose(adv, ref_adv, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(ret, ref_ret, rtol=1e-5, atol=1e-5)


def test_gae_one_step_by_hand():
    adv, ret = gae(np.array([[1.0]]), np.array([[0.5]]), np.array([[0.0]]), np.array([2.0]), 0.9, 0.8)
    assert adv[0, 0] == pytest.approx(1.0 + 0.9 * 2.0 - 0.5)
    assert ret[0, 0] == pytest.approx(1.0 + 0.9 * 2.0)


def test_tanh_gaussian_log_prob_matches_change_of_variables():
    dist = torch.distributions.Normal(torch.tensor([0.3, -1.0, 2.0]), torch.tensor([0.5, 0.2, 1.0]))
    u = torch.tensor([0.1, -2.0, 4.0], dtype=torch.float64).float()
    expected = dist.log_prob(u) - torch.log(1 - torch.tanh(u.double()) ** 2).float()
    torch.testing.assert_close(squash_log_prob(dist, u), expected, rtol=1e-4, atol=1e-4)


def test_tanh_gaussian_log_prob_is_finite_and_right_at_the_bounds():
    dist = torch.distributions.Normal(torch.zeros(4), torch.ones(4))
    # far in the tails tanh(u) rounds to +-1; the stable form stays finite and exact
    u = torch.tensor([-30.0, -12.0, 12.0, 30.0])
    lp = squash_log_prob(dist, u)
    assert torch.isfinite(lp).all()
    # log(1 - tanh(u)^2) ~ log 4 - 2|u| for large |u|
    expected = dist.log_prob(u) - (math.log(4.0) - 2 * u.abs())
    torch.testing.assert_close(lp, expected, rtol=1e-5, atol=1e-4)
    # actions given exactly at the bounds (from another policy) are clamped, not infinite
    a = torch.tensor([-1.0, -1.0, 1.0, 1.0])
    assert torch.isfinite(action_log_prob(dist, a)).all()


def _trained_model(seed: int = 0) -> ActorCritic:
    torch.manual_seed(seed)
    model = ActorCritic(NetConfig(entity_dim=16, hidden=32))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return model


def _header(**extra):
    return {"task": "4p2e1o", "num_p": 4, "num_e": 2, "seed": 0, "step": 7, **extra}


def test_checkpoint_round_trips_to_identical_actions(tmp_path):
    model = _trained_model()
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, _header(name="m"))
    policy = load_policy(path)
    env = BatchedPursuit("4p2e1o", num_envs=8, seed=3)
    obs = env.reset()
    batch = DroneBatch.all_slots(obs)
    with torch.no_grad():
        direct = torch.tanh(model.dist(torch.from_numpy(batch.obs), 2).mean).numpy()
    np.testing.assert_array_equal(policy.act(batch), direct)
    header = read_header(path)
    assert header["step"] == 7 and header["architecture"]["hidden"] == 32 and len(header["sha256"]) == 64
    assert path.read_bytes().startswith(b"ATDRONE-CHECKPOINT 1\n")


def test_loaded_checkpoint_works_for_three_evaders(tmp_path):
    path = tmp_path / "m.pt"
    save_checkpoint(path, _trained_model(), _header())
    policy = load_policy(path)
    env = BatchedPursuit("4p3e5o", num_envs=2, seed=0)
    actions = policy.act(DroneBatch.all_slots(env.reset()))
    assert actions.shape == (8,) and np.all(np.abs(actions) <= 1)


def test_corrupted_checkpoint_is_refused(tmp_path):
    path = tmp_path / "m.pt"
    save_checkpoint(path, _trained_model(), _header())
    data = bytearray(path.read_bytes())
    data[-10] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="sha256"):
        load_checkpoint(path)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda b: b"NOT A CHECKPOINT\n" + b, "magic"),
        (lambda b: b[:30], "header"),
        (lambda b: b.replace(b'"hidden": 32', b'"hidden": 64'), "header was changed"),
        ({"obs_layout_version": 9}, "layout"),
        ({"architecture": ActorCritic.header(NetConfig(entity_dim=16, hidden=64))}, "architecture"),
    ],
)
def test_mismatched_checkpoint_is_refused(tmp_path, mutate, message):
    """Damaged files, an edited header, and (signed again, as another atdrone would write them) a header
    whose layout or architecture does not fit."""
    path = tmp_path / "m.pt"
    save_checkpoint(path, _trained_model(), _header())
    if isinstance(mutate, dict):
        sign_header(path, **mutate)
    else:
        path.write_bytes(mutate(path.read_bytes()))
    with pytest.raises(CheckpointError, match=message):
        load_checkpoint(path)


def test_checkpoint_for_another_task_is_refused(tmp_path):
    path = tmp_path / "m.pt"
    save_checkpoint(path, _trained_model(), _header())
    with pytest.raises(CheckpointError, match="4p2e5o"):
        load_checkpoint(path, expect_task="4p2e5o")


def test_ppo_config_rejects_bad_values_by_name():
    with pytest.raises(ConfigError, match=r"ppo\.lr"):
        ppo_config({"lr": -1.0})
    with pytest.raises(ConfigError, match=r"ppo\.epochs"):
        ppo_config({"epochs": "many"})
    with pytest.raises(ConfigError, match=r"ppo\.bogus"):
        ppo_config({"bogus": 1})
    assert ppo_config(preset="paper").epochs == 20 and ppo_config(preset="paper").minibatch_size == 256


def _tiny(tmp_path, **kw):
    doc = {
        "name": "tiny",
        "task": "4p2e1o",
        "seed": 1,
        "total_env_steps": 10_000,
        "eval_every": 1000,
        "eval_episodes": 4,
        "out_dir": str(tmp_path),
        "ppo": {"epochs": 2, "num_envs": 8, "rollout_steps": 32, "minibatch_size": 256, "entity_dim": 16, "hidden": 32},
    }
    doc.update(kw)
    return load_train_config(doc)


TIMING = ("perf/", "wall_s")  # wall-clock measurements: the only history fields a resume may change


def _untimed(rows: list[dict]) -> str:
    """History rows without their timing fields, as JSON (NaN, e.g. eval/AST without captures, equals NaN)."""
    return json.dumps([{k: v for k, v in row.items() if not k.startswith(TIMING)} for row in rows], sort_keys=True)


def _assert_same_learner(got: Trainer, want: Trainer) -> None:
    """Every parameter, every optimiser slot and setting, the update generator and the counters, equal."""
    assert (got.updates, got.env_steps) == (want.updates, want.env_steps)
    weights, reference = got.model.state_dict(), want.model.state_dict()
    assert list(weights) == list(reference)
    for name in reference:
        assert torch.equal(weights[name], reference[name]), name
    optim, optim_ref = got.learner.optimizer.state_dict(), want.learner.optimizer.state_dict()
    groups = [json.loads(json.dumps(g)) for g in (optim["param_groups"], optim_ref["param_groups"])]
    assert groups[0] == groups[1]  # lr (the schedule's position), betas, eps: as JSON (betas come back a list)
    assert list(optim["state"]) == list(optim_ref["state"]) and len(optim_ref["state"]) == len(reference)
    for idx, slots in optim_ref["state"].items():
        assert set(optim["state"][idx]) == set(slots) == {"step", "exp_avg", "exp_avg_sq"}
        for slot, value in slots.items():
            assert torch.equal(torch.as_tensor(optim["state"][idx][slot]), torch.as_tensor(value)), (idx, slot)
    assert torch.equal(got.learner.generator.get_state(), want.learner.generator.get_state())


@pytest.mark.parametrize("protocol", [None, "sizes3-6"])
def test_a_run_killed_after_a_save_and_resumed_ends_as_the_uninterrupted_run(tmp_path, monkeypatch, protocol):
    """Four updates with an evaluation and a save every two: run A straight through; run B killed right after
    its first save (update 2) and resumed in a new Trainer. Both end with the same weights, optimiser state,
    generator and history rows (evaluations included; only wall-clock fields differ), and the same history.csv.
    So too with team sizes drawn per rollout (teams of 3 to 6)."""
    kw = {"total_env_steps": 4 * 8 * 32, "eval_every": 2, "checkpoint_every": 2, "eval_episodes": 2}
    if protocol:
        kw.update(protocol=protocol, seed=3)  # seed 1 happens to draw teams of 5 for all four rollouts
    a = Trainer(_tiny(tmp_path / "a", **kw))
    a.train(progress=False)
    assert a.updates == 4 and len(a.history) == 4 and [("eval/SUC" in r) for r in a.history] == [0, 1, 0, 1]
    sizes = {r["train/samples"] / (8 * 32) for r in a.history}  # pursuers per env step: the rollouts' team sizes
    assert sizes == {4.0} if protocol is None else len(sizes) > 1 and sizes <= {3.0, 4.0, 5.0, 6.0}, sizes

    class Killed(Exception):
        pass

    b = Trainer(_tiny(tmp_path / "b", **kw))
    save = b.save

    def save_then_die(metrics_now=None):
        save(metrics_now)
        raise Killed

    monkeypatch.setattr(b, "save", save_then_die)
    with pytest.raises(Killed):
        b.train(progress=False)
    assert b.updates == 2
    resumed = Trainer(_tiny(tmp_path / "b", **kw))
    assert resumed.resume()
    _assert_same_learner(resumed, b)  # the state at the save, restored
    assert json.dumps(resumed.history, sort_keys=True) == json.dumps(b.history, sort_keys=True)
    assert len(resumed.history) == 2
    resumed.train(progress=False)
    _assert_same_learner(resumed, a)
    assert _untimed(resumed.history) == _untimed(a.history)
    assert all(sum(not k.startswith(TIMING) for k in r) > 10 for r in a.history)  # train/ and eval/ fields
    curves = [pd.read_csv(d / "tiny" / "history.csv") for d in (tmp_path / "b", tmp_path / "a")]
    timing = [c for c in curves[1].columns if c.startswith(TIMING)]
    assert sorted(curves[0].columns) == sorted(curves[1].columns) and timing
    # the same rows and values (the resumed file's columns come in another order: its first rows went through JSON)
    pd.testing.assert_frame_equal(curves[0].drop(columns=timing), curves[1].drop(columns=timing), check_like=True)
    want, _ = load_checkpoint(tmp_path / "a" / "tiny" / "last.pt")
    got, _ = load_checkpoint(tmp_path / "b" / "tiny" / "last.pt")
    for name, value in want.state_dict().items():
        assert torch.equal(got.state_dict()[name], value), name


def test_train_config_errors_name_the_field(tmp_path):
    with pytest.raises(ConfigError, match=r"^mode"):
        _tiny(tmp_path, mode="greedy")
    with pytest.raises(ConfigError, match=r"^zoo"):
        _tiny(tmp_path, mode="best_response")
    with pytest.raises(ConfigError, match=r"^task"):
        _tiny(tmp_path, task="nope")


def test_seeded_short_self_play_run_learns_beyond_a_no_learning_control(tmp_path):
    """14 updates (2 epochs each) of seed 0, and the same run with learning rate 0 (the policy never moves;
    the same episodes' drift: early episodes are the short collisions, so even a fixed policy's mean return
    rises).

    Measured, late-minus-early mean return (last 3 vs first 3 updates), seeds 0-4: learning +2.77, +2.76,
    +3.26, +2.57, +2.82; the control -0.40, +0.67, +0.52, +0.56, +0.34 (sd 0.43); learning minus control
    +3.16, +2.09, +2.74, +2.00, +2.48. Two runs without learning differ by about 0.6 (sd); the bar of 1.5 is
    2.5 of those, and seed 0 (deterministic) clears it by 1.7.
    """
    deltas = {}
    for name in ("learn", "control"):
        ppo = {"epochs": 2, "num_envs": 32, "rollout_steps": 64, "minibatch_size": 1024, "lr": 1e-3}
        trainer = Trainer(_tiny(tmp_path / name, seed=0, ppo=ppo))
        start = {k: v.clone() for k, v in trainer.model.state_dict().items()}
        if name == "control":
            trainer.learner.set_hparams(lr=0.0)
        returns = [trainer.update_once().get("train/episode_return", np.nan) for _ in range(14)]
        deltas[name] = np.nanmean(returns[-3:]) - np.nanmean(returns[:3])
        moved = any(not torch.equal(start[k], v) for k, v in trainer.model.state_dict().items())
        assert moved == (name == "learn")  # the control is a real no-learning run
    assert deltas["learn"] - deltas["control"] > 1.5, deltas


def test_stop_at_suc_stops_at_the_first_evaluation_that_reaches_it(tmp_path):
    cfg = _tiny(tmp_path, stop_at_suc=50.0, eval_every=1, eval_episodes=1, total_env_steps=100 * 8 * 32)
    trainer = Trainer(cfg)
    levels = iter([10.0, 30.0, 60.0, 90.0])
    trainer.evaluate = lambda episodes, seed=12345: {"SUC": next(levels), "COL": 0.0, "AST": 1.0, "REW": 0.0}
    last = trainer.train(progress=False)
    assert last["eval/SUC"] == 60.0 and trainer.updates == 3
    assert read_header(tmp_path / "tiny" / "last.pt")["step"] == 3 * 8 * 32  # the checkpoint is the stopping one
    with pytest.raises(ConfigError, match=r"^stop_at_suc"):
        _tiny(tmp_path, stop_at_suc=120.0)


def test_proximity_feature_by_hand():
    from atdrone.models.networks import EntityTrunk

    trunk = EntityTrunk(NetConfig(entity_dim=4, hidden=4, proximity=0.15))
    block = torch.tensor([[1.0, 0.1 / 5.0, 0.0, 1.0], [0.0, 0.0, 0.0, 0.0]])  # visible at 0.1 m; masked
    feats = trunk._features(block)
    assert feats.shape == (2, 4)
    assert feats[0, 3].item() == pytest.approx(math.exp(-0.1 / 0.15))
    assert feats[1, 3].item() == 0.0  # a masked entity is never "near"
    assert EntityTrunk(NetConfig(entity_dim=4, hidden=4, proximity=0.0))._features(block).shape == (2, 3)


def test_actor_and_critic_parameter_groups_partition_the_model():
    model = ActorCritic(NetConfig(entity_dim=8, hidden=8, centralised_critic=True))
    actor, critic = model.parameter_groups()
    assert {id(p) for p in actor}.isdisjoint(id(p) for p in critic)
    assert len(actor) + len(critic) == len(list(model.parameters()))
    assert any(p is model.log_std for p in actor) and any(p is model.value_head.weight for p in critic)


def test_collision_credit_by_hand():
    # Two envs, four pursuers, learners in slots (2, 0) and (1, 3).
    # Env 0: pursuer 2 (a learner) and pursuer 3 (a partner) collided.
    # Env 1: only pursuer 2 (a partner) hit the bar.
    collided = np.array([[False, False, True, True], [False, False, True, False]])
    info = {"collided": collided, "team": {"learner_slots": np.array([[2, 0], [1, 3]])}}
    shared = np.array([[-10 + 1.5, -10 + 1.5], [-10 + 0.5, -10 + 0.5]], dtype=np.float32)  # task reward, both columns
    own = credited_rewards(shared, info, collision=-10.0, credit="own", scale=1.0)
    np.testing.assert_allclose(own, [[-8.5, 1.5], [0.5, 0.5]])
    own3 = credited_rewards(shared, info, collision=-10.0, credit="own", scale=3.0)
    np.testing.assert_allclose(own3, [[-28.5, 1.5], [0.5, 0.5]])
    team2 = credited_rewards(shared, info, collision=-10.0, credit="team", scale=2.0)
    np.testing.assert_allclose(team2, [[-18.5, -18.5], [-19.5, -19.5]])
    with pytest.raises(ValueError, match="credit"):
        credited_rewards(shared, info, collision=-10.0, credit="blame", scale=1.0)


def test_ppo_config_checks_collision_credit():
    assert ppo_config({"collision_credit": "own"}).collision_credit == "own"
    with pytest.raises(ConfigError, match="collision_credit"):
        ppo_config({"collision_credit": "blame"})
    with pytest.raises(ConfigError, match="collision_scale"):
        ppo_config({"collision_scale": -1.0})


def test_widening_into_a_centralised_critic_keeps_actions_and_values():
    small = _trained_model()
    wide = ActorCritic(NetConfig(entity_dim=16, hidden=32, centralised_critic=True))
    wide.widen_from(small)
    core = BatchedPursuit("4p2e1o", num_envs=6, seed=3)
    obs = torch.from_numpy(core.reset())
    state = torch.from_numpy(global_state(core.state, core.geometry, 4))[:, None].expand(6, 4, -1)
    torch.testing.assert_close(wide.dist(obs, 2).mean, small.dist(obs, 2).mean)
    torch.testing.assert_close(wide.value(obs, 2, state, 4), small.value(obs, 2))
    # the global inputs start at zero weight and learn from there
    wide.value(obs, 2, state, 4).sum().backward()
    assert wide.global_encoder is not None
    assert any(p.grad is not None and p.grad.abs().sum() > 0 for p in wide.critic.body[0].parameters())
    with pytest.raises(ValueError, match="centralised critic"):
        small.widen_from(wide)
    with pytest.raises(ValueError, match="does not match"):
        ActorCritic(NetConfig(entity_dim=8, hidden=32, centralised_critic=True)).widen_from(small)


def test_best_response_with_a_centralised_critic_starts_from_a_self_play_checkpoint(tmp_path):
    sp = Trainer(_tiny(tmp_path, name="sp", total_env_steps=2048))
    sp.update_once()
    path = sp.save()
    br = Trainer(
        _tiny(tmp_path, name="br", mode="best_response", zoo="zoo1", init_checkpoint=str(path), centralised_critic=True)
    )
    assert br.model.global_encoder is not None
    obs = torch.from_numpy(br.worker.obs)
    torch.testing.assert_close(br.model.dist(obs, 2).mean, sp.model.dist(obs, 2).mean)
    stats = br.update_once()
    assert np.isfinite(stats["train/value_loss"])


def test_start_std_overrides_the_initial_checkpoints_noise(tmp_path):
    sp = Trainer(_tiny(tmp_path, name="sp"))
    path = sp.save()
    kept = Trainer(_tiny(tmp_path, name="kept", init_checkpoint=str(path)))
    assert kept.model.log_std.item() == pytest.approx(sp.model.log_std.item())
    quiet = Trainer(_tiny(tmp_path, name="quiet", init_checkpoint=str(path), start_std=0.2))
    assert quiet.model.log_std.item() == pytest.approx(math.log(0.2))
    torch.testing.assert_close(quiet.model.mu.weight, sp.model.mu.weight)  # only the noise changed
    with pytest.raises(ConfigError, match="start_std"):
        _tiny(tmp_path, start_std=-0.1)


def test_a_run_with_history_starts_from_a_checkpoint_without_it(tmp_path):
    sp = Trainer(_tiny(tmp_path, name="sp"))
    path = sp.save()
    ppo = {**_tiny(tmp_path).ppo, "history": 2}
    br = Trainer(_tiny(tmp_path, name="br", mode="best_response", zoo="zoo1", init_checkpoint=str(path), ppo=ppo))
    assert br.model.cfg.history == 2
    obs = br.worker.obs
    inputs = torch.from_numpy(br.worker.inputs(obs))
    torch.testing.assert_close(br.model.dist(inputs, 2).mean, sp.model.dist(torch.from_numpy(obs), 2).mean)
    assert np.isfinite(br.update_once()["train/value_loss"])
    with pytest.raises(ConfigError, match="init_checkpoint"):
        Trainer(_tiny(tmp_path, name="none", init_checkpoint=str(tmp_path / "missing.pt")))


class _Tiny(torch.nn.Module):
    """A stand-in policy with one mean, one log-std and one value, the same for every input."""

    def __init__(self) -> None:
        super().__init__()
        self.mu = torch.nn.Parameter(torch.zeros(()))
        self.log_std = torch.nn.Parameter(torch.zeros(()))
        self.v = torch.nn.Parameter(torch.zeros(()))

    def dist(self, inputs: torch.Tensor, num_e: int) -> torch.distributions.Normal:
        shape = inputs.shape[:-1]
        return torch.distributions.Normal(self.mu.expand(shape), self.log_std.exp().expand(shape))

    def value(self, inputs, num_e, state=None, num_p=0):
        return self.v.expand(inputs.shape[:-1])

    def parameter_groups(self):
        return [self.mu, self.log_std], [self.v]


def _worked_batch(ratios: list[float], adv: list[float], ret: list[float], model: _Tiny) -> dict[str, np.ndarray]:
    """obs and actions at u = 0, with the old log-probabilities that make the new/old ratios ``ratios``."""
    n = len(ratios)
    obs = np.zeros((n, 3))
    u = np.zeros(n)
    with torch.no_grad():
        logp = squash_log_prob(model.dist(torch.as_tensor(obs), 2), torch.as_tensor(u)).numpy()
    return {"obs": obs, "u": u, "logp": logp - np.log(ratios), "adv": np.array(adv), "ret": np.array(ret)}


def _worked_cfg(**kw: float) -> PPOConfig:
    base: dict[str, Any] = {"epochs": 1, "minibatch_size": 2, "clip": 0.2, "vf_coef": 0.5, "ent_coef": 0.0}
    base["max_grad_norm"] = 10.0
    return replace(PPOConfig(), normalize_advantages=False, **{**base, **kw})


def test_ppo_update_clips_the_surrogate_as_the_paper_defines_it():
    """Ratios 1.5 (A = +1) and 0.5 (A = -1) with clip 0.2: both terms take the clipped branch, so
    L = -mean(1.2 * 1, 0.8 * -1) = -0.2 and the policy gets no gradient (SGD leaves mu and std)."""
    model = _Tiny()
    optimizer = torch.optim.SGD(model.parameters(), lr=1.0)
    batch = _worked_batch([1.5, 0.5], adv=[1.0, -1.0], ret=[0.0, 0.0], model=model)
    stats = ppo_update(model, optimizer, batch, _worked_cfg(), 2, 4, torch.Generator().manual_seed(0))
    assert stats["policy_loss"] == pytest.approx(-0.2)
    assert stats["clipfrac"] == 1.0
    assert model.mu.item() == 0.0 and model.log_std.item() == 0.0
    # inside the trust region (ratio 1.1, A = +1) the surrogate is r * A: d(-r)/d(mu) = -r * d(log p)/d(mu) = 0 at
    # u = mu = 0, but d(-r)/d(log std) = -r * (u^2 / std^2 - 1) = 1.1: one SGD step of lr 1 moves log std by -1.1
    model = _Tiny()
    optimizer = torch.optim.SGD(model.parameters(), lr=1.0)
    batch = _worked_batch([1.1, 1.1], adv=[1.0, 1.0], ret=[0.0, 0.0], model=model)
    stats = ppo_update(model, optimizer, batch, _worked_cfg(), 2, 4, torch.Generator().manual_seed(0))
    assert stats["policy_loss"] == pytest.approx(-1.1) and stats["clipfrac"] == 0.0
    assert model.log_std.item() == pytest.approx(-1.1)


def test_ppo_update_value_loss_and_gradient_clipping_by_hand():
    """Value 0 against returns 1 and 3: value loss 0.5 * mean(1, 9) = 2.5; its gradient vf_coef * mean(v - ret)
    = 0.5 * -2 = -1 has norm 1, clipped to max_grad_norm 0.4, so SGD (lr 1) moves v to +0.4."""
    model = _Tiny()
    optimizer = torch.optim.SGD(model.parameters(), lr=1.0)
    batch = _worked_batch([1.0, 1.0], adv=[0.0, 0.0], ret=[1.0, 3.0], model=model)
    stats = ppo_update(model, optimizer, batch, _worked_cfg(max_grad_norm=0.4), 2, 4, torch.Generator().manual_seed(0))
    assert stats["value_loss"] == pytest.approx(2.5)
    assert model.v.item() == pytest.approx(0.4)
    # unclipped (max_grad_norm 10) the same step moves v by the whole gradient, to +1
    model = _Tiny()
    optimizer = torch.optim.SGD(model.parameters(), lr=1.0)
    ppo_update(model, optimizer, batch, _worked_cfg(), 2, 4, torch.Generator().manual_seed(0))
    assert model.v.item() == pytest.approx(1.0)


def _one_step(ratios: list[float], adv: list[float], ret: list[float], **cfg: float) -> tuple[_Tiny, dict]:
    """One SGD step (lr 1) of ppo_update on a fresh _Tiny: the parameters then hold minus the clipped gradient."""
    model = _Tiny()
    optimizer = torch.optim.SGD(model.parameters(), lr=1.0)
    batch = _worked_batch(ratios, adv=adv, ret=ret, model=model)
    stats = ppo_update(cast(Any, model), optimizer, batch, _worked_cfg(**cfg), 2, 4, torch.Generator().manual_seed(0))
    return model, stats


def test_ppo_update_keeps_the_gradient_of_a_ratio_outside_the_range_on_the_pessimistic_side():
    """min(r A, clip(r) A) clips only where clipping lowers the objective: ratio 0.5 with A = +1 and ratio 1.5
    with A = -1 are outside [0.8, 1.2] yet take the unclipped branch, L = -mean(0.5, -1.5) = 0.5, and at
    u = mu = 0, d(log p)/d(log std) = -1, so dL/d(log std) = mean(A r) = (0.5 - 1.5) / 2 = -0.5: log std -> +0.5.
    (Clipping these, as clip(r) A alone or a max would, leaves log std at 0.)"""
    model, stats = _one_step([0.5, 1.5], adv=[1.0, -1.0], ret=[0.0, 0.0])
    assert stats["policy_loss"] == pytest.approx(0.5) and stats["clipfrac"] == 1.0
    assert model.log_std.item() == pytest.approx(0.5) and model.mu.item() == 0.0
    # one clipped sample (1.5, A = +1: the clipped 1.2 is the min) beside an unclipped one (1.1, A = +1): only the
    # unclipped one has a gradient, averaged over both: L = -mean(1.2, 1.1) = -1.15, dL/d(log std) = 1.1 / 2
    model, stats = _one_step([1.5, 1.1], adv=[1.0, 1.0], ret=[0.0, 0.0])
    assert stats["policy_loss"] == pytest.approx(-1.15) and stats["clipfrac"] == 0.5
    assert model.log_std.item() == pytest.approx(-0.55)


def test_ppo_update_clips_the_actor_and_critic_gradients_each_to_max_grad_norm():
    """Actor gradient 1.1 (on log std: ratio 1.1, A = +1) and critic gradient -1 (value 0, returns 1 and 3,
    vf_coef 0.5), each clipped to 0.4 on its own: both parameters move by exactly 0.4. (One global clip would
    scale both by 0.4 / hypot(1.1, 1), moving them by 0.30 and 0.27.)"""
    model, stats = _one_step([1.1, 1.1], adv=[1.0, 1.0], ret=[1.0, 3.0], max_grad_norm=0.4)
    assert stats["value_loss"] == pytest.approx(2.5)
    assert model.log_std.item() == pytest.approx(-0.4) and model.v.item() == pytest.approx(0.4)
    # under the bound nothing is scaled: the same step with max_grad_norm 10 moves them by the whole gradients
    model, _ = _one_step([1.1, 1.1], adv=[1.0, 1.0], ret=[1.0, 3.0])
    assert model.log_std.item() == pytest.approx(-1.1) and model.v.item() == pytest.approx(1.0)


def test_ppo_update_steps_the_real_network_with_each_group_gradient_norm_at_most_max_grad_norm(tmp_path):
    """On a real ActorCritic and a collected fragment: at every optimiser step the actor's and the critic's
    gradient norms are each <= max_grad_norm (here equal to it: both were larger and got scaled down)."""
    trainer = Trainer(_tiny(tmp_path))
    batch = trainer.worker.collect(8).batch(0.99, 0.95)
    model = trainer.model
    cfg = replace(trainer.ppo, max_grad_norm=1e-3, minibatch_size=64, epochs=2)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-4)
    step, norms = optimizer.step, []

    def recording_step(*args, **kwargs):
        norms.append([float(torch.linalg.vector_norm(torch.stack([p.grad.norm() for p in g]))) for g in groups])
        return step(*args, **kwargs)

    groups = model.parameter_groups()
    optimizer.step = recording_step  # type: ignore[method-assign]
    ppo_update(model, optimizer, batch, cfg, 2, 4, torch.Generator().manual_seed(0))
    n = len(batch["obs"])
    assert len(norms) == cfg.epochs * (n // 64) > 2
    assert np.array(norms) == pytest.approx(np.full((len(norms), 2), 1e-3), rel=1e-3)
