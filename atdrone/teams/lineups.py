"""Many partner lineups of one learner played in one batch of environments (HOLA-Drone V2's min step: every
hyperedge of G'_t at once instead of one match at a time)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from atdrone.config import TaskConfig
from atdrone.policies.base import Policy
from atdrone.teams.evaluation import metrics, run_episodes


def evaluate_lineups(
    learner: Policy,
    task: TaskConfig | str,
    partners: Sequence[Policy],
    lineups: Sequence[Sequence[int]],
    episodes: Sequence[int],
    seed: int = 0,
) -> list[dict[str, float]]:
    """SUC/COL/AST/REW of ``learner`` with each lineup of ``partners`` (their indices), ``episodes[i]`` episodes
    of lineup i, all played in one batch of environments; per lineup also ``REW_var`` (the returns' sample
    variance) and ``steps`` (its environment steps). The same episodes as one run per lineup would play,
    batched: a step of many small matches costs about as much as a step of one."""
    if len(lineups) != len(episodes) or not len(lineups) or min(episodes) < 1:
        raise ValueError(f"need a positive episode count per lineup, got {list(episodes)} for {len(lineups)} lineups")
    which = np.repeat(np.arange(len(lineups)), episodes)
    plan = np.asarray(lineups, dtype=np.intp).reshape(len(lineups), -1)[which]  # episode e: its lineup
    records = run_episodes(learner, task, partners, len(which), seed=seed, lineups=plan)
    out = []
    for i in range(len(lineups)):
        rows = records[which == i]
        returns = rows["return"].to_numpy(np.float64)
        var = float(returns.var(ddof=1)) if len(returns) > 1 else 0.0
        out.append({**metrics(rows), "REW_var": var, "steps": int(rows["length"].sum())})
    return out
