"""Team events in the batched simulator: swaps, drops and joins as data, applied in the step."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from atdrone.config import load_task
from atdrone.envs.core import BatchedPursuit
from atdrone.envs.events import DROP, JOIN, SWAP, EventPlan, EventSpec, parked
from atdrone.models.networks import ActorCritic, NetConfig
from atdrone.policies.neural import NeuralPolicy
from atdrone.policies.rules import GreedyPolicy, VicsekPolicy
from atdrone.teams.match import Match

TASK = "4p2e1o"


def _play(core: BatchedPursuit, partners: list, steps: int, seed: int = 5) -> tuple[list, list, Match]:
    """Greedy learners with ``partners`` for ``steps`` steps: the states and infos of every step."""
    match = Match(core, partners, seed=seed)
    learner = GreedyPolicy()
    match.reset()
    states, infos = [core.state.copy()], []
    for _ in range(steps):
        acts = learner.act(match.learner_batch()).reshape(core.num_envs, -1)
        infos.append(match.step(acts)[3])
        states.append(core.state.copy())
    return states, infos, match


def test_a_swap_leaves_the_episode_bit_identical_up_to_its_step_and_the_new_drone_takes_the_pose() -> None:
    t = 12
    plan = EventPlan((EventSpec("swap", (t, t)),))
    partners = [GreedyPolicy(), VicsekPolicy()]
    plain, _, _ = _play(BatchedPursuit(TASK, 6, seed=3), partners, 30)
    swapped, infos, _ = _play(BatchedPursuit(TASK, 6, seed=3, events=plan), partners, 30)
    for a, b in zip(plain[: t + 1], swapped[: t + 1], strict=True):
        assert np.array_equal(a.pos, b.pos) and np.array_equal(a.heading, b.heading)
    changed = infos[t - 1]["team_changed"]  # the step that brings the episodes to step t
    running = plain[t].t == t  # episodes that lived to step t
    assert (changed.sum(1) == running).all() and running.any()
    env, slot = np.nonzero(changed)
    assert not (infos[t - 1]["team"]["learner_slots"][env] == slot[:, None]).any()  # partners only by default
    assert np.array_equal(swapped[t].pos[env, slot], plain[t].pos[env, slot])  # the backup's pose is the old one's
    j = np.argmax(infos[t - 1]["team"]["partner_slots"][env] == slot[:, None], axis=1)
    assert (infos[t - 2]["team"]["partner_members"][env, j] != infos[t - 1]["team"]["partner_members"][env, j]).all()
    assert not all(np.array_equal(a.pos, b.pos) for a, b in zip(plain[t + 1 :], swapped[t + 1 :], strict=True))
    assert not any(info["team_changed"].any() for k, info in enumerate(infos) if k != t - 1)


def test_a_dropped_drone_neither_captures_nor_collides_and_no_observation_shows_it() -> None:
    core = BatchedPursuit(TASK, 2, seed=0, events=EventPlan((EventSpec("drop", (1, 1), "any"),)))
    core.reset()
    core.state.ev_slot[:] = 0
    _, _, _, info = core.step(np.zeros((2, 4)))
    assert info["team_changed"][:, 0].all() and not core.state.present[:, 0].any()
    assert np.array_equal(core.state.pos[:, 0], np.broadcast_to(parked(4)[0], (2, 2)))
    # put the landed drone on an evader, then on a teammate: neither counts
    core.state.pos[:, 0] = core.state.pos[:, 4]
    info = core.step(np.zeros((2, 4)))[3]
    assert not info["captured_now"].any() and not info["collided"].any()
    core.state.pos[:, 0] = core.state.pos[:, 1]
    info = core.step(np.zeros((2, 4)))[3]
    assert not info["collided"].any() and not info["hit_pairs"].any()
    assert np.array_equal(core.state.pos[:, 0], np.broadcast_to(parked(4)[0], (2, 2)))  # back at its spot
    _landed_drone_is_unseen(core)


def _landed_drone_is_unseen(core: BatchedPursuit) -> None:
    """With slot 0 landed and the others well apart within range of each other: slot 0 sees nothing and no
    other drone's teammate block shows it."""
    s = core.state
    s.pos[:, 1:4] = [[1.0, 1.0], [1.5, 1.0], [2.0, 1.0]]
    obs = core.observe()
    assert not obs[:, 0].any()  # a landed drone sees nothing
    E = core.num_e
    teammate = obs[:, 1:, 4 * (E + 1) :].reshape(len(obs), 3, 3, 4)  # each other drone's 3 teammate blocks
    assert not teammate[:, :, 0].any() and teammate[:, :, 1:].any()  # slot 0 is each one's first teammate block


def test_a_landed_drone_is_hidden_even_where_the_reception_range_reaches_its_parking_spot() -> None:
    cfg = load_task(TASK)
    wide = dataclasses.replace(cfg, players=dataclasses.replace(cfg.players, reception_range=1000.0))
    core = BatchedPursuit(wide, 2, seed=0, events=EventPlan((EventSpec("drop", (1, 1), "any"),)))
    core.reset()
    core.state.ev_slot[:] = 0
    core.step(np.zeros((2, 4)))
    assert not core.state.present[:, 0].any()
    _landed_drone_is_unseen(core)


def test_a_join_refills_the_dropped_slot_in_the_spawn_region() -> None:
    plan = EventPlan((EventSpec("drop", (3, 3), "any"), EventSpec("join", (4, 4))))
    core = BatchedPursuit(TASK, 16, seed=1, events=plan)
    core.reset()
    slot = core.state.ev_slot[:, 0].copy()
    assert np.array_equal(core.state.ev_slot[:, 1], slot) and (core.state.ev_step[:, 1] == 7).all()
    for _ in range(7):
        _, _, done, info = core.step(np.zeros((16, 4)))
    live = ~done
    assert core.state.present[live].all() and info["team_changed"][np.arange(16), slot][live].all()
    region = core.cfg.players.respawn_region.pursuer
    x = core.state.pos[np.arange(16), slot, 0] - region.x_step * slot
    y = core.state.pos[np.arange(16), slot, 1]
    assert ((x >= region.x[0]) & (x <= region.x[1]) & (y >= region.y[0]) & (y <= region.y[1]))[live].all()


def test_event_schedules_come_from_each_episode_key_whatever_the_batch() -> None:
    plan = EventPlan((EventSpec("drop", (10, 200)), EventSpec("join", (5, 50)), EventSpec("swap", (0, 300), "any")))
    one = BatchedPursuit(TASK, 8, seed=9, events=plan)
    one.reset()
    other = BatchedPursuit(TASK, 3, seed=9, events=plan)
    other.reset(episodes=np.array([6, 2, 7]))
    for name in ("ev_kind", "ev_step", "ev_pick", "ev_slot"):
        assert np.array_equal(getattr(one.state, name)[[6, 2, 7]], getattr(other.state, name))
    assert list(one.state.ev_kind[0]) == [DROP, JOIN, SWAP]
    again = BatchedPursuit(TASK, 8, seed=9, events=plan)
    again.reset()
    assert np.array_equal(again.state.ev_step, one.state.ev_step)
    assert len(np.unique(one.state.ev_step[:, 0])) > 1  # drawn, not fixed


def test_memory_is_reset_exactly_for_the_changed_slot() -> None:
    torch = pytest.importorskip("torch")
    torch.manual_seed(0)
    nets = [NeuralPolicy(ActorCritic(NetConfig(entity_dim=8, hidden=8, history=2)), f"h{i}") for i in range(2)]
    core = BatchedPursuit(TASK, 5, seed=2, events=EventPlan((EventSpec("swap", (4, 4)),)))
    match = Match(core, nets, seed=5)
    match.reset()
    learner = GreedyPolicy()
    fresh = []
    for _ in range(4):
        info = match.step(learner.act(match.learner_batch()).reshape(5, -1))[3]
        fresh.append([_fresh(p, 5, 4) for p in nets])
    changed = info["team_changed"]
    assert changed.sum() == 5
    for before, after in zip(fresh[-2], fresh[-1], strict=True):
        assert np.array_equal(after & ~before, changed & ~before)  # forgotten: the changed slots, nothing else
        assert after[changed].all()


def _fresh(policy: NeuralPolicy, rows: int, slots: int) -> np.ndarray:
    """(rows, slots) whether the policy's memory holds nothing of each drone (beyond its memory: nothing)."""
    out = np.ones((rows, slots), dtype=bool)
    held = policy.memory.fresh  # type: ignore[union-attr]
    out[: held.shape[0], : held.shape[1]] = held[:rows, :slots]
    return out


def test_without_events_the_step_reports_no_team_change() -> None:
    core = BatchedPursuit(TASK, 2, seed=0)
    core.reset()
    info = core.step(np.zeros((2, 4)))[3]
    assert "team_changed" not in info and core.state.ev_kind.shape == (2, 0)


def test_training_draws_the_protocol_events_and_forgets_a_replaced_learner_drone() -> None:
    from atdrone.config import ConfigError
    from atdrone.envs.events import EventPlan as Plan
    from atdrone.learn.ppo import ppo_config
    from atdrone.learn.rollout import RolloutWorker
    from atdrone.learn.trainer import load_train_config

    arch = ActorCritic.header(NetConfig(entity_dim=8, hidden=8, history=2))
    plan = Plan((EventSpec("swap", (3, 3)),))  # partners: in self-play, any learner drone
    worker = RolloutWorker(TASK, 0, arch, ppo_config({"num_envs": 4}), events=plan)
    worker.collect(2)
    seen = worker.memory.fresh.copy()  # type: ignore[attr-defined]
    assert not seen.any()
    worker.collect(1)  # the step that brings every episode to step 3: one learner drone each is replaced
    fresh = worker.memory.fresh  # type: ignore[attr-defined]
    assert (fresh.sum(1) == 1).all()
    cfg = load_train_config({"name": "ev", "task": TASK, "protocol": "zoo3+swap"})
    assert cfg.protocol == "zoo3+swap"
    with pytest.raises(ConfigError) as err:
        load_train_config({"name": "ev", "task": TASK, "protocol": "zoo3+nothing"})
    assert err.value.path == "protocol"
