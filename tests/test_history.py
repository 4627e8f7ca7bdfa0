"""Networks that read past frames: the per-drone memory, its use in rollouts and zoo policies, widening."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from atdrone.config import ConfigError, load_task
from atdrone.envs import BatchedPursuit
from atdrone.learn.ppo import ppo_config
from atdrone.learn.rollout import RolloutWorker
from atdrone.models.history import ObsHistory, input_dim
from atdrone.models.networks import ActorCritic, NetConfig
from atdrone.policies.base import DroneBatch
from atdrone.policies.neural import NeuralPolicy
from atdrone.policies.zoo import load_zoo
from atdrone.teams.evaluation import run_episodes


def test_history_by_hand():
    mem = ObsHistory(history=2, num_envs=2, num_keys=2, obs_dim=2)
    env, key = np.array([0, 1]), np.array([1, 0])
    a = np.array([[1.0, 2.0], [3.0, 4.0]], np.float32)
    # first step: the past repeats the current frame, past actions are 0
    np.testing.assert_array_equal(mem.augment(a, env, key), [[1, 2, 1, 2, 1, 2, 0, 0], [3, 4, 3, 4, 3, 4, 0, 0]])
    mem.record(a, env, key, np.array([0.5, -0.5]))
    b = a + 10
    np.testing.assert_array_equal(
        mem.augment(b, env, key), [[11, 12, 1, 2, 1, 2, 0.5, 0], [13, 14, 3, 4, 3, 4, -0.5, 0]]
    )
    mem.record(b, env, key, np.array([0.25, 1.0]))
    c = a + 20
    np.testing.assert_array_equal(
        mem.augment(c, env, key), [[21, 22, 11, 12, 1, 2, 0.25, 0.5], [23, 24, 13, 14, 3, 4, 1.0, -0.5]]
    )
    mem.reset(np.array([False, True]))  # env 1's episode ended: its drone starts over, env 0's keeps its past
    np.testing.assert_array_equal(
        mem.augment(c, env, key), [[21, 22, 11, 12, 1, 2, 0.25, 0.5], [23, 24, 23, 24, 23, 24, 0, 0]]
    )
    assert input_dim(2, 2) == 8
    with pytest.raises(ValueError, match="history"):
        ObsHistory(0, 1, 1, 2)


def _short_task(horizon: int = 12):
    doc = load_task("4p2e1o").to_dict()
    doc["task"]["task_horizon"] = horizon
    return load_task(doc)


def test_rollout_inputs_hold_the_previous_frame_and_action():
    arch = ActorCritic(NetConfig(entity_dim=8, hidden=16, history=1)).architecture()
    worker = RolloutWorker(_short_task(), 0, arch, ppo_config(), num_envs=3)
    frag = worker.collect(30)
    D = worker.core.obs_dim
    assert frag.obs.shape == (30, 3, 4, input_dim(D, 1))
    assert frag.dones.sum() >= 3  # every env ends at least once (horizon 12)
    for t in range(29):
        now, nxt = frag.obs[t], frag.obs[t + 1]
        for b in range(3):
            if frag.dones[t, b]:  # a new episode: no past yet
                np.testing.assert_array_equal(nxt[b, :, D : 2 * D], nxt[b, :, :D])
                np.testing.assert_array_equal(nxt[b, :, 2 * D], 0.0)
            else:
                np.testing.assert_array_equal(nxt[b, :, D : 2 * D], now[b, :, :D])
                np.testing.assert_allclose(nxt[b, :, 2 * D], np.tanh(frag.u[t, b]), rtol=1e-5, atol=1e-6)


def _trained_model(history: int = 0) -> ActorCritic:
    torch.manual_seed(0)
    model = ActorCritic(NetConfig(entity_dim=16, hidden=32, history=history))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return model


def test_widening_into_past_frames_keeps_the_policy_in_evaluation():
    small = _trained_model()
    wide = ActorCritic(NetConfig(entity_dim=16, hidden=32, history=2))
    wide.widen_from(small)
    assert wide.actor.mate[0].weight.shape[1] == 4 + 2 * 5  # (d, sin, cos, near) now + (features, mask) per past frame
    greedy = load_zoo("zoo1").policies()
    plain = run_episodes(NeuralPolicy(small), "4p2e1o", greedy, episodes=12, seed=4)
    remembering = run_episodes(NeuralPolicy(wide), "4p2e1o", greedy, episodes=12, seed=4)
    cols = ["length", "return", "reason", "captured"]
    assert (plain[cols] == remembering[cols]).all().all()
    with pytest.raises(ValueError, match="past frames"):
        small.widen_from(wide)


def test_neural_policy_remembers_per_slot_and_forgets_at_episode_end():
    policy = NeuralPolicy(_trained_model(history=1))
    core = BatchedPursuit("4p2e1o", num_envs=2, seed=1)
    obs = core.reset(seed=1)
    batch = DroneBatch.all_slots(obs)
    first = policy.act(batch)
    assert policy.memory is not None
    np.testing.assert_array_equal(policy.memory.obs[:, :, 0], obs)
    np.testing.assert_allclose(policy.memory.actions[:, :, 0], first.reshape(2, 4), rtol=1e-6)
    obs2 = core.step(first.reshape(2, 4))[0]
    again = DroneBatch.all_slots(obs2)
    inputs = policy.inputs(again)
    np.testing.assert_array_equal(inputs[:, core.obs_dim : 2 * core.obs_dim], obs.reshape(8, -1))
    policy.reset(np.array([True, False]))
    inputs = policy.inputs(again)
    np.testing.assert_array_equal(inputs[:4, core.obs_dim : 2 * core.obs_dim], obs2[0])  # env 0 starts over
    np.testing.assert_array_equal(inputs[4:, core.obs_dim : 2 * core.obs_dim], obs[1])
    policy.reset(np.ones(5, dtype=bool))  # another batch of environments: a new memory
    assert policy.memory is None


def test_ppo_config_checks_history():
    assert ppo_config({"history": 2}).history == 2
    with pytest.raises(ConfigError, match=r"ppo\.history"):
        ppo_config({"history": -1})
