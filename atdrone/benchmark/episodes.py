"""What a zoo's evaluation episodes were made of: the measurements that explain a metric against the paper's.

A cell's record keeps, per zoo it was evaluated with, :func:`episode_summary` of its episodes
(``record["episodes"][zoo]``): who was in the collisions that ended episodes, how many evaders
were captured, how long the episodes ran, and the mean team return split into the terms of
the reward (SPEC section 6). The report's section on where ours differs from the paper
(:mod:`~atdrone.benchmark.report_gaps`) reads them.
"""

from __future__ import annotations

import pandas as pd

from atdrone.config import TaskConfig
from atdrone.teams.evaluation import crash_shares

SUMMARY_KEYS = (
    "learner_crash",
    "partner_only_crash",
    "captured",
    "length",
    "return_capture",
    "return_collision",
    "return_rest",
)


def episode_summary(records: pd.DataFrame, task: TaskConfig) -> dict[str, float]:
    """Means over the episodes of one evaluation (:data:`SUMMARY_KEYS`).

    learner_crash, partner_only_crash: % of episodes ended by a collision with a learner drone in it, and
    with partner drones alone (their sum is COL when every collision ends its episode); captured: evaders
    captured per episode; length: steps per episode, every episode (AST counts the successful ones only);
    return_capture: the capture reward's part of the mean return (its coefficient x captured);
    return_collision: the collision penalty's (its coefficient x the share of episodes with a collision: it is
    paid once in a step with any collision); return_rest: the remainder, the approach shaping and the proximity
    penalties. The three parts add up to REW."""
    reward = task.task.reward
    shares = crash_shares(records)
    ret, captured = float(records["return"].mean()), float(records["captured"].mean())
    capture = reward.capture * captured
    collision = reward.collision * float(records["collided"].to_numpy(bool).mean())
    return {
        "learner_crash": float(shares["learner_crash"]),
        "partner_only_crash": float(shares["partner_only_crash"]),
        "captured": captured,
        "length": float(records["length"].mean()),
        "return_capture": capture,
        "return_collision": collision,
        "return_rest": ret - capture - collision,
    }
