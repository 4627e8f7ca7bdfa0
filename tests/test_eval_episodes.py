"""Evaluation episode by episode: the batched, refilled and shrinking evaluation gives every
episode the record it gets when played alone (a plain one-row loop), on the four tasks,
with rule-based and sampling neural partners, whatever the batch size."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pandas as pd
import pytest
import torch

from atdrone.benchmark.cells import RandomPolicy
from atdrone.config import TASK_NAMES, TaskConfig, load_task
from atdrone.envs import BatchedPursuit
from atdrone.envs.core import DONE_REASONS
from atdrone.envs.streams import RowStream, episode_keys, fold, normal, root_key
from atdrone.policies import GreedyPolicy, VicsekPolicy
from atdrone.policies.base import DroneBatch, Policy
from atdrone.policies.neural import load_policy
from atdrone.policies.zoo import checkpoint_path, load_zoo
from atdrone.teams.evaluation import episode_seeds, metrics, run_episodes
from atdrone.teams.lineups import evaluate_lineups
from atdrone.teams.match import Match

COLUMNS = ["outcome", "length", "return", "captured", "collided", "learner_slots", "partners"]
HORIZON = 200  # steps: episodes of every outcome (capture, collision, timeout), at a test's cost


def short(task: str) -> TaskConfig:
    doc = load_task(task).to_dict()
    doc["task"]["task_horizon"] = HORIZON
    return load_task(doc)


@pytest.fixture(autouse=True)
def one_torch_thread() -> Iterator[None]:
    """Small networks on one thread: two threads on a busy 2-core machine run 20x slower."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def sampling_partners() -> list[Policy]:
    """Rule-based drones and the zoo's two trained drones, sampling their actions."""
    spec = {m.name: m for m in load_zoo("zoo3", "4p2e1o").spec.members}
    neural = []
    for name in ("sp_high", "sp_low"):
        policy = load_policy(checkpoint_path(spec[name]), deterministic=False)
        policy.name = name
        neural.append(policy)
    return [GreedyPolicy(), VicsekPolicy(), *neural]


def alone(
    learner: Policy,
    task: TaskConfig,
    partners: list[Policy],
    seed: int,
    episode: int,
    lineups: np.ndarray | None = None,
) -> dict[str, object]:
    """Episode ``episode`` of evaluation seed ``seed``, played by itself on a one-row core."""
    cfg = load_task(task)
    core_seed, match_seed = episode_seeds(seed)
    core = BatchedPursuit(cfg, num_envs=1, seed=core_seed)
    match = Match(core, partners, seed=match_seed, lineups=lineups)
    match.reset(episodes=np.array([episode]))
    learner.reset(np.ones(1, dtype=bool))
    for _ in range(cfg.task.task_horizon):
        actions = learner.act(match.learner_batch()).reshape(1, match.num_ctrl)
        _, _, dones, info = match.step(actions)
        if dones[0]:
            break
    assert dones[0], "an episode ends by the horizon"
    team = info["team"]
    return {
        "outcome": DONE_REASONS[int(info["done_reason"][0])],
        "length": int(info["episode_length"][0]),
        "return": float(info["episode_return"][0]),
        "captured": int(info["episode_captured"][0]),
        "collided": bool(info["episode_collided"][0]),
        "learner_slots": ",".join(map(str, team["learner_slots"][0])),
        "partners": ",".join(team["partners"][0]),
    }


@pytest.mark.parametrize("task", TASK_NAMES)
def test_every_episode_of_a_batched_evaluation_is_the_episode_played_alone(task: str) -> None:
    partners, learner, cfg = sampling_partners(), GreedyPolicy(), short(task)
    records = run_episodes(learner, cfg, partners, episodes=5, seed=11, max_envs=3)  # refilled, then shrinking
    assert records["episode"].tolist() == list(range(5))
    reference = pd.DataFrame([alone(learner, cfg, partners, 11, e) for e in range(5)])
    pd.testing.assert_frame_equal(records[COLUMNS], reference[COLUMNS], check_dtype=False, check_exact=True)


def test_a_lineup_per_episode_plays_exactly_those_partners_in_the_episode_played_alone() -> None:
    partners, learner, cfg = sampling_partners(), GreedyPolicy(), short("4p2e3o")  # two partner slots
    plan = np.array([[0, 1], [2, 3], [3, 3], [1, 0], [2, 0], [0, 0]])
    records = run_episodes(learner, cfg, partners, episodes=6, seed=4, max_envs=4, lineups=plan)  # rows refilled
    names = [p.name for p in partners]
    assert records["partners"].tolist() == [f"{names[a]},{names[b]}" for a, b in plan]
    reference = pd.DataFrame([alone(learner, cfg, partners, 4, e, plan) for e in range(6)])
    pd.testing.assert_frame_equal(records[COLUMNS], reference[COLUMNS], check_dtype=False, check_exact=True)
    with pytest.raises(ValueError, match="lineups must be"):
        run_episodes(learner, cfg, partners, episodes=2, lineups=np.array([[0, 4]]))  # only 4 partners
    with pytest.raises(ValueError, match="lineups must be"):
        run_episodes(learner, cfg, partners, episodes=2, lineups=np.array([[0]]))  # one slot of two


def test_lineups_evaluated_in_one_batch_each_get_their_own_episodes() -> None:
    partners, learner, cfg = sampling_partners(), GreedyPolicy(), short("4p2e3o")
    results = evaluate_lineups(learner, cfg, partners, [[0, 1], [2, 3]], [3, 4], seed=9)
    records = run_episodes(learner, cfg, partners, 7, seed=9, lineups=np.array([[0, 1]] * 3 + [[2, 3]] * 4))
    for result, rows in zip(results, (records.iloc[:3], records.iloc[3:]), strict=True):
        assert {k: result[k] for k in ("SUC", "COL", "REW")} == {k: metrics(rows)[k] for k in ("SUC", "COL", "REW")}
        assert result["steps"] == rows["length"].sum()
        assert result["REW_var"] == pytest.approx(rows["return"].var(ddof=1))
    assert results == evaluate_lineups(learner, cfg, partners, [[0, 1], [2, 3]], [3, 4], seed=9)  # run twice
    with pytest.raises(ValueError, match="positive episode count"):
        evaluate_lineups(learner, cfg, partners, [[0, 1]], [0])


def test_the_batch_size_changes_no_episode_record() -> None:
    learner = load_policy(checkpoint_path(load_zoo("zoo2", "4p2e1o").spec.members[0]), deterministic=False)
    partners = sampling_partners()
    wide = run_episodes(learner, short("4p2e3o"), partners, episodes=20, seed=5)
    narrow = run_episodes(learner, short("4p2e3o"), partners, episodes=20, seed=5, max_envs=6)
    pd.testing.assert_frame_equal(wide, narrow, check_exact=True)
    assert wide["outcome"].nunique() > 1 and wide["length"].nunique() > 10  # episodes that differ


def test_the_floors_random_learner_plays_each_episode_as_alone_whatever_the_batch_size() -> None:
    """The benchmark's floor draws each turn from the drone's key (episode, step, slot), not from a stream the
    batch's order consumes: a replay of a floor cell gives its record back, however the evaluation batches it."""
    partners, cfg = sampling_partners(), short("4p2e3o")
    records = run_episodes(RandomPolicy(0), cfg, partners, episodes=5, seed=11, max_envs=3)
    reference = pd.DataFrame([alone(RandomPolicy(0), cfg, partners, 11, e) for e in range(5)])
    pd.testing.assert_frame_equal(records[COLUMNS], reference[COLUMNS], check_dtype=False, check_exact=True)
    wide = run_episodes(RandomPolicy(1), cfg, partners, episodes=5, seed=11)
    pd.testing.assert_frame_equal(records, wide, check_exact=True)
    n = 4000
    keyed = DroneBatch(
        obs=np.zeros((n, 1)), env=np.arange(n), slot=np.zeros(n, int), keys=fold(np.arange(n, dtype=np.uint64), 3)
    )
    turns = RandomPolicy(0).act(keyed)
    assert (
        turns.min() >= -1.0
        and turns.max() <= 1.0
        and abs(float(turns.mean())) < 0.03
        and abs(turns.var() - 1 / 3) < 0.02
    )


def test_a_longer_evaluation_starts_with_the_same_episodes() -> None:
    short = run_episodes(GreedyPolicy(), "4p2e1o", load_zoo("zoo1"), episodes=10, seed=3)
    longer = run_episodes(GreedyPolicy(), "4p2e1o", load_zoo("zoo1"), episodes=30, seed=3, max_envs=7)
    pd.testing.assert_frame_equal(short, longer.iloc[:10])
    other = run_episodes(GreedyPolicy(), "4p2e1o", load_zoo("zoo1"), episodes=10, seed=4)
    assert not other["length"].equals(short["length"])


def test_finished_rows_leave_the_batch() -> None:
    """The evaluation steps about the sum of the episodes' lengths, not episodes x the longest."""
    core_steps: list[int] = []
    original = BatchedPursuit.step

    def counting(self: BatchedPursuit, actions: np.ndarray):  # type: ignore[no-untyped-def]
        core_steps.append(self.num_envs)
        return original(self, actions)

    mp = pytest.MonkeyPatch()
    mp.setattr(BatchedPursuit, "step", counting)
    try:
        records = run_episodes(GreedyPolicy(), "4p2e1o", load_zoo("zoo1"), episodes=40, seed=2, max_envs=16)
    finally:
        mp.undo()
    total = int(records["length"].sum())
    assert total <= sum(core_steps) < total + 16 * 2  # only rows that start an episode past the last one waste a step
    assert max(core_steps) == 16 and core_steps[-1] < 16


# --------------------------------------------------------------- the streams
def test_row_streams_draw_each_row_from_its_own_key() -> None:
    keys = episode_keys(root_key(0), np.arange(6))
    both = RowStream(keys)
    first = both.uniform(-1.0, 1.0, size=(6, 3))
    counts = both.integers(10, 16, size=(6, 2))
    part = RowStream(keys[[4, 1]])
    np.testing.assert_array_equal(part.uniform(-1.0, 1.0, size=(2, 3)), first[[4, 1]])
    np.testing.assert_array_equal(part.integers(10, 16, size=(2, 2)), counts[[4, 1]])
    assert len(np.unique(first)) == first.size and (first >= -1).all() and (first < 1).all()
    assert set(np.unique(counts)) <= set(range(10, 16))
    # a child for some rows draws the same for a row whatever the other rows are
    np.testing.assert_array_equal(
        both.rows(np.array([0, 1, 0, 0, 1, 0], bool)).random((2, 4))[1],
        part.rows(np.array([1, 0], bool)).random((1, 4))[0],
    )


def test_counter_draws_are_uniform_and_normal() -> None:
    keys = fold(np.arange(200_000, dtype=np.uint64), 7)
    u = RowStream(keys).random((len(keys), 1))[:, 0]
    assert abs(u.mean() - 0.5) < 0.005 and abs(u.var() - 1 / 12) < 0.002
    z = normal(keys)
    assert abs(z.mean()) < 0.01 and abs(z.std() - 1) < 0.01 and abs((z**3).mean()) < 0.03
