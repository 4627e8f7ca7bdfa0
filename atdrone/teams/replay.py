"""Recorded episodes: a policy (and optionally zoo partners) plays one episode, drawn frame by frame.

The drawing is :mod:`atdrone.envs.render`; this module adds who plays (a policy, a
:class:`~atdrone.teams.match.Match` with partners), so it sits beside the teams. An
episode is played first (:func:`play_episode` keeps every state) and drawn after
(:func:`draw_episode`), so what is shown is exactly what was played.
"""

from __future__ import annotations

import os
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from atdrone.config import TaskConfig
from atdrone.envs.core import DONE_REASONS, RUNNING, BatchedPursuit, PursuitState
from atdrone.envs.render import FrameRenderer, save_gif
from atdrone.envs.single import Stepper
from atdrone.policies.base import DroneBatch
from atdrone.policies.base import Policy as DronePolicy
from atdrone.policies.rules import chase_nearest
from atdrone.policies.zoo import Zoo, load_zoo
from atdrone.teams.match import Match

Steer = Callable[[np.ndarray, BatchedPursuit], np.ndarray]  # obs (B, n, obs_dim), core -> actions (B, n)
Partners = Zoo | Sequence[DronePolicy]


@dataclass
class Episode:
    """One played episode: its core, the states after the reset and after every step (the last one before
    any auto-reset), its summary (see :func:`record_episode`) and the pursuer slots of the partners."""

    core: BatchedPursuit
    states: list[PursuitState]
    summary: dict[str, Any]
    partner_slots: list[int] = field(default_factory=list)


def play_episode(
    task: TaskConfig | str,
    seed: int | None = 0,
    policy: Steer | DronePolicy | None = None,
    max_steps: int | None = None,
    partners: Partners | None = None,
) -> Episode:
    """Play one episode of ``BatchedPursuit(task, num_envs=1, seed)`` to its end (or ``max_steps``), keeping each state.

    Who steers what is described in :func:`record_episode`.
    """
    core = BatchedPursuit(task, num_envs=1, seed=seed)
    match = Match(core, partners, seed=seed) if partners is not None else None
    stepper: Stepper = match if match is not None else core
    act = _actor(policy, core, match)
    obs = stepper.reset(seed=seed)
    team = {k: v[0].tolist() for k, v in match.team().items() if k != "partner_members"} if match else {}
    states, reason = [core.state.copy()], RUNNING
    limit = core.cfg.task.task_horizon if max_steps is None else max_steps
    while len(states) <= limit and reason == RUNNING:
        obs, _, done, info = stepper.step(np.asarray(act(obs), dtype=np.float64).reshape(1, -1))
        state = core.state
        if done[0]:
            assert core.final_state is not None
            state, reason = core.final_state, int(info["done_reason"][0])
        states.append(state.copy())
    final = states[-1]
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
        summary["team"] = team  # drawn at the reset: an auto-reset at the end draws the next episode's
    return Episode(core, states, summary, team.get("partner_slots", []))


def frame_steps(steps: int, frame_every: int) -> list[int]:
    """The steps drawn of an episode of ``steps`` steps: 0, every ``frame_every``-th, and the last.

    That is ``ceil(steps / frame_every) + 1`` frames, so the whole episode is shown.
    """
    if frame_every < 1:
        raise ValueError(f"frame_every must be >= 1, got {frame_every}")
    return sorted({*range(0, steps, frame_every), steps})


def draw_episode(
    episode: Episode, frame_every: int = 1, trails: bool = True, title: str | None = None, member: str | None = None
) -> list[np.ndarray]:
    """The frames of ``episode`` at :func:`frame_steps`; ``title`` on each (default: task, seed, partners).

    The legend names ``member`` for the drones it flies (the learner slots, or every
    pursuer without partners) and, in a team, the zoo partners.
    """
    steps = frame_steps(len(episode.states) - 1, frame_every)
    if title is None:
        title = f"{episode.summary['task']}  seed {episode.summary['seed']}"
        if "team" in episode.summary:
            title += f"  partners: {', '.join(episode.summary['team']['partners'])}"
    track = np.stack([s.pos[0] for s in episode.states])
    renderer = FrameRenderer(episode.core, 0, partner_slots=episode.partner_slots, member=member)
    try:
        return [
            renderer.draw(episode.states[i], title=title, trails=track[: i + 1] if trails and i else None)
            for i in steps
        ]
    finally:
        renderer.close()


def record_episode(
    task: TaskConfig | str,
    seed: int | None = 0,
    policy: Steer | DronePolicy | None = None,
    max_steps: int | None = None,
    frame_every: int = 1,
    trails: bool = True,
    title: str | None = None,
    partners: Partners | None = None,
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
    frame_steps(0, frame_every)  # a bad frame_every fails before the episode is played
    episode = play_episode(task, seed, policy, max_steps, partners)
    member = member_name(policy) if policy is not None else "chase nearest"
    if title is None:
        title = caption(member, episode.summary)
    return draw_episode(episode, frame_every, trails, title, member), episode.summary


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


# ------------------------------------------------------------------ showcase
def representative_episode(
    task: TaskConfig | str, policy: Steer | DronePolicy, partners: Partners | None, seed: int = 0, tries: int = 8
) -> Episode:
    """An episode that shows how ``policy`` usually does, not a lucky seed.

    Seeds ``seed, seed + 1, ...`` (``tries`` of them) are each played whole; the outcome
    most of them ended with is kept (a tie goes to the earlier seed's outcome), and of
    those episodes the one of median length (the lower median; the earlier seed of
    equals). ``summary["typical"]`` says how many of the seeds ended that way.
    """
    episodes = [play_episode(task, s, policy, partners=partners) for s in range(seed, seed + max(1, tries))]
    counts = Counter(e.summary["outcome"] for e in episodes)
    usual = max(counts, key=lambda outcome: counts[outcome])  # Counter keeps first-seen order: ties go earlier
    alike = sorted((e for e in episodes if e.summary["outcome"] == usual), key=lambda e: e.summary["steps"])
    chosen = alike[(len(alike) - 1) // 2]
    chosen.summary["typical"] = f"{counts[usual]} of {len(episodes)} seeds ended {usual}"
    return chosen


def member_name(policy: Steer | DronePolicy) -> str:
    """The name a policy is shown by: its ``name``, else its function name."""
    return str(getattr(policy, "name", None) or getattr(policy, "__name__", "policy"))


def caption(member: str, summary: dict[str, Any]) -> str:
    """``"<member> + <partners>: <outcome> in <steps> steps (<caught>/<evaders> caught), seed <seed>"``
    (``"<member> alone: ..."`` without partners), then ``"; <k> of <n> seeds ended <outcome>"`` when the
    episode was picked as the typical one (:func:`representative_episode`)."""
    partners = summary.get("team", {}).get("partners", [])
    who = f"{member} + {', '.join(partners)}" if partners else f"{member} alone"
    text = (
        f"{who}: {summary['outcome']} in {summary['steps']} steps "
        f"({summary['captured']}/{summary['num_e']} caught), seed {summary['seed']}"
    )
    return f"{text}; {summary['typical']}" if summary.get("typical") else text


def showcase(
    task: TaskConfig | str,
    policy: Steer | DronePolicy,
    partners: Partners | str | None,
    seed: int = 0,
    tries: int = 8,
    frame_every: int = 5,
) -> tuple[list[np.ndarray], dict[str, Any]]:
    """A whole, representative episode of ``policy`` with ``partners`` (a zoo, its name, or None: alone), drawn.

    The episode is :func:`representative_episode`'s; every ``frame_every``-th step, the
    first and the last are drawn (:func:`frame_steps`). The :func:`caption` (each frame's
    title, and ``summary["caption"]``) names the member, its partners and the outcome.
    """
    frame_steps(0, frame_every)
    zoo = load_zoo(partners) if isinstance(partners, str) else partners
    episode = representative_episode(task, policy, zoo, seed, tries)
    summary = {**episode.summary, "caption": caption(member_name(policy), episode.summary)}
    return draw_episode(episode, frame_every, title=summary["caption"], member=member_name(policy)), summary


def showcase_gif(
    task: TaskConfig | str,
    policy: Steer | DronePolicy,
    zoo: Zoo | str | None,
    seed: int,
    out: str | os.PathLike[str],
    max_tries: int = 8,
    frame_every: int = 4,
    fps: float = 10,
) -> dict[str, Any]:
    """Write :func:`showcase`'s GIF of ``policy`` with partners from ``zoo`` to ``out`` (atomically).

    Returns member, partners (the zoo members drawn; [] alone), seed, outcome, steps,
    captured, num_e, caption, frames (the GIF's frame count) and path.
    """
    frames, summary = showcase(task, policy, zoo, seed, max_tries, frame_every)
    path = save_gif(frames, out, fps=fps)
    keep = ("seed", "outcome", "steps", "captured", "num_e", "caption")
    return {
        "member": member_name(policy),
        "partners": summary.get("team", {}).get("partners", []),
        **{k: summary[k] for k in keep},
        "frames": len(frames),
        "path": Path(path),
    }
