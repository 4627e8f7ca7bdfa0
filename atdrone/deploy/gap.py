"""The gap to simulation: a flight's SUC/COL/AST beside the training simulator's on the same team and task."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from atdrone.config import TaskConfig
from atdrone.deploy.config import DeployConfig
from atdrone.deploy.team import Team


def simulation_gap(cfg: DeployConfig, task: TaskConfig, team: Team, flown: dict[str, Any]) -> dict[str, Any]:
    """The flown SUC/COL/AST beside the training simulator's evaluation of the same team.

    The simulator plays ``max(500, flown episodes)`` episodes of the same learner and
    partners (fixed members in the partner slots, or the zoo drawn per episode) on the
    same task and horizon. Differences carry binomial standard errors (SUC, COL) or the
    standard error of the mean (AST), the two samples being independent.
    """
    from atdrone.teams.evaluation import metrics, run_episodes

    episodes = max(500, int(flown["episodes"]))
    if cfg.partners.members:
        partners = team.partners
        fixed = np.arange(len(partners))
        records = run_episodes(
            team.learner, task, partners, episodes, seed=cfg.seed, sampler=lambda rng, n: np.tile(fixed, (n, 1))
        )
    else:
        from atdrone.policies.zoo import load_zoo

        records = run_episodes(team.learner, task, load_zoo(cfg.partners.zoo, task).policies(), episodes, seed=cfg.seed)
    sim = metrics(records)
    n_sim, n_fly = len(records), int(flown["episodes"])
    sim_ast_sd = (
        float(records.loc[records["success"], "length"].std(ddof=1)) if records["success"].sum() > 1 else math.nan
    )
    rows = {}
    for m in ("SUC", "COL"):
        a, b = flown[m] / 100, sim[m] / 100
        se = math.sqrt(a * (1 - a) / max(n_fly, 1) + b * (1 - b) / n_sim) * 100
        rows[m] = {"fleet": flown[m], "simulator": sim[m], "diff": flown[m] - sim[m], "se": se}
    fly_ast_sd = float(flown.get("AST_std", math.nan))
    n_succ_fly = max(1, round(n_fly * flown["SUC"] / 100))
    n_succ_sim = max(1, int(records["success"].sum()))
    se_ast = math.sqrt(fly_ast_sd**2 / n_succ_fly + sim_ast_sd**2 / n_succ_sim)
    rows["AST"] = {"fleet": flown["AST"], "simulator": sim["AST"], "diff": flown["AST"] - sim["AST"], "se": se_ast}
    return {"episodes": {"fleet": n_fly, "simulator": n_sim}, "metrics": rows}


def format_gap(gap: dict[str, Any]) -> str:
    """The gap to simulation as a table."""
    n = gap["episodes"]
    lines = [
        f"gap to simulation (fleet: {n['fleet']} episodes; training simulator: {n['simulator']} episodes)",
        "| metric | sim fleet | simulator | fleet - simulator |",
        "|---|---|---|---|",
    ]
    for m, r in gap["metrics"].items():
        lines.append(f"| {m} | {r['fleet']:.1f} | {r['simulator']:.1f} | {r['diff']:+.1f} +- {r['se']:.1f} |")
    return "\n".join(lines)
