"""Hand-computed physics of the batched pursuit core: kinematics, geometry, capture,
collision, reward, observation, episode ends, determinism and spawns (SPEC sections 1-6).

Scenes are set by overwriting ``env.state`` after ``reset()``. Where an evader's motion
would blur a hand-computed number, the task is loaded with ``velocity_e`` = 1e-9 so the
evaders (still running their escape policy) move 1e-10 m per step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import pytest

from atdrone.config import TASK_NAMES, TaskConfig, load_task
from atdrone.envs.core import CAPTURED, COLLISION, RUNNING, TIMEOUT, BatchedPursuit
from atdrone.envs.geometry import Geometry, nearest_obstacle, obstacle_distances, signed_distances

UP, DOWN, RIGHT = math.pi / 2, -math.pi / 2, 0.0
STEP_P = 0.3 * 0.1  # pursuer metres per step
STEP_E = 0.6 * 0.1  # evader metres per step
R2 = math.sqrt(2) / 2
R3 = math.sqrt(3) / 2


def modified(task: str, changes: dict[str, Any]) -> TaskConfig:
    """The paper task with dotted-path fields replaced, e.g. {"task.task_horizon": 5}."""
    doc = load_task(task).to_dict()
    for dotted, value in changes.items():
        *parents, leaf = dotted.split(".")
        node = doc
        for key in parents:
            node = node[key]
        node[leaf] = value
    return load_task(doc)


def still_evaders(task: str = "4p2e1o", **changes: Any) -> TaskConfig:
    return modified(task, {"players.velocity_e": 1e-9, **changes})


def make(task: TaskConfig | str, num_envs: int = 1, seed: int = 0) -> BatchedPursuit:
    env = BatchedPursuit(task, num_envs=num_envs, seed=seed)
    env.reset()
    return env


def place(
    env: BatchedPursuit,
    pursuers: Sequence[tuple[float, float, float]],
    evaders: Sequence[tuple[float, float]],
    b: int = 0,
    captured: Sequence[bool] | None = None,
) -> None:
    """Put env ``b``'s pursuers at (x, y, heading) and evaders at (x, y), then re-baseline shaping."""
    s, P = env.state, env.num_p
    for i, (x, y, h) in enumerate(pursuers):
        s.pos[b, i] = (x, y)
        s.heading[b, i] = h
    for j, (x, y) in enumerate(evaders):
        s.pos[b, P + j] = (x, y)
        s.heading[b, P + j] = UP
    if captured is not None:
        s.captured[b] = captured
    s.prev_dist = env._evader_distances(s.pos)


def shaping(
    evaders: Sequence[tuple[float, float]],
    before: Sequence[tuple[float, float]],
    after: Sequence[tuple[float, float]],
    active: Sequence[bool] | None = None,
) -> float:
    """Sum over active evaders of the drop in nearest-pursuer distance, / 0.3."""
    total = 0.0
    for j, e in enumerate(evaders):
        if active is None or active[j]:
            total += min(math.dist(e, p) for p in before) - min(math.dist(e, p) for p in after)
    return total / 0.3


def up(points: Sequence[tuple[float, float, float]], dy: float = STEP_P) -> list[tuple[float, float]]:
    """Positions after one step with action 0 of pursuers heading straight up."""
    return [(x, y + dy) for x, y, _ in points]


def step(env: BatchedPursuit, actions: Sequence[float] | np.ndarray | None = None):
    a = np.zeros((env.num_envs, env.num_p)) if actions is None else np.asarray(actions, dtype=float)
    return env.step(a.reshape(env.num_envs, env.num_p))


# ------------------------------------------------------------------ kinematics
def test_pursuer_turn_is_limited_to_45_degrees_and_speed_is_constant() -> None:
    env = make("4p2e1o", num_envs=2)
    row = [(0.5, 1.0), (1.2, 1.0), (1.9, 1.0), (2.6, 1.0)]
    place(env, [(x, y, UP) for x, y in row], [(0.8, 4.5), (2.8, 4.5)], b=0)
    place(env, [(x, y, RIGHT) for x, y in row[:3]] + [(2.6, 1.5, math.pi - 0.1)], [(0.8, 4.5), (2.8, 4.5)], b=1)
    before = env.state.pos[:, :4].copy()
    actions = [[1.0, 5.0, -1.0, 0.0], [-5.0, 0.5, -0.5, 1.0]]
    obs, _, done, _ = step(env, actions)
    assert not done.any()
    expected_heading = [
        [3 * math.pi / 4, 3 * math.pi / 4, math.pi / 4, math.pi / 2],
        [-math.pi / 4, math.pi / 8, -math.pi / 8, math.pi - 0.1 + math.pi / 4],
    ]
    h = env.state.heading[:, :4]
    assert np.cos(h) == pytest.approx(np.cos(expected_heading), abs=1e-12)
    assert np.sin(h) == pytest.approx(np.sin(expected_heading), abs=1e-12)
    assert np.all((h > -math.pi) & (h <= math.pi))
    moved = env.state.pos[:, :4] - before
    assert np.hypot(moved[..., 0], moved[..., 1]) == pytest.approx(np.full((2, 4), 0.03), abs=1e-12)
    assert moved[..., 0] == pytest.approx(STEP_P * np.cos(expected_heading), abs=1e-12)
    assert moved[..., 1] == pytest.approx(STEP_P * np.sin(expected_heading), abs=1e-12)
    # the observation returned is that of the new state
    assert np.array_equal(obs, env.observe())


def test_nan_action_flies_straight() -> None:
    env = make("4p2e1o")
    place(env, [(0.5, 1.0, UP), (1.2, 1.0, UP), (1.9, 1.0, UP), (2.6, 1.0, UP)], [(0.8, 4.5), (2.8, 4.5)])
    step(env, [math.nan, 0.0, 0.0, 0.0])
    assert env.state.pos[0, 0] == pytest.approx((0.5, 1.03), abs=1e-12)
    assert np.isfinite(env.state.pos).all()


def test_evaders_move_exactly_0_06_m_per_step_and_captured_ones_stand_still() -> None:
    env = make("4p2e1o", num_envs=3)
    far = [(0.5, 0.5, UP), (1.2, 0.5, UP), (2.0, 0.5, UP), (3.0, 0.5, UP)]
    evaders = [(1.0, 3.8), (2.6, 3.8)]
    place(env, far, evaders, b=0)  # calm: wandering
    place(env, [(1.0, 3.3, UP), (2.6, 3.2, UP), (2.0, 0.5, UP), (3.0, 0.5, UP)], evaders, b=1)  # fleeing
    place(env, far, evaders, b=2, captured=[True, False])
    before = env.evader_pos.copy()
    _, _, done, _ = step(env)
    assert not done.any()
    moved = env.evader_pos - before
    length = np.hypot(moved[..., 0], moved[..., 1])
    assert length == pytest.approx(np.array([[STEP_E, STEP_E], [STEP_E, STEP_E], [0.0, STEP_E]]), abs=1e-12)
    h = env.state.heading[:, 4:]
    active = ~env.state.captured
    assert moved[active] == pytest.approx(STEP_E * np.stack([np.cos(h), np.sin(h)], -1)[active], abs=1e-12)
    # fleeing evaders run away from the pursuer 0.5 m below them
    assert moved[1, :, 1].min() > 0


# -------------------------------------------------------------------- geometry
def test_geometry_lists_walls_then_boxes_then_discs() -> None:
    geo = Geometry.from_config(load_task("4p2e3o"))
    assert geo.names == ("wall_left", "wall_right", "wall_bottom", "wall_top", "cube_low", "cube_high", "cylinder")


@pytest.mark.parametrize(
    ("point", "expected", "normals"),
    [
        # outside cube_low (x 1.0-1.4, y 1.3-1.7), facing its left face
        (
            (0.5, 1.5),
            [0.5, 3.1, 1.5, 3.5, 0.5, math.sqrt(0.5**2 + 1.8**2), math.hypot(1.9, 1.0) - 0.2],
            {4: (-1.0, 0.0)},
        ),
        # off cube_low's top-right corner (1.4, 1.7) by (0.3, 0.4)
        ((1.7, 2.1), [1.7, 1.9, 2.1, 2.9, 0.5, math.hypot(0.3, 1.2), math.hypot(0.7, 0.4) - 0.2], {4: (0.6, 0.8)}),
        # inside cube_low: 0.15 from the left face, 0.2 from top and bottom, 0.25 from the right
        ((1.15, 1.5), [1.15, 2.45, 1.5, 3.5, -0.15, 1.8, math.hypot(1.25, 1.0) - 0.2], {4: (-1.0, 0.0)}),
        # outside the cylinder (centre (2.4, 2.5), r 0.2) by 0.3 along (0.6, 0.8)
        ((2.7, 2.9), [2.7, 0.9, 2.9, 2.1, math.hypot(1.3, 1.2), math.hypot(1.3, 0.4), 0.3], {6: (0.6, 0.8)}),
        # inside the cylinder
        ((2.45, 2.5), [2.45, 1.15, 2.5, 2.5, math.hypot(1.05, 0.8), math.hypot(1.05, 0.8), -0.15], {6: (1.0, 0.0)}),
        # near the top-left corner of the arena
        (
            (0.3, 4.6),
            [0.3, 3.3, 4.6, 0.4, math.hypot(0.7, 2.9), math.hypot(0.7, 0.9), math.hypot(2.1, 2.1) - 0.2],
            {0: (1.0, 0.0), 1: (-1.0, 0.0), 2: (0.0, 1.0), 3: (0.0, -1.0)},
        ),
    ],
    ids=["box-face", "box-corner", "inside-box", "disc", "inside-disc", "walls"],
)
def test_signed_distances_are_exact(
    point: tuple[float, float], expected: list[float], normals: dict[int, tuple[float, float]]
) -> None:
    geo = Geometry.from_config(load_task("4p2e3o"))
    dist, normal = signed_distances(np.array([point]), geo)
    assert dist[0] == pytest.approx(expected, abs=1e-12)
    for k, n in normals.items():
        assert normal[0, k] == pytest.approx(n, abs=1e-12)
    d, n = nearest_obstacle(np.array(point), geo)
    k = int(np.argmin(expected))
    assert float(d) == pytest.approx(expected[k], abs=1e-12)
    assert np.linalg.norm(n) == pytest.approx(1.0)


def test_signed_distances_keep_batch_shape() -> None:
    geo = Geometry.from_config(load_task("4p2e5o"))
    points = np.random.default_rng(0).uniform(0, 3.6, size=(3, 5, 2))
    dist, normal = signed_distances(points, geo)
    assert dist.shape == (3, 5, 9) and normal.shape == (3, 5, 9, 2)
    assert dist[..., 0] == pytest.approx(points[..., 0])
    np.testing.assert_array_equal(obstacle_distances(points, geo), dist)


# ------------------------------------------------------------------- capture
@pytest.mark.parametrize(("gap", "caught"), [(0.229, True), (0.24, False)], ids=["ends-at-0.199", "ends-at-0.21"])
def test_capture_when_a_pursuer_ends_within_0_2_m(gap: float, caught: bool) -> None:
    env = make(still_evaders())
    pursuers = [(1.0, 3.5 - gap, UP), (2.0, 0.5, UP), (2.6, 0.5, UP), (3.2, 0.5, UP)]
    evaders = [(1.0, 3.5), (3.0, 4.6)]
    place(env, pursuers, evaders)
    _, reward, done, info = step(env)
    assert info["captured_now"][0].tolist() == [caught, False]
    assert env.state.captured[0].tolist() == [caught, False]
    assert not done[0]
    expected = 10.0 * caught + shaping(evaders, [p[:2] for p in pursuers], up(pursuers))
    assert reward[0] == pytest.approx(np.full(4, expected), abs=1e-5)


# ------------------------------------------------------------------- collision
PARKED = [(2.0, 0.5, UP), (2.6, 0.5, UP), (3.2, 0.5, UP)]


@pytest.mark.parametrize(
    ("pursuers", "collided"),
    [
        ([(0.5, 3.0, UP), (0.69, 3.0, UP), *PARKED[1:]], [True, True, False, False]),
        ([(0.5, 3.0, UP), (0.71, 3.0, UP), *PARKED[1:]], [False] * 4),
        ([(0.91, 1.47, UP), *PARKED], [True, False, False, False]),
        ([(0.89, 1.47, UP), *PARKED], [False] * 4),
        ([(1.454, 1.742, UP), *PARKED], [True, False, False, False]),
        ([(1.466, 1.758, UP), *PARKED], [False] * 4),
        ([(2.69, 2.47, UP), *PARKED], [True, False, False, False]),
        ([(2.71, 2.47, UP), *PARKED], [False] * 4),
        ([(0.09, 2.97, UP), *PARKED], [True, False, False, False]),
        ([(0.11, 2.97, UP), *PARKED], [False] * 4),
        ([(0.5, 0.12, DOWN), *PARKED], [True, False, False, False]),
        ([(0.5, 0.14, DOWN), *PARKED], [False] * 4),
    ],
    ids=[
        "pursuers-0.19-apart",
        "pursuers-0.21-apart",
        "box-face-0.09",
        "box-face-0.11",
        "box-corner-0.09",
        "box-corner-0.11",
        "disc-0.09",
        "disc-0.11",
        "left-wall-0.09",
        "left-wall-0.11",
        "bottom-wall-0.09",
        "bottom-wall-0.11",
    ],
)
def test_collision_below_threshold_only(pursuers: list[tuple[float, float, float]], collided: list[bool]) -> None:
    env = make("4p2e3o")
    place(env, pursuers, [(2.0, 4.5), (3.0, 4.5)])
    _, reward, done, info = step(env)
    assert info["collided"][0].tolist() == collided
    assert bool(done[0]) == any(collided)
    assert info["done_reason"][0] == (COLLISION if any(collided) else RUNNING)
    assert (reward[0, 0] < -9.0) == any(collided)


# ---------------------------------------------------------------------- reward
EVADERS = [(0.5, 4.0), (3.0, 4.0)]


def test_shaping_rewards_the_drop_in_nearest_pursuer_distance() -> None:
    env = make(still_evaders())
    # p0 flies straight at evader 0 (1.0 m -> 0.97 m); p3 flies sideways under evader 1
    pursuers = [(0.5, 3.0, UP), (1.5, 1.0, UP), (2.2, 1.0, UP), (3.0, 3.0, RIGHT)]
    place(env, pursuers, EVADERS)
    _, reward, done, _ = step(env)
    expected = (0.03 + (1.0 - math.hypot(0.03, 1.0))) / 0.3
    assert expected == pytest.approx(
        shaping(EVADERS, [p[:2] for p in pursuers], [(0.5, 3.03), (1.5, 1.03), (2.2, 1.03), (3.03, 3.0)])
    )
    assert not done[0]
    assert reward[0] == pytest.approx(np.full(4, expected), abs=1e-6)
    assert reward.dtype == np.float32


def test_capture_pays_10_plus_the_captured_evaders_last_approach() -> None:
    env = make(still_evaders())
    pursuers = [(0.5, 3.0, UP), (1.5, 1.0, UP), (2.2, 1.0, UP), (3.0, 3.0, RIGHT)]
    evaders = [(0.5, 3.229), (3.0, 4.0)]
    place(env, pursuers, evaders)
    _, reward, _, info = step(env)
    assert info["captured_now"][0].tolist() == [True, False]
    expected = 10.0 + (0.03 + (1.0 - math.hypot(0.03, 1.0))) / 0.3
    assert reward[0, 0] == pytest.approx(expected, abs=1e-5)


def test_already_captured_evaders_earn_no_shaping() -> None:
    env = make(still_evaders())
    pursuers = [(0.5, 3.0, DOWN), (1.5, 1.0, UP), (2.2, 1.0, UP), (3.0, 3.0, UP)]
    place(env, pursuers, EVADERS, captured=[True, False])
    _, reward, _, info = step(env)
    assert not info["captured_now"][0].any()
    assert reward[0, 0] == pytest.approx(0.03 / 0.3, abs=1e-6)


def test_collision_costs_10_once_per_step() -> None:
    env = make(still_evaders())
    # p1 and p2 are 0.19 m apart and both end 0.09 m below the bar (y 2.45): three collisions
    pursuers = [(0.5, 3.0, UP), (1.5, 2.33, UP), (1.69, 2.33, UP), (3.0, 3.0, UP)]
    place(env, pursuers, EVADERS)
    _, reward, done, info = step(env)
    assert info["collided"][0].tolist() == [False, True, True, False]
    assert done[0] and info["done_reason"][0] == COLLISION
    assert reward[0, 0] == pytest.approx(-10.0 + 2 * 0.03 / 0.3, abs=1e-5)


@pytest.mark.parametrize("enabled", [False, True], ids=["disabled", "enabled"])
def test_proximity_penalty_bands(enabled: bool) -> None:
    cfg = still_evaders(**{"task.reward.proximity.enabled": enabled})
    env = make(cfg)
    # neighbours 0.22 (band -1), 0.27 (band -0.1) and 0.35 (band -0.01) apart; other pairs >= 0.49
    pursuers = [(0.5, 0.5, UP), (0.72, 0.5, UP), (0.99, 0.5, UP), (1.34, 0.5, UP)]
    place(env, pursuers, EVADERS)
    _, reward, done, _ = step(env)
    assert not done[0]
    expected = shaping(EVADERS, [p[:2] for p in pursuers], up(pursuers)) + (-1.11 if enabled else 0.0)
    assert reward[0, 0] == pytest.approx(expected, abs=1e-5)


# ----------------------------------------------------------------- observation
# Pursuer 0 at (1.8, 2.0), 0.45 m below the bar of 4p2e1o (x 1.0-2.5, y 2.45-2.55).
OBS_P0 = (1.8, 2.0)


def at(r: float, degrees: float) -> tuple[float, float]:
    return OBS_P0[0] + r * math.cos(math.radians(degrees)), OBS_P0[1] + r * math.sin(math.radians(degrees))


OBS_EVADERS = [at(1.99, 120), at(2.01, 60)]
OBS_TEAMMATES = [at(1.99, -45), at(2.01, -135), at(1.0, -90)]


@pytest.mark.parametrize(
    ("heading", "expected"),
    [
        (
            UP,
            [
                [1, 1.99 / 5, 0.5, R3],  # evader 0, bearing +30 deg
                [0, 0, 0, 0],  # evader 1 at 2.01 m: masked
                [1, 0.45 / 5, 0.0, 1.0],  # the bar straight ahead
                [1, 1.99 / 5, -R2, -R2],  # teammate 1, bearing -135 deg
                [0, 0, 0, 0],  # teammate 2 at 2.01 m: masked
                [1, 1.0 / 5, 0.0, -1.0],  # teammate 3 straight behind
            ],
        ),
        (
            RIGHT,
            [
                [1, 1.99 / 5, R3, -0.5],  # bearing +120 deg
                [0, 0, 0, 0],
                [1, 0.45 / 5, 1.0, 0.0],  # bar on the left
                [1, 1.99 / 5, -R2, R2],  # bearing -45 deg
                [0, 0, 0, 0],
                [1, 1.0 / 5, -1.0, 0.0],  # on the right
            ],
        ),
    ],
    ids=["facing-up", "facing-right"],
)
def test_observation_is_egocentric_and_masks_beyond_2_m(heading: float, expected: list[list[float]]) -> None:
    env = make("4p2e1o")
    place(env, [(*OBS_P0, heading), *[(x, y, UP) for x, y in OBS_TEAMMATES]], OBS_EVADERS)
    obs = env.observe()
    assert obs.shape == (1, 4, 24) and obs.dtype == np.float32
    assert obs[0, 0].reshape(6, 4) == pytest.approx(np.array(expected, dtype=float), abs=1e-6)


def test_captured_evader_is_masked_even_when_close() -> None:
    env = make("4p2e1o")
    place(env, [(*OBS_P0, UP), *[(x, y, UP) for x, y in OBS_TEAMMATES]], OBS_EVADERS, captured=[True, False])
    blocks = env.observe()[0, 0].reshape(6, 4)
    assert blocks[0].tolist() == [0, 0, 0, 0]
    assert blocks[1].tolist() == [0, 0, 0, 0]
    assert blocks[3, 0] == 1


def test_observations_stay_within_the_declared_bound_over_random_play() -> None:
    env = make("4p3e5o", num_envs=8, seed=1)
    rng = np.random.default_rng(0)
    for _ in range(100):
        obs, _, _, info = env.step(rng.uniform(-1, 1, size=(8, 4)))
        assert np.abs(obs).max() <= 1.5 and np.abs(info["final_obs"]).max() <= 1.5
        masks = obs.reshape(8, 4, 7, 4)[..., 0]
        assert set(np.unique(masks)) <= {0.0, 1.0}


# ----------------------------------------------------------------- episode end
def test_capturing_the_last_evader_ends_the_episode_as_success() -> None:
    env = make(still_evaders())
    pursuers = [(0.5, 3.0, UP), (1.5, 1.0, UP), (2.2, 1.0, UP), (3.0, 3.0, UP)]
    place(env, pursuers, [(0.5, 4.0), (3.0, 3.229)], captured=[True, False])
    env.state.t[0], env.state.ep_return[0] = 41, 5.0
    _, reward, done, info = step(env)
    assert done[0] and info["done_reason"][0] == CAPTURED
    assert info["episode_length"][0] == 42
    assert info["episode_captured"][0] == 2 and not info["episode_collided"][0]
    assert info["episode_return"][0] == pytest.approx(5.0 + 10.0 + 0.03 / 0.3)
    assert info["episode_return"][0] == pytest.approx(5.0 + reward[0, 0])
    assert env.final_state is not None and env.final_state.captured[0].all()
    assert_fresh_episode(env, 0)


def test_collision_ends_the_episode_as_failure() -> None:
    env = make(still_evaders())
    place(env, [(0.5, 3.0, UP), (0.69, 3.0, UP), *PARKED[1:]], EVADERS)
    _, _, done, info = step(env)
    assert done[0] and info["done_reason"][0] == COLLISION
    assert info["episode_collided"][0] and info["episode_length"][0] == 1
    assert_fresh_episode(env, 0)


def test_collision_does_not_end_the_episode_when_configured_so() -> None:
    env = make(still_evaders(**{"task.collision_ends_episode": False}))
    pursuers = [(0.5, 3.0, UP), (0.69, 3.0, UP), *PARKED[1:]]
    place(env, pursuers, EVADERS)
    _, reward, done, info = step(env)
    assert not done[0] and info["done_reason"][0] == RUNNING
    assert info["collided"][0].tolist() == [True, True, False, False]
    assert info["episode_collided"][0] and env.state.ep_collided[0] and env.state.t[0] == 1
    expected = -10.0 + shaping(EVADERS, [p[:2] for p in pursuers], up(pursuers))
    assert reward[0, 0] == pytest.approx(expected, abs=1e-5)


def test_timeout_at_task_horizon() -> None:
    env = make(modified("4p2e1o", {"task.task_horizon": 5}), num_envs=6)
    total = np.zeros(6)
    for t in range(1, 6):
        _, reward, done, info = step(env)  # straight up from the spawn: no capture, no collision
        total += reward[:, 0]
        assert done.tolist() == [t == 5] * 6
    assert (info["done_reason"] == TIMEOUT).all()
    assert (info["episode_length"] == 5).all()
    assert info["episode_return"] == pytest.approx(total, abs=1e-5)
    assert (env.state.t == 0).all()


def test_episode_return_and_length_sum_the_steps_across_auto_resets() -> None:
    env = make(modified("4p2e5o", {"task.task_horizon": 30}), num_envs=8, seed=3)
    rng = np.random.default_rng(0)
    total, length, reasons = np.zeros(8), np.zeros(8, dtype=int), set()
    for _ in range(150):
        before = env.state.pos.copy()
        obs, reward, done, info = env.step(rng.uniform(-1, 1, size=(8, 4)))
        total += reward[:, 0]
        length += 1
        for b in np.flatnonzero(done):
            assert info["episode_return"][b] == pytest.approx(total[b], abs=1e-4)
            assert info["episode_length"][b] == length[b]
            reasons.add(int(info["done_reason"][b]))
            assert_fresh_episode(env, b)
            assert np.array_equal(obs[b], env.observe()[b])  # the new episode's first observation
            assert not np.array_equal(obs[b], info["final_obs"][b])
            assert not np.allclose(env.state.pos[b], before[b])
            total[b], length[b] = 0.0, 0
        assert np.array_equal(env.state.t, length)
    assert {COLLISION, TIMEOUT} <= reasons


def assert_fresh_episode(env: BatchedPursuit, b: int) -> None:
    """Env ``b`` restarted: step 0, nothing captured, drones inside the SPEC spawn regions."""
    s = env.state
    assert s.t[b] == 0 and s.ep_return[b] == 0 and not s.ep_collided[b] and not s.captured[b].any()
    assert np.array_equal(s.prev_dist[b], env._evader_distances(s.pos[b : b + 1])[0])
    assert_spec_spawn(s.pos[b : b + 1], s.heading[b : b + 1], env.num_p, env.num_e)


def assert_spec_spawn(pos: np.ndarray, heading: np.ndarray, num_p: int, num_e: int) -> None:
    px, py = pos[:, :num_p, 0], pos[:, :num_p, 1]
    offset = 0.6 * np.arange(num_p)
    assert ((px - offset >= 0.2) & (px - offset <= 1.2)).all()
    assert ((py >= 0.2) & (py <= 0.8)).all()
    ex, ey = pos[:, num_p:, 0], pos[:, num_p:, 1]
    base = ex - 0.4 * np.arange(num_e)
    assert base == pytest.approx(np.repeat(base[:, :1], num_e, 1), abs=1e-12)  # one shared draw
    assert ((base >= 0.2) & (base <= 2.6)).all()
    assert ((ey >= 4.2) & (ey <= 4.8)).all()
    assert (heading == UP).all()
    i, j = np.triu_indices(num_p, 1)
    assert (np.hypot(px[:, i] - px[:, j], py[:, i] - py[:, j]) >= 0.2).all()


# ----------------------------------------------------------------- spawn, seeds
@pytest.mark.parametrize("task", TASK_NAMES)
def test_spawns_fill_the_spec_regions_with_headings_up_and_pursuers_apart(task: str) -> None:
    env = make(task, num_envs=3000, seed=11)
    P, E = env.num_p, env.num_e
    assert_spec_spawn(env.state.pos, env.state.heading, P, E)
    px = env.state.pos[:, :P, 0] - 0.6 * np.arange(P)
    ey = env.state.pos[:, P:, 1]
    # the draws cover their whole ranges
    assert px.min() < 0.25 and px.max() > 1.15
    assert ey.min() < 4.25 and ey.max() > 4.75
    base = env.state.pos[:, P, 0]
    assert base.min() < 0.3 and base.max() > 2.5


def test_fixed_respawn_puts_every_drone_mid_region() -> None:
    env = make(modified("4p3e5o", {"players.random_respawn": False}), num_envs=3)
    expected_p = [(0.7 + 0.6 * i, 0.5) for i in range(4)]
    expected_e = [(1.4 + 0.4 * j, 4.5) for j in range(3)]
    for b in range(3):
        assert env.state.pos[b] == pytest.approx(np.array(expected_p + expected_e), abs=1e-12)


def rollout(env: BatchedPursuit, steps: int, action_seed: int = 0) -> list[tuple[np.ndarray, ...]]:
    rng = np.random.default_rng(action_seed)
    trace = []
    for _ in range(steps):
        obs, reward, done, info = env.step(rng.uniform(-1.5, 1.5, size=(env.num_envs, env.num_p)))
        trace.append((obs, reward, done, info["done_reason"], env.state.pos.copy(), env.state.heading.copy()))
    return trace


def test_same_seed_and_actions_give_identical_trajectories() -> None:
    a = make("4p2e5o", num_envs=4, seed=7)
    b = make("4p2e5o", num_envs=4, seed=7)
    assert np.array_equal(a.observe(), b.observe())
    ends = 0
    for step_a, step_b in zip(rollout(a, 300), rollout(b, 300), strict=True):
        for x, y in zip(step_a, step_b, strict=True):
            assert np.array_equal(x, y)
        ends += int(step_a[2].sum())
    assert ends > 0  # auto-resets are covered too


def test_different_seeds_give_different_trajectories() -> None:
    a = make("4p2e5o", num_envs=4, seed=7)
    b = make("4p2e5o", num_envs=4, seed=8)
    assert not np.array_equal(a.state.pos, b.state.pos)
    trace_a, trace_b = rollout(a, 300), rollout(b, 300)
    assert not all(np.array_equal(x[4], y[4]) for x, y in zip(trace_a, trace_b, strict=True))


def test_reset_with_a_seed_restarts_the_same_trajectory() -> None:
    env = make("4p2e3o", num_envs=2, seed=0)
    first = (env.reset(seed=5), *rollout(env, 50))
    second = (env.reset(seed=5), *rollout(env, 50))
    assert np.array_equal(first[0], second[0])
    for x, y in zip(first[1:], second[1:], strict=True):
        assert all(np.array_equal(u, v) for u, v in zip(x, y, strict=True))


def test_step_rejects_actions_of_the_wrong_shape_and_steps_before_reset() -> None:
    env = BatchedPursuit("4p2e1o", num_envs=2, seed=0)
    with pytest.raises(RuntimeError):
        env.step(np.zeros((2, 4)))
    env.reset()
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros((4,)))


def test_info_names_who_hit_what():
    # 0 and 1 fly side by side 0.1 m apart (< 0.2); 2 flies left into the wall (0.12 -> 0.09 m
    # from it, < 0.1); 3 flies up in the open.
    env = make(still_evaders())
    place(env, [(1.0, 1.0, RIGHT), (1.0, 1.1, RIGHT), (0.12, 3.0, math.pi), (3.0, 1.0, UP)], [(2.0, 4.5), (3.0, 4.5)])
    _, _, done, info = env.step(np.zeros((1, 4)))
    assert done[0] and info["done_reason"][0] == COLLISION
    np.testing.assert_array_equal(info["collided"][0], [True, True, True, False])
    hit = {tuple(p) for p, h in zip(env.pairs, info["hit_pairs"][0], strict=True) if h}
    assert hit == {(0, 1)}
    assert [env.geometry.names[k] if k >= 0 else None for k in info["hit_obstacle"][0]] == [
        None,
        None,
        "wall_left",
        None,
    ]
