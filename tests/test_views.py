"""The PettingZoo and Gymnasium views: their own API checkers, and step-for-step
agreement with the batched core they wrap (auto-reset path included)."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from pettingzoo.test import parallel_api_test, parallel_seed_test

from atdrone.config import TASK_NAMES, TaskConfig, load_task
from atdrone.envs import DONE_REASONS, BatchedPursuit, PursuitEnv, PursuitParallelEnv, PursuitVectorEnv
from atdrone.envs.core import CAPTURED, COLLISION, RUNNING, TIMEOUT


def short_horizon(task: str, horizon: int = 40) -> TaskConfig:
    doc = load_task(task).to_dict()
    doc["task"]["task_horizon"] = horizon
    return load_task(doc)


@pytest.mark.parametrize("task", TASK_NAMES)
def test_pettingzoo_parallel_api_test_passes(task: str) -> None:
    parallel_api_test(PursuitParallelEnv(task, seed=0), num_cycles=300)


@pytest.mark.parametrize("task", TASK_NAMES)
def test_pettingzoo_parallel_seed_test_passes(task: str) -> None:
    parallel_seed_test(lambda: PursuitParallelEnv(task), num_cycles=300)


def test_pettingzoo_spaces_are_cached_per_agent() -> None:
    env = PursuitParallelEnv("4p3e5o")
    for agent in env.possible_agents:
        assert env.observation_space(agent) is env.observation_space(agent)
        assert env.observation_space(agent).shape == (28,)
        assert env.action_space(agent) is env.action_space(agent)
    assert env.possible_agents == ["pursuer_0", "pursuer_1", "pursuer_2", "pursuer_3"]


@pytest.mark.parametrize("task", TASK_NAMES)
def test_gymnasium_check_env_passes(task: str) -> None:
    env = gymnasium.make("atdrone/Pursuit-v0", task=task)
    assert isinstance(env.unwrapped, PursuitEnv)
    check_env(env.unwrapped, skip_render_check=True)


@pytest.mark.parametrize("task", TASK_NAMES)
def test_gymnasium_make_vec_steps_the_batched_core(task: str) -> None:
    env = gymnasium.make_vec("atdrone/Pursuit-v0", num_envs=4, vectorization_mode="vector_entry_point", task=task)
    assert isinstance(env, PursuitVectorEnv)
    obs, _ = env.reset(seed=0)
    assert obs in env.observation_space
    env.action_space.seed(0)
    for _ in range(30):
        obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
        assert obs in env.observation_space
        assert reward.shape == (4,) and terminated.dtype == bool and truncated.dtype == bool
        assert set(info["done_reason_name"]) <= set(DONE_REASONS)
        ended = terminated | truncated
        assert np.array_equal(ended, info["done_reason"] != RUNNING)
    env.close()


def test_gymnasium_make_vec_is_reproducible_from_a_seed() -> None:
    def trace() -> list[np.ndarray]:
        env = gymnasium.make_vec("atdrone/Pursuit-v0", num_envs=3, vectorization_mode="vector_entry_point")
        out = [env.reset(seed=4)[0]]
        rng = np.random.default_rng(0)
        for _ in range(50):
            out.append(env.step(rng.uniform(-1, 1, size=(3, 4)).astype(np.float32))[0])
        return out

    for a, b in zip(trace(), trace(), strict=True):
        assert np.array_equal(a, b)


def _check_outcome(reason: int, terminated: bool, truncated: bool) -> None:
    assert terminated == (reason in (CAPTURED, COLLISION))
    assert truncated == (reason == TIMEOUT)


@pytest.mark.parametrize("task", TASK_NAMES)
@pytest.mark.parametrize("seed", [0, 1])
def test_pettingzoo_view_matches_batched_core_step_for_step(task: str, seed: int) -> None:
    cfg = short_horizon(task, horizon=12)
    view = PursuitParallelEnv(cfg, seed=seed)
    core = BatchedPursuit(cfg, num_envs=1, seed=seed)
    agents = view.possible_agents
    obs, _ = view.reset()
    core_obs = core.reset()
    assert np.array_equal(np.stack([obs[a] for a in agents]), core_obs[0])
    rng = np.random.default_rng(seed)
    ends, reasons = 0, set()
    for _ in range(200):
        action = rng.uniform(-1, 1, size=4) * 0.3  # gentle turns: some episodes reach the horizon
        obs, rewards, terms, truncs, infos = view.step({a: action[i : i + 1] for i, a in enumerate(agents)})
        core_obs, core_rewards, core_done, core_info = core.step(action[None])
        reason = int(core_info["done_reason"][0])
        expected_obs = core_info["final_obs"][0] if core_done[0] else core_obs[0]
        assert np.array_equal(np.stack([obs[a] for a in agents]), expected_obs)
        assert [rewards[a] for a in agents] == core_rewards[0].tolist()
        for a in agents:
            _check_outcome(reason, terms[a], truncs[a])
        if core_done[0]:
            ends += 1
            reasons.add(reason)
            assert view.agents == []
            assert infos[agents[0]]["done_reason"] == DONE_REASONS[reason]
            assert infos[agents[0]]["episode_return"] == pytest.approx(float(core_info["episode_return"][0]))
            obs, _ = view.reset()  # continues with the episode the core already started
            assert np.array_equal(np.stack([obs[a] for a in agents]), core_obs[0])
        else:
            assert view.agents == agents
    assert ends >= 3
    assert {COLLISION, TIMEOUT} <= reasons


@pytest.mark.parametrize("task", ["4p2e1o", "4p3e5o"])
def test_gymnasium_view_matches_batched_core_step_for_step(task: str) -> None:
    cfg = short_horizon(task)
    view = PursuitEnv(cfg)
    core = BatchedPursuit(cfg, num_envs=1)
    obs, _ = view.reset(seed=9)
    assert np.array_equal(obs, core.reset(seed=9)[0])
    rng = np.random.default_rng(1)
    ends = 0
    for _ in range(200):
        action = rng.uniform(-1, 1, size=4).astype(np.float32)
        obs, reward, terminated, truncated, _ = view.step(action)
        core_obs, core_rewards, core_done, core_info = core.step(action[None].astype(np.float64))
        expected_obs = core_info["final_obs"][0] if core_done[0] else core_obs[0]
        assert np.array_equal(obs, expected_obs)
        assert reward == core_rewards[0, 0]
        _check_outcome(int(core_info["done_reason"][0]), terminated, truncated)
        if core_done[0]:
            ends += 1
            obs, _ = view.reset()
            assert np.array_equal(obs, core_obs[0])
    assert ends >= 3


def test_views_refuse_to_step_a_finished_episode() -> None:
    env = PursuitEnv(short_horizon("4p2e1o", horizon=2))
    env.reset(seed=0)
    env.step(np.zeros(4, dtype=np.float32))
    _, _, terminated, truncated, _ = env.step(np.zeros(4, dtype=np.float32))
    assert truncated and not terminated
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(4, dtype=np.float32))
