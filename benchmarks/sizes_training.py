"""Training with team sizes drawn against training at one size: does a learner that met teams of 3 to 6 pursuers
in training do better in them?

    python benchmarks/sizes_training.py [--task 4p2e1o] [--seeds 100 101 102] [--episodes 500] [--report-only]

Two recipes, the same in every other way: ``configs/train/sp_paper.json`` (self-play IPPO at 1,048,576 env
steps, teams of 4) and ``configs/train/sp_paper_sizes.json`` (the same, each rollout's team of 3 to 6 pursuers,
protocol ``sizes3-6``). The budget is in env steps, so the second trains on 4.5 drone-steps per env step
against 4. Each seed's final learner is played on the task's variants with 3, 4, 5 and 6 pursuers with Zoo 1
(rule-based drones, which fly in any team size; ``--episodes`` each, evaluation seed 0, the same episodes for
both): SUC and COL, mean ± std (ddof 1) over the seeds, and the paired difference (sizes - one size) with a
t-interval of seeds - 1 degrees of freedom.

Resumable: trained learners (runs_partners/, as benchmarks/events_training.py trains them) and evaluated
cells (benchmarks/results/sizes_training/cells/) are not done again. Writes report.md and report.json beside
the cells.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from events_training import arguments, paired, train, write_json, write_report  # shared

from atdrone.benchmark.stats import over_seeds

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "sizes_training"
RECIPES = {"one size": "sp_paper", "sizes": "sp_paper_sizes"}
SIZES = (3, 4, 5, 6)
METRICS = ("SUC", "COL")


def size_task(task: str, pursuers: int) -> str:
    """The variant of ``task`` (``<P>p<E>e<O>o``) with ``pursuers`` pursuers."""
    return f"{pursuers}p{task.split('p', 1)[1]}"


def evaluate_cell(recipe: str, task: str, seed: int, pursuers: int, episodes: int, learner: Path) -> dict[str, Any]:
    """One learner on one team size with Zoo 1; cached in cells/."""
    played = size_task(task, pursuers)
    path = OUT / "cells" / f"{recipe}_{task}_s{seed}_{played}.json"
    if path.is_file():
        return dict(json.loads(path.read_text()))
    from atdrone.config import CONFIG_DIR
    from atdrone.models.checkpoint import read_header
    from atdrone.policies.zoo import load_checkpoint
    from atdrone.teams.evaluation import evaluate

    start = time.time()
    result = evaluate(
        load_checkpoint(learner),
        str(CONFIG_DIR / "tasks" / f"{played}.json"),
        "zoo1",
        episodes=episodes,
        seeds=[0],
        cross_task=pursuers != int(task.split("p", 1)[0]),
    )
    cell = {
        "recipe": recipe,
        "task": task,
        "played_on": played,
        "pursuers": pursuers,
        "seed": seed,
        "episodes": episodes,
        "learner_sha256": read_header(learner)["sha256"],
        "zoo_version": result.zoo_version,
        **{k: v for k, v in result.mean.items() if k in (*METRICS, "AST", "REW")},
        "env_steps": int(result.records["length"].sum()),
        "wall_s": round(time.time() - start, 1),
    }
    write_json(path, cell)
    print(f"[sizes] {recipe} s{seed} {played}: SUC {cell['SUC']:.1f}", flush=True)
    return cell


def report(task: str, seeds: list[int], episodes: int) -> dict[str, Any]:
    cells = {}
    for path in sorted((OUT / "cells").glob(f"*_{task}_s*.json")):
        cell = json.loads(path.read_text())
        if cell["seed"] in seeds:
            cells[(cell["recipe"], cell["seed"], cell["pursuers"])] = cell
    doc: dict[str, Any] = {"task": task, "seeds": seeds, "episodes": episodes, "recipes": RECIPES, "sizes": {}}
    md = [
        "# Training with team sizes drawn against training at one size",
        "",
        f"Self-play IPPO on {task} at 1,048,576 env steps: `configs/train/sp_paper.json` (teams of "
        f"{task.split('p', 1)[0]}) and `configs/train/sp_paper_sizes.json` (the same, each rollout's team of 3 to "
        "6 pursuers drawn, protocol `sizes3-6`; 4.5 drone-steps per env step on average against 4), seeds "
        f"{', '.join(map(str, seeds))}. Each final learner played with Zoo 1 (rule-based drones) in teams of "
        f"3 to 6, {episodes} episodes each (evaluation seed 0: the same episodes for both). Mean ± std (ddof 1) "
        "over the seeds; the difference is paired by seed (sizes - one size), 95 % t-interval with "
        f"{len(seeds) - 1} degrees of freedom. Re-run: `python benchmarks/sizes_training.py`.",
        "",
        "| team | metric | one size | sizes drawn | sizes - one size [95 % CI] |",
        "|---|---|---|---|---|",
    ]
    for p in SIZES:
        rows = {}
        for metric in METRICS:
            vals = {r: [float(cells.get((r, s, p), {}).get(metric, np.nan)) for s in seeds] for r in RECIPES}
            diff = paired(vals["sizes"], vals["one size"])
            rows[metric] = {**vals, **diff}
            ci = f"[{diff['ci95'][0]:+.1f}, {diff['ci95'][1]:+.1f}]" if diff["ci95"] else "-"
            d = f"{diff['diff']:+.1f} {ci}" if diff["n"] else "-"
            line = f"| {size_task(task, p)} | {metric} | {over_seeds(vals['one size'])} | {over_seeds(vals['sizes'])}"
            md.append(f"{line} | {d} |")
        doc["sizes"][size_task(task, p)] = rows
    return write_report(OUT, list(cells.values()), md, doc)


def main() -> None:
    args = arguments(__doc__)
    if not args.report_only:
        for seed in args.seeds:
            for name, recipe in RECIPES.items():
                learner = train(recipe, args.task, seed)
                for p in SIZES:
                    evaluate_cell(name, args.task, seed, p, args.episodes, learner)
    report(args.task, args.seeds, args.episodes)
    print((OUT / "report.md").read_text())


if __name__ == "__main__":
    main()
