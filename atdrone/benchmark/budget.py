"""Equal budgets: how many generations (and updates) give an algorithm about a given number of env steps.

Every learner update takes ``ppo.num_envs x ppo.rollout_steps`` environment steps; a run's
length is set in generations of ``updates_per_generation`` updates. Algorithms spend
their generations differently (HOLA's generation 0 trains Pi_0's self-play seeds, FCP's
its frozen pool, PBT trains several members per generation), so the generations that
reach a budget depend on the algorithm and its section. The service counts what a run
really spent (env steps, learner samples, evaluation env steps): reports state that,
not this plan.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any


def plan(
    algorithm: str, section: Mapping[str, Any], env_steps: int, updates: int, update_env_steps: int
) -> dict[str, Any]:
    """The experiment keys (``generations``, for PBT also ``updates_per_generation``) that give a run of
    ``algorithm`` (with its config ``section``) about ``env_steps`` env steps at ``updates`` learner updates
    per generation of ``update_env_steps`` env steps each."""
    total = max(1, round(env_steps / update_env_steps))  # learner updates of the whole run
    if algorithm in ("hola", "hola_no_g"):  # generation 0 trains pi0_seeds self-play runs of `updates` updates
        pi0 = int(section.get("pi0_seeds", 2))
        return {"generations": max(1, 1 + math.ceil((total - pi0 * updates) / updates))}
    if algorithm == "fcp":  # generation 0 also trains the frozen pool: `seeds` self-play runs
        seeds = int(section.get("seeds", 3))
        return {"generations": max(1, math.ceil((total - seeds * updates) / updates))}
    if algorithm == "pbt":  # population_size members, each updates / population_size updates per generation
        size = int(section.get("population_size", 4))
        return {"generations": max(1, math.ceil(total / updates)), "updates_per_generation": max(1, updates // size)}
    return {"generations": max(1, math.ceil(total / updates))}
