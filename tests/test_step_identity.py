"""The simulator's step is bit-identical to the recorded one: 1,500 steps on each of the four tasks.

Every output of every step (observations, rewards, dones, every info array) and the final
state, in the fields it had then (``RECORDED_STATE``), are hashed; the digests were recorded
from the step before its speed-up (issue 26, commit 081bc2c). A faster step must reproduce
them to the bit. The pursuers chase the
nearest evader with noise (so captures, collisions, timeouts and auto-resets all happen);
the "-free" cases enable the proximity bands, let collisions go on and end episodes
after 150 steps, so pursuers capture every evader and episodes time out.

Transcendental functions (sin, cos, exp, arctan2) may round differently on another CPU or
numpy build, so the digests are checked where they were recorded (numpy's version and SIMD
features below) and elsewhere the test only checks that two runs agree.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from atdrone.config import TASK_NAMES, TaskConfig, load_task
from atdrone.envs.core import BatchedPursuit
from atdrone.envs.kinematics import turn_towards

STEPS, NUM_ENVS = 1500, 24
RECORDED_ON = ("2.4.6", ("X86_V3", "X86_V4", "AVX512_ICL"))
# the state's fields when the digests were recorded; the open-teaming fields added since (ev_kind, ev_pick,
# ev_slot, ev_step, present) are not in them (in these cases no event happens and every slot is present)
RECORDED_STATE = (
    "captured",
    "ep_collided",
    "ep_return",
    "episode",
    "heading",
    "key",
    "pos",
    "prev_dist",
    "t",
    "wander_heading",
    "wander_left",
)
DIGESTS = {
    "4p2e1o": "58f89a9da9830de154dcd68cc32eb1ecedee81767830e3c3a1c2d7278fed0271",
    "4p2e3o": "39ca61b267930ba34b86e2650c99351a3e1185eda7bbdc9373dca7cb6602c939",
    "4p2e5o": "399f633d359d67cf77b5b27242f17cd4fcb81086327fdcb3056f427383830c1b",
    "4p3e5o": "906863fd218e27b9b8f6043d54475864c43b655d6262794a193235f35ea580f1",
    "4p2e1o-free": "90e78fcf144678af9f221e6c8454826182044f47223796e170e2e2981b0325e6",
    "4p3e5o-free": "0da5be5dc743635d1bcb109cb629f3d7bccda1c47d96953c3669c1b042bdd4d2",
}


def _case(case: str) -> str | TaskConfig:
    """The task of a case: a paper task, or ``<task>-free`` (see the module docstring)."""
    if not case.endswith("-free"):
        return case
    doc = load_task(case.removesuffix("-free")).to_dict()
    doc["task"]["collision_ends_episode"] = False
    doc["task"]["task_horizon"] = 150
    doc["task"]["reward"]["proximity"]["enabled"] = True
    return load_task(doc)


def trajectory_digest(task: str | TaskConfig, steps: int = STEPS, num_envs: int = NUM_ENVS) -> str:
    """sha256 of every output of ``steps`` steps of a noisy chase, and of the final state."""
    env = BatchedPursuit(task, num_envs=num_envs, seed=7)
    h = hashlib.sha256(env.reset().tobytes())
    rng = np.random.default_rng(3)
    P, noise_scale = env.num_p, np.linspace(0.0, 0.6, num_envs)[:, None]
    for _ in range(steps):
        s = env.state
        rel = s.pos[:, None, P:] - s.pos[:, :P, None]  # (B, P, E, 2)
        dist = np.where(s.captured[:, None], np.inf, np.hypot(rel[..., 0], rel[..., 1]))
        k = dist.argmin(-1)[..., None]
        bearing = np.arctan2(
            np.take_along_axis(rel[..., 1], k, -1)[..., 0], np.take_along_axis(rel[..., 0], k, -1)[..., 0]
        )
        noise = rng.normal(0.0, 0.6, (num_envs, P)) * noise_scale  # row 0 chases greedily, the last row wildly
        actions = turn_towards(s.heading[:, :P], bearing) + noise
        actions[rng.random((num_envs, P)) < 0.01] = np.nan
        obs, rewards, done, info = env.step(actions)
        for arr in (obs, rewards, done, *(np.asarray(info[k]) for k in sorted(info))):
            h.update(arr.tobytes())
    for name in RECORDED_STATE:
        h.update(np.asarray(getattr(env.state, name)).tobytes())
    return h.hexdigest()


def _recorded_here() -> bool:
    """numpy's version and the SIMD targets it dispatches to on this CPU are those the digests were recorded on."""
    from numpy._core import _multiarray_umath as umath

    features = getattr(umath, "__cpu_features__", {})
    targets = tuple(t for t in getattr(umath, "__cpu_dispatch__", ()) if features.get(t))
    return (np.__version__, targets) == RECORDED_ON


@pytest.mark.parametrize("case", list(DIGESTS))
def test_step_reproduces_the_recorded_trajectory_bit_for_bit(case: str) -> None:
    task = _case(case)
    digest = trajectory_digest(task)
    if _recorded_here():
        assert digest == DIGESTS[case]
    else:
        assert digest == trajectory_digest(task)


def test_the_cases_cover_the_four_tasks() -> None:
    assert set(TASK_NAMES) <= set(DIGESTS)


def test_the_recorded_state_fields_are_the_states_own() -> None:
    env = BatchedPursuit("4p2e1o", num_envs=2, seed=0)
    assert set(RECORDED_STATE) <= set(env.state.__dict__)


@pytest.mark.parametrize("n", [1, 2, 4, 7, 8, 9, 15, 16, 19, 40])
def test_last_axis_sum_rounds_as_numpy_sums_a_short_last_axis(n: int) -> None:
    """Summing (n, M) rows gives the bits of numpy's sum over a contiguous (M, n) last axis: terms of mixed
    magnitude (where the order of additions shows) and rows of signed zeros (numpy starts from +0.0)."""
    from atdrone.envs.evaders import last_axis_sum

    rng = np.random.default_rng(n)
    terms = rng.standard_normal((n, 4096)) * 10.0 ** rng.integers(-8, 8, (n, 4096))
    terms[:, :8] = -0.0
    want = np.ascontiguousarray(np.moveaxis(terms, 0, -1)).sum(-1)
    got = last_axis_sum(terms)
    assert got.tobytes() == want.tobytes()
    if n >= 8:  # rows added one after another (terms.sum(0)) round otherwise: the order is what is pinned
        assert terms.sum(0).tobytes() != want.tobytes()


def test_first_argmin_is_numpys_argmin_over_rows_ties_to_the_first() -> None:
    from atdrone.envs.geometry import first_argmin

    values = np.random.default_rng(0).integers(0, 3, (5, 1000)).astype(float)  # many ties
    np.testing.assert_array_equal(first_argmin(values), values.argmin(0))
    np.testing.assert_array_equal(first_argmin(values, values.min(0)), values.argmin(0))
