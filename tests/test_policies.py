"""Rule-based teammates on hand-built scenes: greedy and VICSEK drones steer where SPEC
section 8 says, by the right amount, and never outside the 45-degree turn limit."""

from __future__ import annotations

import numpy as np
import pytest

from atdrone.envs.core import BatchedPursuit
from atdrone.envs.kinematics import MAX_TURN
from atdrone.policies import DroneBatch, GreedyPolicy, Policy, VicsekPolicy

TURN = MAX_TURN  # radians per unit action
AVOID = 20 / 45  # greedy's 20-degree veer as an action
UP = np.pi / 2
# Teammates 1-3 parked far from drone 0, from each other, from walls and from the bar
# of 4p2e1o (x 1.0-2.5, y 2.45-2.55): nothing near them but what a test puts there.
PARKED = [(0.6, 0.6), (3.0, 0.6), (3.0, 4.0)]


def scene(
    p0: tuple[float, float],
    heading0: float,
    evaders: list[tuple[float, float]],
    mates: list[tuple[float, float]] = PARKED,
    mate_headings: list[float] | None = None,
    captured: list[bool] | None = None,
    task: str = "4p2e1o",
) -> DroneBatch:
    """A one-environment scene: pursuer 0 at ``p0`` with ``heading0``, the other pursuers at ``mates``."""
    core = BatchedPursuit(task, num_envs=1, seed=0)
    core.reset()
    s, P = core.state, core.num_p
    s.pos[0, :P] = [p0, *mates]
    s.pos[0, P:] = evaders
    s.heading[0, :P] = [heading0, *(mate_headings or [UP] * (P - 1))]
    s.captured[0] = captured or [False] * core.num_e
    return DroneBatch.all_slots(core.observe(), core.poses())


def polar(origin: tuple[float, float], dist: float, angle: float) -> tuple[float, float]:
    return (origin[0] + dist * np.cos(angle), origin[1] + dist * np.sin(angle))


def act0(policy: Policy, batch: DroneBatch) -> float:
    actions = policy.act(batch)
    assert actions.shape == (len(batch),)
    return float(actions[0])


# ------------------------------------------------------------------ greedy
def test_greedy_turns_towards_the_nearest_evader_by_the_bearing_over_45_degrees():
    p0 = (1.8, 1.0)
    near = polar(p0, 0.8, UP + np.deg2rad(30))  # 30 degrees to the left
    batch = scene(p0, UP, [near, (3.0, 4.6)])
    assert act0(GreedyPolicy(), batch) == pytest.approx(30 / 45)
    # mirrored: 30 degrees to the right
    batch = scene(p0, UP, [polar(p0, 0.8, UP - np.deg2rad(30)), (3.0, 4.6)])
    assert act0(GreedyPolicy(), batch) == pytest.approx(-30 / 45)


def test_greedy_ignores_a_captured_evader():
    p0, far = (1.8, 1.0), (3.0, 4.6)
    batch = scene(p0, UP, [polar(p0, 0.8, UP + np.deg2rad(30)), far], captured=[True, False])
    expected = (np.arctan2(far[1] - p0[1], far[0] - p0[0]) - UP) / TURN
    assert act0(GreedyPolicy(), batch) == pytest.approx(expected)
    assert expected < 0  # the far evader is to the right, the captured one was to the left


def test_greedy_turns_at_most_45_degrees_towards_an_evader_behind_it():
    p0 = (1.8, 1.0)
    batch = scene(p0, UP, [polar(p0, 0.8, UP + np.deg2rad(150)), (3.0, 4.6)])
    assert act0(GreedyPolicy(), batch) == 1.0
    batch = scene(p0, UP, [polar(p0, 0.8, UP - np.deg2rad(150)), (3.0, 4.6)])
    assert act0(GreedyPolicy(), batch) == -1.0


def test_greedy_veers_20_degrees_off_a_wall_within_0_3_m_ahead():
    # Nose 11.5 degrees left of the top wall's normal, the evader up-left: the chase would
    # turn hard left into the wall; greedy veers 20 degrees right instead.
    heading = UP - 0.2
    near_wall = scene((1.8, 4.82), heading, [(1.0, 4.7), (3.0, 0.3)])
    assert act0(GreedyPolicy(), near_wall) == pytest.approx(-AVOID)
    # the same scene 0.35 m from the wall: plain chase, a full left turn
    clear = scene((1.8, 4.65), heading, [(1.0, 4.53), (3.0, 0.3)])
    assert act0(GreedyPolicy(), clear) == 1.0


def test_greedy_veers_20_degrees_off_an_obstacle_within_0_3_m_ahead():
    # 0.2 m under the bar of 4p2e1o, the bar 6 degrees left of the nose, evader beyond the bar
    batch = scene((1.8, 2.25), UP - 0.1, [(1.8, 4.0), (0.4, 4.6)])
    assert act0(GreedyPolicy(), batch) == pytest.approx(-AVOID)  # veers right, away from it
    mirrored = scene((1.8, 2.25), UP + 0.1, [(1.8, 4.0), (0.4, 4.6)])
    assert act0(GreedyPolicy(), mirrored) == pytest.approx(AVOID)


def test_greedy_veers_20_degrees_off_a_teammate_within_0_3_m():
    p0 = (1.8, 1.5)
    evaders = [(1.8, 4.0), (0.4, 4.6)]  # straight ahead: the chase alone would fly straight
    mate = (1.9, 1.72)  # 0.24 m away, ahead and to the right
    batch = scene(p0, UP, evaders, mates=[mate, *PARKED[1:]])
    assert act0(GreedyPolicy(), batch) == pytest.approx(AVOID)  # left, away from it
    mirrored = scene(p0, UP, evaders, mates=[(1.7, 1.72), *PARKED[1:]])
    assert act0(GreedyPolicy(), mirrored) == pytest.approx(-AVOID)
    far = scene(p0, UP, evaders, mates=[(1.9, 2.1), *PARKED[1:]])
    assert act0(GreedyPolicy(), far) == pytest.approx(0.0)


def test_greedy_anticipates_a_teammate_closing_head_on():
    # 0.4 m apart now, but closing at 0.06 m/step: within 0.3 m in the 4-step lookahead
    p0, evaders = (1.8, 1.5), [(1.8, 4.0), (0.4, 4.6)]
    mates = [(1.85, 1.9), *PARKED[1:]]
    headings = [-UP, UP, UP]
    assert act0(GreedyPolicy(), scene(p0, UP, evaders, mates, headings)) == pytest.approx(AVOID)
    assert act0(GreedyPolicy(lookahead=0), scene(p0, UP, evaders, mates, headings)) == pytest.approx(0.0)


# ------------------------------------------------------------------ VICSEK
def test_vicsek_chases_the_nearest_evader_when_no_teammate_is_close():
    p0 = (1.8, 1.0)
    batch = scene(p0, UP, [polar(p0, 0.8, UP + np.deg2rad(30)), (3.0, 4.6)])
    # pure chase term: the exact bearing
    assert act0(VicsekPolicy(cohesion=0.0, alignment=0.0), batch) == pytest.approx(30 / 45)
    # with the weak long-range terms it still turns most of the way towards the evader
    assert 0.4 < act0(VicsekPolicy(), batch) < 0.9


def test_noisy_vicsek_turns_the_wanted_heading_by_its_keys_draw():
    """The Vicsek model's angular noise: the wanted heading plus noise * (u - 1/2), u the key's uniform draw,
    the same for the same key (whatever else shares the batch), none at noise 0, and the policy's own generator
    without keys (a deploy)."""
    from dataclasses import replace

    from atdrone.envs.streams import fold, unit
    from atdrone.policies.rules import NOISE_DRAW

    p0 = (1.8, 1.0)
    batch = scene(p0, UP, [polar(p0, 0.8, UP + np.deg2rad(30)), (3.0, 4.6)])
    pure = {"cohesion": 0.0, "alignment": 0.0}
    noise = np.deg2rad(20.0)
    turns = []
    for key in range(1, 41):
        keys = np.full(len(batch), key, dtype=np.uint64)
        u = float(unit(fold(keys, NOISE_DRAW))[0])
        want = 30.0 + np.rad2deg(noise) * (u - 0.5)  # degrees left of the nose: inside the 45-degree limit
        got = act0(VicsekPolicy(noise=noise, **pure), replace(batch, keys=keys))
        assert got == pytest.approx(want / 45), key
        assert act0(VicsekPolicy(noise=0.0, **pure), replace(batch, keys=keys)) == pytest.approx(30 / 45)
        turns.append(got * 45 - 30)
    assert max(turns) - min(turns) > 15.0  # the draws spread over most of the 20 degrees
    same = np.full(len(batch), 5, dtype=np.uint64)
    assert act0(VicsekPolicy(noise=noise), replace(batch, keys=same)) == act0(
        VicsekPolicy(noise=noise), replace(batch, keys=same)
    )
    own = [act0(VicsekPolicy(noise=noise, **pure), batch) for _ in range(2)]  # no keys: a fresh generator each
    assert own[0] == own[1] != pytest.approx(30 / 45)
    with pytest.raises(ValueError, match="noise"):
        VicsekPolicy(noise=-0.1)


def test_vicsek_turns_away_from_a_close_teammate_instead_of_chasing():
    p0, evaders = (1.8, 1.5), [(1.8, 4.0), (0.4, 4.6)]
    right = scene(p0, UP, evaders, mates=[polar(p0, 0.1, UP - np.deg2rad(45)), *PARKED[1:]])
    left = scene(p0, UP, evaders, mates=[polar(p0, 0.1, UP + np.deg2rad(45)), *PARKED[1:]])
    assert act0(VicsekPolicy(), right) == 1.0  # repulsion outweighs the chase: hard left
    assert act0(VicsekPolicy(), left) == -1.0
    # beyond the 0.25 m repulsion range the teammate only nudges (cohesion), the chase wins
    beyond = scene(p0, UP, evaders, mates=[polar(p0, 0.3, UP - np.deg2rad(45)), *PARKED[1:]])
    assert abs(act0(VicsekPolicy(), beyond)) < 0.1


def _gaps_chasing_one_evader(policy: Policy, steps: int = 20) -> list[float]:
    """Two drones 0.22 m apart fly at one (frozen) evader; their gap after each step."""
    core = BatchedPursuit("4p2e1o", num_envs=1, seed=0)
    core.reset()
    s, P = core.state, core.num_p
    s.pos[0, :P] = [(1.7, 0.5), (1.92, 0.5), (0.3, 0.4), (3.3, 0.4)]
    s.pos[0, P:] = [(1.8, 1.6), (0.4, 4.6)]
    step = core.cfg.players.velocity_p * core.cfg.dt
    gaps = []
    for _ in range(steps):
        heading = s.heading[0, :P] + policy.act(DroneBatch.all_slots(core.observe(), core.poses())) * TURN
        s.pos[0, :2] += step * np.stack([np.cos(heading[:2]), np.sin(heading[:2])], -1)
        s.heading[0, :P] = heading
        gaps.append(float(np.linalg.norm(s.pos[0, 0] - s.pos[0, 1])))
    return gaps


def test_vicsek_keeps_separation_where_a_pure_chase_would_collide():
    collision = 0.2
    assert min(_gaps_chasing_one_evader(VicsekPolicy())) > collision + 0.02
    assert min(_gaps_chasing_one_evader(VicsekPolicy(mate_gain=0.0))) < collision  # no repulsion: they converge


# --------------------------------------------------------- both policies
@pytest.mark.parametrize("policy", [GreedyPolicy(), VicsekPolicy()], ids=["greedy", "vicsek"])
def test_rule_actions_are_finite_and_within_the_turn_limit_on_random_scenes(policy: Policy):
    core = BatchedPursuit("4p3e5o", num_envs=256, seed=0)
    core.reset()
    rng = np.random.default_rng(0)
    s = core.state
    s.pos[...] = rng.uniform([0.0, 0.0], [3.6, 5.0], size=s.pos.shape)  # inside obstacles too
    s.pos[:8, 1] = s.pos[:8, core.num_p]  # drone on top of an evader
    s.pos[8:16, 1] = s.pos[8:16, 0]  # two drones at one point
    s.heading[...] = rng.uniform(-np.pi, np.pi, size=s.heading.shape)
    s.captured[...] = rng.random(s.captured.shape) < 0.4
    s.captured[:4] = True  # nothing left to chase
    actions = policy.act(DroneBatch.all_slots(core.observe(), core.poses()))
    assert actions.shape == (256 * core.num_p,)
    assert np.isfinite(actions).all()
    assert (np.abs(actions) <= 1.0).all()
    before = s.heading[:, : core.num_p].copy()
    core.step(actions.reshape(256, core.num_p))
    # final_state: the whole batch after the step, before finished environments reset
    after = core.final_state if core.final_state is not None else core.state
    turn = np.angle(np.exp(1j * (after.heading[:, : core.num_p] - before)))
    assert np.abs(turn).max() <= TURN + 1e-9


def test_rule_policies_act_on_any_subset_of_drones():
    batch = scene((1.8, 1.0), UP, [(1.4, 1.7), (3.0, 4.6)])
    for policy in (GreedyPolicy(), VicsekPolicy()):
        full = policy.act(batch)
        sub = DroneBatch(batch.obs[[2, 0]], batch.env[[2, 0]], batch.slot[[2, 0]], batch.poses)
        np.testing.assert_array_equal(policy.act(sub), full[[2, 0]])
        assert isinstance(policy, Policy)
