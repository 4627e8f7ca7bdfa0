"""The split of the team drawn in training: a protocol's ``learners`` range.

Each episode draws how many of its learner slots the learner flies; partners fly the
others (their actions executed, not the learner's), and those drone-steps are left out
of the PPO batch. Without a split everything is as before, bit for bit.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_teams_eval import Constant

from atdrone.config import ConfigError
from atdrone.envs.core import BatchedPursuit
from atdrone.learn.ppo import PRESETS, architecture
from atdrone.learn.rollout import RolloutWorker
from atdrone.learn.trainer import load_train_config
from atdrone.policies.rules import GreedyPolicy
from atdrone.teams.evaluation import evaluate
from atdrone.teams.match import Match
from atdrone.teams.protocols import is_protocol, parse_protocol, zoo_of

TASK = "4p2e1o"  # 2 learner slots, 2 partner slots
LEARNER, PARTNER = -0.9, 0.5


def _step(split: tuple[int, int] | None, envs: int = 64, seed: int = 7) -> tuple[Match, dict]:
    """One step of a Match whose learners all turn LEARNER and whose one partner turns PARTNER."""
    match = Match(BatchedPursuit(TASK, envs, seed=seed), [Constant("c", PARTNER)], seed=seed, split=split)
    match.reset()
    info = match.step(np.full((envs, match.num_ctrl), LEARNER))[3]
    return match, info


def test_a_lent_learner_slot_executes_the_partners_action_and_the_split_is_drawn_per_episode() -> None:
    _, info = _step((1, 2))
    lent, slots = info["team"]["lent"], info["team"]["learner_slots"]
    executed = np.take_along_axis(info["actions"], slots, axis=1)
    assert np.array_equal(executed == PARTNER, lent) and np.array_equal(executed == LEARNER, ~lent)
    partners = np.take_along_axis(info["actions"], info["team"]["partner_slots"], axis=1)
    assert (partners == PARTNER).all()
    flown = (~lent).sum(1)
    assert set(flown) == {1, 2}  # both k drawn over 64 episodes
    assert (~lent[:, 0]).all()  # the learner keeps its first columns: k of them (the slots are shuffled)
    # (1, 1): exactly one learner slot each episode; (2, 2): none lent
    assert (_step((1, 1))[1]["team"]["lent"].sum(1) == 1).all()
    assert not _step((2, 2))[1]["team"]["lent"].any()


def test_the_split_is_drawn_after_the_team_so_the_team_is_the_same_and_runs_repeat() -> None:
    plain = _step(None)[1]["team"]
    split = _step((1, 2))[1]["team"]
    for key in ("learner_slots", "partner_slots", "partner_members"):
        assert np.array_equal(plain[key], split[key])
    assert "lent" not in plain
    assert np.array_equal(split["lent"], _step((1, 2))[1]["team"]["lent"])  # from the episodes' keys


def test_a_split_needs_partners_and_fits_the_learner_slots() -> None:
    core = BatchedPursuit(TASK, 2, seed=0)
    for split in [(0, 1), (2, 1), (1, 3)]:
        with pytest.raises(ValueError, match="split"):
            Match(core, [GreedyPolicy()], split=split)
    with pytest.raises(ValueError, match="split"):
        Match(core, [], num_ctrl=4, split=(1, 2))


def _worker(split: tuple[int, int] | None, partners: list) -> RolloutWorker:
    ppo = replace(PRESETS["default"], num_envs=8, rollout_steps=16)
    return RolloutWorker(TASK, 3, architecture(ppo), ppo, partners=partners, split=split)


def test_the_slots_partners_flew_are_left_out_of_the_batch() -> None:
    frag = _worker((1, 1), [GreedyPolicy()]).collect(16)
    assert frag.own is not None and frag.own.shape == frag.u.shape
    assert (frag.own.sum(-1) == 1).all()  # one of the two learner slots each step
    batch = frag.batch(0.99, 0.95)
    assert len(batch["obs"]) == frag.samples == frag.own.sum() == frag.u.size // 2
    assert np.array_equal(batch["u"], frag.u[frag.own])  # exactly the rows the learner flew, in order
    assert np.array_equal(batch["obs"], frag.obs[frag.own])
    full = _worker(None, [GreedyPolicy()]).collect(16)
    assert full.own is None and len(full.batch(0.99, 0.95)["obs"]) == full.samples == full.u.size


def test_self_play_with_a_split_gives_the_other_slots_to_a_copy_of_the_learner() -> None:
    worker = _worker((1, 3), [])
    assert worker.match.num_ctrl == 4 and [p.name for p in worker.match.partners] == ["self"]
    frag = worker.collect(8)
    assert frag.own is not None and set(frag.own[0].sum(-1)) <= {1, 2, 3}


def _doc(tmp_path: Path, **doc: object) -> str:
    path = tmp_path / "split.json"
    path.write_text(json.dumps({"name": "zoo3+split", "zoo": "zoo3", **doc}))
    return str(path)


def test_a_protocol_may_draw_the_split_and_is_then_for_training_only(tmp_path: Path) -> None:
    protocol = parse_protocol({"zoo": "zoo3", "learners": [1, 2]}, "s")
    assert protocol.split == (1, 2) and not len(protocol.plan)
    assert protocol.to_dict()["learners"] == [1, 2]
    swap = {"zoo": "zoo3", "events": [{"kind": "swap", "steps": [1, 2]}]}
    assert "learners" not in parse_protocol(swap, "s").to_dict()
    for bad in ([0, 1], [2, 1], [1], "1-2", [1, True]):
        with pytest.raises(ConfigError, match="learners"):
            parse_protocol({"zoo": "zoo3", "learners": bad}, "s")
    with pytest.raises(ConfigError, match="events"):
        parse_protocol({"zoo": "zoo3"}, "s")
    path = _doc(tmp_path, learners=[1, 2])
    assert is_protocol(path)
    with pytest.raises(ConfigError, match=r"learners.*only training"):
        zoo_of(path)
    with pytest.raises(ConfigError, match=r"learners.*only training"):
        evaluate(GreedyPolicy(), TASK, "zoo1", episodes=2, protocol=path)


def test_a_train_config_refuses_a_split_past_the_learner_slots_of_its_mode(tmp_path: Path) -> None:
    doc = {"name": "t", "task": TASK, "out_dir": str(tmp_path), "protocol": _doc(tmp_path, learners=[1, 3])}
    assert load_train_config(doc).protocol  # self-play: the learner fills all 4 slots
    with pytest.raises(ConfigError, match=r"protocol\.learners: .*at most 2"):
        load_train_config({**doc, "mode": "best_response", "zoo": "zoo1"})
