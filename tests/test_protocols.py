"""Protocols of team events, their metrics, every split of the team and other team sizes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from atdrone.cli import main
from atdrone.config import ConfigError
from atdrone.policies.base import DroneBatch
from atdrone.policies.neural import load_policy
from atdrone.policies.rules import GreedyPolicy
from atdrone.teams.evaluation import evaluate, run_episodes
from atdrone.teams.match import Match
from atdrone.teams.protocols import event_metrics, load_protocol, parse_protocol, protocol_names
from atdrone.teams.splits import evaluate_splits, seat_assignments

SIX = "configs/tasks/6p2e1o.json"
SP_HIGH = "configs/zoos/checkpoints/4p2e1o/sp_high.pt"


def test_the_shipped_protocols_play_zoo3_with_their_events() -> None:
    assert {"zoo3+swap", "zoo3+drop", "zoo3+drop+join"} <= set(protocol_names())
    kinds = {name: [e.kind for e in load_protocol(name).plan.events] for name in protocol_names()}
    assert kinds["zoo3+swap"] == ["swap"] and kinds["zoo3+drop+join"] == ["drop", "join"]
    assert {load_protocol(name).zoo for name in protocol_names()} == {"zoo3"}


@pytest.mark.parametrize(
    ("events", "field"),
    [
        ([{"kind": "land", "steps": [1, 2]}], "events[0].kind"),
        ([{"kind": "swap", "steps": [5, 2]}], "events[0].steps"),
        ([{"kind": "swap", "steps": [1, 2]}, {"kind": "join", "steps": [1, 2]}], "events[1].kind"),
        ([{"kind": "drop", "steps": [1, 2], "slots": "pilots"}], "events[0].slots"),
    ],
)
def test_a_bad_protocol_is_refused_naming_the_field(events: list, field: str) -> None:
    with pytest.raises(ConfigError) as err:
        parse_protocol({"zoo": "zoo1", "events": events})
    assert err.value.path == field


def test_event_metrics_split_each_episode_at_its_first_event() -> None:
    records = pd.DataFrame(
        {  # ended before its event (success), then 3 that lived to it: success after 40 steps, collision, timeout
            "success": [True, True, False, False],
            "collided": [False, False, True, False],
            "event_step": [-1, 30, 50, 60],
            "recovery": [-1, 40, -1, 20],
        }
    )
    m = event_metrics(records)
    assert m["EVT"] == 75.0 and m["SUC_pre"] == 25.0 and m["COL_pre"] == 0.0
    assert m["SUC_post"] == pytest.approx(100 / 3) and m["COL_post"] == pytest.approx(100 / 3)
    assert m["REC"] == 30.0 and m["REC_none"] == pytest.approx(100 / 3)


def test_a_protocol_run_records_each_episode_schedule_first_event_and_recovery() -> None:
    plan = load_protocol("zoo3+drop+join").plan
    a = run_episodes(GreedyPolicy(), "4p2e1o", [GreedyPolicy()], 12, seed=4, events=plan)
    b = run_episodes(GreedyPolicy(), "4p2e1o", [GreedyPolicy()], 12, seed=4, events=plan)
    pd.testing.assert_frame_equal(a, b)  # reproducible from the seed
    first = a["events"].str.extract(r"^drop@(\d+):s(\d)").astype(int)
    lived = a["length"] > first[0]
    assert (a["event_step"][lived] == first[0][lived]).all() and (a["event_step"][~lived] == -1).all()
    assert ((a["recovery"] > 0) <= lived).all() and (a["recovery"][a["success"] & lived] > 0).all()
    partner_slot = [int(s) not in map(int, ls.split(",")) for s, ls in zip(first[1], a["learner_slots"], strict=True)]
    assert all(partner_slot)  # partners only by default


def test_the_k_split_visits_every_k_and_seat_with_the_learner_in_those_seats() -> None:
    assert len(seat_assignments(4)) == 4 + 6 + 4
    split = evaluate_splits(GreedyPolicy(), "4p2e1o", "zoo1", episodes=2)
    assert list(split.cells) == seat_assignments(4)
    for seats, ev in split.cells.items():
        assert set(ev.records["learner_slots"]) == {",".join(map(str, seats))}
    table = split.per_k()
    assert list(table.index) == [1, 2, 3] and list(table["seat_sets"]) == [4, 6, 4]


def test_a_six_pursuer_team_flies_a_four_pursuer_trained_drone() -> None:
    policy = load_policy(SP_HIGH)
    assert policy.num_p == 4
    with pytest.raises(ConfigError):
        evaluate(policy, SIX, "zoo1", episodes=2)  # another team size is asked for
    result = evaluate(policy, SIX, "zoo1", episodes=2, cross_task=True)
    assert result.task == "6p2e1o" and len(result.records) == 2
    from atdrone.envs.core import BatchedPursuit

    core = BatchedPursuit(SIX, 3, seed=0)
    match = Match(core, [GreedyPolicy()], seed=0)
    match.reset()
    batch = match.learner_batch()
    assert batch.obs.shape[-1] == 4 * (6 + 2)
    acts = load_policy(SP_HIGH).act(batch)  # the evaders' count from the poses: 2, not 8 - 4
    plain = load_policy(SP_HIGH).act_obs(batch.obs, batch.env, batch.slot, num_e=2)
    assert np.array_equal(acts, plain) and np.isfinite(acts).all()
    assert not np.array_equal(acts, load_policy(SP_HIGH).act(DroneBatch(batch.obs, batch.env, batch.slot)))


def test_evaluate_takes_a_protocol_where_a_zoo_goes(tmp_path: Path) -> None:
    doc = tmp_path / "zoo1+swap.json"
    doc.write_text(json.dumps({"name": "zoo1+swap", "zoo": "zoo1", "events": [{"kind": "swap", "steps": [5, 20]}]}))
    out = tmp_path / "out"
    args = ["evaluate", "--policy", "greedy", "--zoo", str(doc), "--episodes", "6", "--no-progress"]
    assert main([*args, "--out-dir", str(out)]) == 0
    (report,) = out.glob("*.json")
    text = report.read_text()
    assert "zoo1+swap" in report.name and '"SUC_post"' in text and '"REC_ci95"' in text


def test_evaluate_splits_plays_every_seat_set_and_prints_one_row_per_k(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`atdrone evaluate --splits`: the 14 seat sets of 4 pursuers, each --episodes; one row per k printed and in
    the CSV, whose SUC equals the episodes' own (pooled over that k's seat sets)."""
    args = ["evaluate", "--policy", "greedy", "--task", "4p2e1o", "--zoo", "zoo1", "--episodes", "2"]
    assert main([*args, "--splits", "--no-progress", "--out-dir", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    table = pd.read_csv(tmp_path / "greedy_4p2e1o_zoo1_splits.csv")
    episodes = pd.read_csv(tmp_path / "greedy_4p2e1o_zoo1_splits_episodes.csv")
    assert list(table.k) == [1, 2, 3] and list(table.seat_sets) == [4, 6, 4] and list(table.episodes) == [8, 12, 8]
    assert episodes.groupby("k")["seats"].nunique().tolist() == [4, 6, 4]
    for k, group in episodes.groupby("k"):
        assert table.set_index("k").loc[k, "SUC"] == pytest.approx(100.0 * group["success"].mean())
    assert "seat_sets" in out and "splits.csv" in out
