"""Recorded episodes: a policy (and optionally zoo partners) plays one episode, drawn frame by frame.

The drawing is :mod:`atdrone.envs.render`; this module adds who plays (a policy, a
:class:`~atdrone.teams.match.Match` with partners), so it sits beside the teams.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from atdrone.config import TaskConfig
from atdrone.envs.core import DONE_REASONS, RUNNING, BatchedPursuit
from atdrone.envs.render import FrameRenderer
from atdrone.envs.single import Stepper
from atdrone.policies.base import DroneBatch
from atdrone.policies.base import Policy as DronePolicy
from atdrone.policies.rules import chase_nearest
from atdrone.policies.zoo import Zoo
from atdrone.teams.match import Match

Steer = Callable[[np.ndarray, BatchedPursuit], np.ndarray]  # obs (B, n, obs_dim), core -> actions (B, n)


def record_episode(
    task: TaskConfig | str,
    seed: int | None = 0,
    policy: Steer | DronePolicy | None = None,
    max_steps: int | None = None,
    frame_every: int = 1,
    trails: bool = True,
    title: str | None = None,
    partners: Zoo | Sequence[DronePolicy] | None = None,
) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Run one episode of ``BatchedPursuit(task, num_envs=1, seed)`` and draw it.

    ``policy``: a :class:`~atdrone.policies.Policy` or a function ``(obs, core) ->
    actions`` over the drones it steers; default :func:`~atdrone.policies.rules.chase_nearest`. Without
    ``partners`` it steers every pursuer (obs (1, num_p, obs_dim), actions (1, num_p)).
    With ``partners`` (a zoo or partner policies) a :class:`~atdrone.teams.match.Match` on
    the core gives it the task's num_ctrl learner slots (obs (1, num_ctrl, obs_dim),
    actions (1, num_ctrl)) and the partners drawn for the episode fill the others;
    they are drawn green. The episode runs until it ends (captured, collision,
    timeout) or for ``max_steps`` steps (outcome "running"). Every ``frame_every``-th
    step is drawn, plus the first and the last (the pre-reset final state).
    Returns the frames and a summary: task, seed, steps, outcome, return, captured,
    num_e, and with partners the team (learner_slots, partner_slots, partners).
    """
    if frame_every < 1:
        raise ValueError(f"frame_every must be >= 1, got {frame_every}")
    core = BatchedPursuit(task, num_envs=1, seed=seed)
    match: Match | None = None
    stepper: Stepper = core
    if partners is not None:
        stepper = match = Match(core, partners, seed=seed)
    act = _actor(policy, core, match)
    obs = stepper.reset(seed=seed)
    name = title if title is not None else f"{core.cfg.name}  seed {seed}"
    team: dict[str, list[Any]] = {}
    if match is not None:
        team = {k: v[0].tolist() for k, v in match.team().items() if k != "partner_members"}
        if title is None:
            name += f"  partners: {', '.join(team['partners'])}"
    renderer = FrameRenderer(core, 0, partner_slots=team.get("partner_slots", ()))
    history = [core.state.pos[0].copy()]
    frames = [renderer.draw(title=name)]
    reason, step, final = RUNNING, 0, core.state
    limit = core.cfg.task.task_horizon if max_steps is None else max_steps
    try:
        while step < limit:
            obs, _, done, info = stepper.step(np.asarray(act(obs), dtype=np.float64).reshape(1, -1))
            step += 1
            if done[0]:
                assert core.final_state is not None
                final, reason = core.final_state, int(info["done_reason"][0])
            else:
                final = core.state
            history.append(final.pos[0].copy())
            if done[0] or step % frame_every == 0 or step == limit:
                trail = np.asarray(history) if trails else None
                frames.append(renderer.draw(final, title=name, trails=trail))
            if done[0]:
                break
    finally:
        renderer.close()
    summary: dict[str, Any] = {
        "task": core.cfg.name,
        "seed": seed,
        "steps": int(final.t[0]),
        "outcome": DONE_REASONS[reason],
        "return": float(final.ep_return[0]),
        "captured": int(final.captured[0].sum()),
        "num_e": core.num_e,
    }
    if team:
        summary["team"] = team
    return frames, summary


def _actor(
    policy: Steer | DronePolicy | None, core: BatchedPursuit, match: Match | None
) -> Callable[[np.ndarray], np.ndarray]:
    """``obs -> actions`` of the drones ``policy`` steers: every pursuer, or the match's learners."""
    if policy is None:
        return lambda obs: chase_nearest(obs, core.num_e)
    if isinstance(policy, DronePolicy):
        drones = policy
        drones.reset(np.ones(1, dtype=bool))
        if match is not None:
            learners = match
            return lambda obs: drones.act(learners.learner_batch())
        return lambda obs: drones.act(DroneBatch.all_slots(obs, core.poses()))
    steer = policy
    return lambda obs: steer(obs, core)


def showcase(
    task: TaskConfig | str,
    policy: DronePolicy,
    partners: Zoo | None,
    seed: int = 0,
    tries: int = 8,
    frame_every: int = 5,
) -> tuple[list[np.ndarray], dict[str, Any]]:
    """A whole, representative episode of ``policy`` with ``partners``, drawn with a caption.

    Plays seeds ``seed, seed + 1, ...`` (up to ``tries``, each to its end) and keeps the
    first that captures every evader, else the longest; then draws that episode whole
    (every ``frame_every``-th step, the first and the last). The caption (each frame's
    title, and ``summary["caption"]``) names the member, its partners and the outcome.
    """
    best: dict[str, Any] | None = None
    for s in range(seed, seed + max(1, tries)):
        _, summary = record_episode(task, s, policy, frame_every=10**9, trails=False, partners=partners)
        if best is None or summary["steps"] > best["steps"] or summary["outcome"] == "captured":
            best = summary
        if summary["outcome"] == "captured":
            break
    assert best is not None
    mates = ", ".join(best.get("team", {}).get("partners", [])) or "itself"
    caption = (
        f"{getattr(policy, 'name', 'policy')} + {mates}: {best['outcome']} in {best['steps']} steps "
        f"({best['captured']}/{best['num_e']} caught), seed {best['seed']}"
    )
    frames, summary = record_episode(
        task, best["seed"], policy, frame_every=frame_every, title=caption, partners=partners
    )
    summary["caption"] = caption
    return frames, summary
