"""Matches, zoos, the adaptive-teaming Gymnasium view and the evaluation protocol:
teams shuffled and recorded, partners acting through the zoo, greedy-team success
pinned per task, metrics equal to a plain recount of the episode records, and the
``atdrone evaluate`` command's table and files."""

from __future__ import annotations

import json

import gymnasium
import numpy as np
import pandas as pd
import pytest
from conftest import missing_zoo
from gymnasium.utils.env_checker import check_env

from atdrone.cli import main
from atdrone.config import TASK_NAMES, ConfigError, TaskConfig, load_task
from atdrone.envs import BatchedPursuit
from atdrone.envs.core import CAPTURED
from atdrone.envs.kinematics import MAX_TURN, wrap_angle
from atdrone.policies import DroneBatch, GreedyPolicy, StatelessPolicy, VicsekPolicy
from atdrone.policies.zoo import ZOO_NAMES, ZooError, checkpoint_path, load_zoo
from atdrone.teams.adaptive import AdaptiveTeamingEnv
from atdrone.teams.evaluation import (
    METRICS,
    GridCell,
    crash_breakdown,
    crash_kinds,
    crash_shares,
    evaluate,
    evaluate_grid,
    metrics,
    run_episodes,
)
from atdrone.teams.match import Match
from atdrone.teams.replay import record_episode
from atdrone.teams.reports import format_table

TURN = MAX_TURN


class Constant(StatelessPolicy):
    """Turns every drone it steers by the same action."""

    def __init__(self, name: str, value: float) -> None:
        self.name, self.value = name, value

    def act(self, batch: DroneBatch) -> np.ndarray:
        return np.full(len(batch), self.value)


def short_horizon(task: str, horizon: int) -> TaskConfig:
    doc = load_task(task).to_dict()
    doc["task"]["task_horizon"] = horizon
    return load_task(doc)


wrap = wrap_angle


# ------------------------------------------------------------------- Match
def test_match_shuffles_learner_slots_and_partners_per_episode_and_records_them():
    core = BatchedPursuit(short_horizon("4p2e1o", 3), num_envs=64, seed=0)
    match = Match(core, [Constant("left", 1.0), Constant("right", -1.0)], seed=0)
    match.reset()
    team = match.team()
    assert team["learner_slots"].shape == (64, 2) and team["partner_slots"].shape == (64, 2)
    slots = np.sort(np.concatenate([team["learner_slots"], team["partner_slots"]], 1), 1)
    assert (slots == np.arange(4)).all()  # every slot filled exactly once
    assert len({tuple(r) for r in team["learner_slots"]}) >= 6  # shuffled: many slot pairs in use
    assert set(np.unique(team["partner_members"])) == {0, 1}
    assert (team["partners"] == np.array(["left", "right"], dtype=object)[team["partner_members"]]).all()
    ended, redrawn = np.zeros(64, dtype=bool), np.zeros(64, dtype=bool)
    for _ in range(3):
        before = match.team()
        _, _, dones, info = match.step(np.zeros((64, 2)))
        for key in before:  # info["team"]: the teams of the episodes just played
            assert (info["team"][key] == before[key]).all(), key
        after = match.team()
        for key in before:  # kept mid-episode
            assert (after[key][~dones] == before[key][~dones]).all(), key
        ended |= dones
        redrawn |= dones & (after["learner_slots"] != before["learner_slots"]).any(1)
    assert ended.all()  # the 3-step horizon (or a collision) ended every episode
    assert redrawn.sum() > 32  # new teams for the new episodes


def test_match_learner_actions_land_in_learner_slots_and_partners_act_themselves():
    core = BatchedPursuit("4p2e1o", num_envs=32, seed=1)
    match = Match(core, [Constant("left", 1.0), Constant("right", -1.0)], seed=1)
    match.reset()
    team, before = match.team(), core.state.heading.copy()
    learner_actions = np.tile([0.5, -0.25], (32, 1))
    match.step(learner_actions)
    # final_state: every environment after the step, before those that ended (collisions) reset
    after = core.final_state if core.final_state is not None else core.state
    rows = np.arange(32)[:, None]
    turned = wrap(after.heading[:, :4] - before[:, :4])
    np.testing.assert_allclose(turned[rows, team["learner_slots"]], learner_actions * TURN, atol=1e-12)
    partner_turn = np.where(team["partner_members"] == 0, 1.0, -1.0) * TURN
    np.testing.assert_allclose(turned[rows, team["partner_slots"]], partner_turn, atol=1e-12)


def test_match_partners_from_a_zoo_act_as_the_zoo_policy_on_their_slots():
    core = BatchedPursuit("4p2e5o", num_envs=16, seed=2)
    match = Match(core, load_zoo("zoo1"), seed=2)
    assert match.partner_names == ["greedy"]
    obs = match.reset()
    assert obs.shape == (16, 2, core.obs_dim)
    team, before = match.team(), core.state.heading.copy()
    env = np.repeat(np.arange(16), 2)
    slot = team["partner_slots"].reshape(-1)
    expected = GreedyPolicy().act(DroneBatch(core.observe()[env, slot], env, slot, core.poses())).reshape(16, 2)
    match.step(np.zeros((16, 2)))
    after = core.final_state if core.final_state is not None else core.state
    turned = wrap(after.heading[:, :4] - before[:, :4])
    rows = np.arange(16)[:, None]
    np.testing.assert_allclose(turned[rows, team["partner_slots"]], expected * TURN, atol=1e-12)
    np.testing.assert_allclose(turned[rows, team["learner_slots"]], 0.0, atol=1e-12)


# -------------------------------------------------------------------- zoos
def test_the_three_zoos_load_and_name_their_missing_members():
    zoos = {name: load_zoo(name, "4p2e1o") for name in ZOO_NAMES}
    assert zoos["zoo1"].names == ["greedy"] and not zoos["zoo1"].missing
    assert isinstance(zoos["zoo1"].policies()[0], GreedyPolicy)
    assert zoos["zoo2"].names == ["sp_high", "sp_low"]
    assert zoos["zoo3"].names == ["greedy", "vicsek", "sp_high", "sp_low"]
    for zoo in zoos.values():  # missing: exactly the checkpoint members without a file
        absent = [m.name for m in zoo.spec.members if m.kind == "checkpoint" and not checkpoint_path(m).is_file()]
        assert zoo.missing == absent
        if zoo.missing:
            with pytest.raises(ZooError, match=zoo.missing[0]):
                zoo.policies()


def test_a_zoo_with_a_missing_checkpoint_loads_and_refuses_to_play_naming_it(tmp_path):
    zoo = load_zoo(missing_zoo(tmp_path))
    assert zoo.name == "ghosts" and zoo.missing == ["ghost"]
    with pytest.raises(ZooError, match=r"'ghost' needs .*ghost\.pt"):
        zoo.policies()
    with pytest.raises(ZooError, match="ghost"):
        Match(BatchedPursuit("4p2e1o"), zoo)


@pytest.mark.parametrize(
    ("member", "path"),
    [
        ({"name": "a", "kind": "kamikaze"}, "members[0].kind"),
        ({"name": "a", "kind": "checkpoint"}, "members[0].checkpoint"),
        ({"name": "a", "kind": "greedy", "checkpoint": "x.pt"}, "members[0].checkpoint"),
        ({"name": "a", "kind": "greedy", "params": {"bogus": 1.0}}, "members[0].params"),
        ({"name": "a", "kind": "vicsek", "params": {"mate_range": "far"}}, "members[0].params.mate_range"),
        ({"name": "a", "kind": "greedy", "colour": "red"}, "members[0].colour"),
        ({"kind": "greedy"}, "members[0].name"),
    ],
)
def test_malformed_zoo_documents_are_refused_naming_the_field(member, path):
    with pytest.raises(ConfigError) as err:
        load_zoo({"name": "bad", "members": [member]})
    assert err.value.path == path


def test_zoo_documents_refuse_duplicate_names_and_empty_member_lists():
    with pytest.raises(ConfigError) as err:
        load_zoo({"name": "bad", "members": [{"name": "a", "kind": "greedy"}, {"name": "a", "kind": "vicsek"}]})
    assert err.value.path == "members[1].name" and "duplicate" in str(err.value)
    with pytest.raises(ConfigError) as err:
        load_zoo({"name": "bad", "members": []})
    assert err.value.path == "members"
    with pytest.raises(ConfigError, match="no zoo named 'zoo9'"):
        load_zoo("zoo9")


# ---------------------------------------------------- the Gymnasium view
@pytest.mark.parametrize("task", TASK_NAMES)
def test_adaptive_teaming_view_passes_gymnasium_check_env(task: str):
    env = gymnasium.make("atdrone/AdaptiveTeaming-v0", task=task, zoo="zoo1")
    assert isinstance(env.unwrapped, AdaptiveTeamingEnv)
    check_env(env.unwrapped, skip_render_check=True)
    num_e = load_task(task).players.num_e
    assert env.observation_space.shape == (2, 4 * (num_e + 4))
    assert env.action_space.shape == (2,)


def test_adaptive_teaming_view_reports_the_team_and_ends_episodes_like_the_match():
    cfg = short_horizon("4p2e3o", 30)
    view = AdaptiveTeamingEnv(cfg, zoo=load_zoo("zoo3", cfg) if not load_zoo("zoo3", cfg).missing else "zoo1")
    match = Match(BatchedPursuit(cfg, num_envs=1), view.zoo)
    obs, info = view.reset(seed=7)
    np.testing.assert_array_equal(obs, match.reset(seed=7)[0])
    assert set(info["team"]) == {"learner_slots", "partner_slots", "partner_members", "partners"}
    team = info["team"]
    rng = np.random.default_rng(0)
    ends = 0
    for _ in range(150):
        action = rng.uniform(-0.3, 0.3, size=2).astype(np.float32)
        obs, reward, terminated, truncated, info = view.step(action)
        m_obs, m_rewards, m_dones, m_info = match.step(action[None].astype(np.float64))
        expected = m_info["final_obs"][0] if m_dones[0] else m_obs[0]
        np.testing.assert_array_equal(obs, expected)
        assert reward == m_rewards[0, 0]
        assert (terminated or truncated) == bool(m_dones[0])
        if m_dones[0]:
            ends += 1
            assert info["team"] == team  # the team of the episode that ended
            assert len(info["team"]["learner_slots"]) == 2 and len(info["team"]["partners"]) == 2
            assert set(info["team"]["partners"]) <= set(view.zoo.names)
            obs, info = view.reset()
            np.testing.assert_array_equal(obs, m_obs[0])
            team = info["team"]
        else:
            assert "team" not in info
    assert ends >= 3


def test_adaptive_teaming_view_with_missing_zoo_members_fails_at_make_time(tmp_path):
    with pytest.raises(ZooError, match="ghost"):
        gymnasium.make("atdrone/AdaptiveTeaming-v0", task="4p2e1o", zoo=str(missing_zoo(tmp_path)))


# ------------------------------------------------------------- evaluation
# Greedy-team SUC (4 greedy drones: greedy learners + zoo1), 200 episodes x seeds 0-7, measured:
# 63.6 / 56.1 / 38.9 / 23.9 % (per-seed range 58-71 / 49-61 / 37-42 / 18-29, within the binomial spread of
# 200 episodes). With per-episode draws (issue 26) the same measure gives 60.8 / 54.0 / 41.8 / 25.1 %
# (per-seed range 57-66 / 46-58 / 37-47 / 21-28), every task within 2 standard errors of the first.
# Seed 0, the one played here, with per-episode draws: 120 / 116 / 77 / 54 successes of 200
# (60.0 / 58.0 / 38.5 / 27.0 %; before: 131 / 122 / 79 / 52).
GREEDY_SUC = {"4p2e1o": 63.6, "4p2e3o": 56.1, "4p2e5o": 38.9, "4p3e5o": 23.9}
GREEDY_SEED0_SUCCESSES = {"4p2e1o": 120, "4p2e3o": 116, "4p2e5o": 77, "4p3e5o": 54}
GREEDY_EPISODES = 200


@pytest.mark.parametrize("task", TASK_NAMES)
def test_a_greedy_team_captures_as_often_as_measured(task: str):
    """Within 4 binomial standard errors of the measured mean (the band a fair sample of 200 episodes stays in),
    and, the evaluation being deterministic by seed (test_evaluation_is_deterministic_given_a_seed), exactly
    seed 0's measured count: a regression of a few episodes fails, not only one of 35 %."""
    n = GREEDY_EPISODES
    result = evaluate(GreedyPolicy(), task, "zoo1", episodes=n, seeds=(0,))
    assert len(result.records) == n
    p = GREEDY_SUC[task] / 100
    band = 4 * 100 * (p * (1 - p) / n) ** 0.5  # 4 standard errors: 13.6 / 14.0 / 13.8 / 12.1 points
    assert abs(result.mean["SUC"] - GREEDY_SUC[task]) <= band, (result.mean["SUC"], GREEDY_SUC[task], band)
    assert int(result.records["success"].sum()) == GREEDY_SEED0_SUCCESSES[task]


def test_evaluation_is_deterministic_given_a_seed():
    task = short_horizon("4p2e5o", 150)
    zoo = "zoo3" if not load_zoo("zoo3", task).missing else "zoo1"
    first = evaluate(VicsekPolicy(), task, zoo, episodes=40, seeds=(3,))
    second = evaluate(VicsekPolicy(), task, first.zoo, episodes=40, seeds=(3,))
    pd.testing.assert_frame_equal(first.records, second.records)
    other = evaluate(VicsekPolicy(), task, first.zoo, episodes=40, seeds=(4,))
    assert not first.records["length"].equals(other.records["length"])


def recount(records: pd.DataFrame) -> dict[str, float]:
    """SPEC section 9 by hand, one record at a time."""
    n = successes = collisions = 0
    success_steps = total_return = 0.0
    for rec in records.to_dict("records"):
        n += 1
        success = rec["outcome"] == "captured"
        successes += success
        collisions += bool(rec["collided"])
        success_steps += rec["length"] if success else 0
        total_return += rec["return"]
    return {
        "SUC": 100.0 * successes / n,
        "COL": 100.0 * collisions / n,
        "AST": success_steps / successes if successes else float("nan"),
        "REW": total_return / n,
    }


def test_metrics_equal_a_plain_recount_of_the_episode_records():
    result = evaluate(GreedyPolicy(), short_horizon("4p2e1o", 250), "zoo1", episodes=60, seeds=(5,))
    records = result.records
    assert set(records["outcome"]) == {"captured", "collision", "timeout"}
    assert list(records.columns[:8]) == [
        "episode",
        "seed",
        "reason",
        "length",
        "return",
        "collided",
        "captured",
        "learner_slots",
    ]
    assert (records["success"] == (records["reason"] == CAPTURED)).all()
    assert (records.loc[records["success"], "captured"] == 2).all()
    assert records["episode"].tolist() == list(range(60))
    by_hand = recount(records)
    for m in METRICS:
        assert result.per_seed.loc[5, m] == pytest.approx(by_hand[m], rel=1e-12)
        assert result.mean[m] == pytest.approx(by_hand[m], rel=1e-12)
    assert 0 < by_hand["SUC"] < 100  # both kinds of episode were counted


def test_ast_is_nan_without_a_success():
    records = pd.DataFrame(
        {"success": [False, False], "collided": [True, False], "length": [10, 1000], "return": [1.0, 2.0]}
    )
    out = metrics(records)
    assert out["SUC"] == 0.0 and out["COL"] == 50.0 and out["REW"] == 1.5 and np.isnan(out["AST"])


def test_several_seeds_give_per_seed_metrics_and_their_mean_and_std():
    seeds = (0, 1, 2)
    task = short_horizon("4p2e3o", 200)
    result = evaluate(GreedyPolicy(), task, "zoo1", episodes=40, seeds=seeds)
    assert list(result.per_seed.index) == list(seeds) and len(result.records) == 120
    for s in seeds:
        per = recount(result.records[result.records["seed"] == s])
        for m in METRICS:
            assert result.per_seed.loc[s, m] == pytest.approx(per[m], rel=1e-12)
    for m in METRICS:
        values = result.per_seed[m].to_numpy()
        assert result.mean[m] == pytest.approx(np.mean(values), rel=1e-12)
        assert result.std[m] == pytest.approx(np.std(values), rel=1e-12, abs=1e-12)
    # a seed's episodes do not depend on which other seeds were played
    alone = evaluate(GreedyPolicy(), task, "zoo1", episodes=40, seeds=(1,))
    pd.testing.assert_frame_equal(
        alone.records, result.records[result.records["seed"] == 1].reset_index(drop=True), check_dtype=False
    )


def test_run_episodes_counts_each_environment_once_and_reports_progress():
    seen = []
    records = run_episodes(GreedyPolicy(), short_horizon("4p2e1o", 20), [GreedyPolicy()], 30, on_progress=seen.append)
    assert len(records) == 30 and sum(seen) == 30
    assert (records["length"] <= 20).all()
    assert set(records["partners"]) == {"greedy,greedy"}


def test_evaluate_grid_lists_missing_members_instead_of_playing(tmp_path):
    zoos = [load_zoo("zoo1"), load_zoo(missing_zoo(tmp_path))]
    cells = evaluate_grid(GreedyPolicy(), [short_horizon("4p2e1o", 30)], zoos, episodes=5)
    assert [(c.zoo, c.evaluation is None, c.missing) for c in cells] == [
        ("zoo1", False, ()),
        ("ghosts", True, ("ghost",)),
    ]
    table = format_table(cells, "greedy", 5, [0])
    assert "missing: ghost" in table and "SUC %" in table and "ghosts" in table


def test_format_table_lays_tasks_in_rows_and_zoos_in_columns():
    evaluation = evaluate(GreedyPolicy(), short_horizon("4p2e1o", 30), "zoo1", episodes=4, seeds=(0, 1))
    cells = [GridCell("4p2e1o", "zoo1", evaluation), GridCell("4p2e1o", "zoo2", None, ("sp_high", "sp_low"))]
    lines = format_table(cells, "greedy", 4, [0, 1]).splitlines()
    assert lines[0].startswith("greedy: 4 episodes per seed, 2 seeds (0, 1)")
    assert lines[2].split() == ["task", "metric", "zoo1", "zoo2"]
    body = lines[4:]
    assert [line.split()[0] for line in body if not line.startswith(" ")] == ["4p2e1o"]
    assert "missing: sp_high, sp_low" in body[0]
    assert [line.split()[-4 if i == 0 else 0] for i, line in enumerate(body)][1:] == ["COL", "AST", "REW"]
    assert "[" in body[0] and "; seeds [" in body[0]  # an interval over episodes, and one over the two seeds


# -------------------------------------------------------------------- CLI
def test_cli_evaluate_prints_the_table_and_writes_json_and_csv(tmp_path, capsys):
    out, task = tmp_path / "eval", tmp_path / "task.json"
    task.write_text(json.dumps(short_horizon("4p2e1o", 250).to_dict()))
    args = ["evaluate", "--policy", "greedy", "--task", str(task), "--zoo", "zoo1", "--episodes", "20"]
    rc = main([*args, "--seeds", "0", "1", "--out-dir", str(out), "--no-progress"])
    assert rc == 0
    stdout = capsys.readouterr().out
    assert "greedy: 20 episodes per seed, 2 seeds (0, 1)" in stdout
    assert "SUC %" in stdout and "COL %" in stdout and "AST steps" in stdout and "REW" in stdout
    doc = json.loads((out / "greedy_4p2e1o_zoo1.json").read_text())
    episodes = pd.read_csv(out / "greedy_4p2e1o_zoo1.csv")
    assert sorted(p.name for p in out.iterdir()) == ["greedy_4p2e1o_zoo1.csv", "greedy_4p2e1o_zoo1.json"]
    assert doc["learner"] == "greedy" and doc["seeds"] == [0, 1] and doc["episodes_per_seed"] == 20
    (cell,) = doc["cells"]
    assert cell["status"] == "ok" and cell["summary"]["episodes"] == 40 and len(cell["per_seed"]) == 2
    assert len(episodes) == 40 and set(episodes["task"]) == {"4p2e1o"} and set(episodes["zoo"]) == {"zoo1"}
    for row in cell["per_seed"]:  # the summary is what the episodes in the CSV say
        by_hand = recount(episodes[episodes["seed"] == row["seed"]])
        assert [row[m] for m in METRICS] == pytest.approx([by_hand[m] for m in METRICS])
    for m in METRICS:
        values = [row[m] for row in cell["per_seed"]]
        assert (cell["summary"][m], cell["summary"][f"{m}_std"]) == pytest.approx((np.mean(values), np.std(values)))
    assert f"{cell['summary']['SUC']:.1f} [" in stdout  # the value with its interval, never a std of one value


def test_cli_evaluate_all_tasks_reports_incomplete_zoos_as_missing(tmp_path, capsys):
    args = ["evaluate", "--policy", "vicsek", "--task", "all", "--zoo", "all", "--episodes", "2"]
    rc = main([*args, "--out-dir", str(tmp_path)])
    assert rc == 0
    captured = capsys.readouterr()
    lines = captured.out.splitlines()
    assert lines[2].split() == ["task", "metric", *ZOO_NAMES]
    body = lines[4 : next(i for i, line in enumerate(lines) if line.startswith("wrote"))]
    assert [line.split()[0] for line in body if line and not line.startswith(" ")] == list(TASK_NAMES)
    for task in TASK_NAMES:  # a zoo whose drones of a task are not all trained: that task's cell lists them
        for name in ZOO_NAMES:
            zoo = load_zoo(name, task)
            if zoo.missing:
                assert f"missing: {', '.join(zoo.missing)}" in captured.out
    assert "evaluate" in captured.err  # the progress bar
    doc = json.loads((tmp_path / "vicsek_all_all.json").read_text())
    assert len(doc["cells"]) == len(TASK_NAMES) * len(ZOO_NAMES)  # 4 x 4


@pytest.mark.parametrize(
    ("flag", "value", "message"),
    [
        ("--task", "4p9e9o", "no task named '4p9e9o'"),
        ("--zoo", "zoo9", "no zoo named 'zoo9'"),
        ("--policy", "kamikaze", "no policy 'kamikaze'"),
    ],
)
def test_cli_evaluate_refuses_bad_names_with_one_line_and_exit_2(flag, value, message, tmp_path, capsys):
    args = {"--policy": "greedy", "--task": "4p2e1o", "--zoo": "zoo1", flag: value}
    rc = main(["evaluate", *[x for kv in args.items() for x in kv], "--episodes", "2", "--out-dir", str(tmp_path)])
    assert rc == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1
    assert not any(tmp_path.iterdir())


def test_render_shows_a_policy_playing_with_zoo_partners(tmp_path, capsys):
    frames, summary = record_episode("4p2e1o", seed=3, policy=GreedyPolicy(), partners=load_zoo("zoo1"), max_steps=4)
    team = summary["team"]
    assert sorted(team["learner_slots"] + team["partner_slots"]) == [0, 1, 2, 3]
    assert team["partners"] == ["greedy", "greedy"] and len(frames) == 5
    args = ["render", "--task", "4p2e1o", "--policy", "vicsek", "--zoo", "zoo1", "--max-steps", "3"]
    rc = main([*args, "--out", str(tmp_path / "team.gif")])
    assert rc == 0 and (tmp_path / "team.gif").is_file()
    assert "team: learners in slots" in capsys.readouterr().out


@pytest.mark.parametrize("straight_learners", [True, False])
def test_records_name_whether_learners_or_partners_crashed(straight_learners):
    # Turning 45 degrees a step, a drone circles on the spot; flying straight (+y, the
    # start heading) at 0.03 m a step, it meets the far wall after more than 30 steps.
    # Earlier endings are a straight flyer clipping a circling neighbour: both crashed.
    learner, partner = (Constant("straight", 0.0), Constant("circling", 1.0))[:: 1 if straight_learners else -1]
    records = run_episodes(learner, "4p2e1o", [partner], 24, seed=2)
    assert (records["outcome"] == "collision").all()
    straight, circling = ("learner", "partner") if straight_learners else ("partner", "learner")
    assert records[f"{straight}_crashed"].all()
    assert (records[f"{circling}_crashed"] == (records["length"] < 30)).all()
    assert (records["length"] >= 30).sum() >= 12  # most episodes end at the wall
    shares = crash_shares(records)
    wall_only = 100.0 * (records["length"] >= 30).mean()
    if straight_learners:
        assert shares == {"learner_crash": 100.0, "partner_only_crash": 0.0}
    else:
        assert shares == pytest.approx({"learner_crash": 100.0 - wall_only, "partner_only_crash": wall_only})
    # late: a straight flyer reached the bar (x 1.0-2.5) or the top wall; earlier, it clipped a circling drone
    late = records["length"] >= 30
    assert records["crash"][late].isin([f"{straight}-wall", f"{straight}-obstacle"]).all()
    assert records["crash"][~late].str.contains("learner-partner").all()
    breakdown = crash_breakdown(records)
    assert breakdown[f"{straight}-obstacle"] > 0
    assert breakdown[f"{straight}-wall"] + breakdown[f"{straight}-obstacle"] == pytest.approx(wall_only)
    assert breakdown["learner-partner"] == pytest.approx(100.0 - wall_only)
    assert breakdown["learner-learner"] == breakdown["partner-partner"] == 0.0


def test_crash_kinds_by_role():
    info = {
        "collided": np.array([[True, True, True, False], [False, False, True, True]]),
        "hit_pairs": np.array([[True, False, False, False, False, False], [False] * 5 + [True]]),
        "hit_obstacle": np.array([[-1, -1, 0, -1], [-1, -1, -1, 4]]),
    }
    pairs = np.stack(np.triu_indices(4, 1), 1)  # (0,1) first, (2,3) last
    kinds = crash_kinds(info, np.array([0, 1]), np.array([[0, 2], [0, 1]]), pairs)
    assert kinds == ["learner-partner+learner-wall", "partner-partner+partner-obstacle"]
