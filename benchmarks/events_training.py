"""Training with team events against training without: does a learner that met teammates dropping out and
backups joining in training lose less when the team changes?

    python benchmarks/events_training.py [--task 4p2e1o] [--seeds 100 101 102] [--episodes 500] [--report-only]

Two recipes, the same in every other way: ``configs/train/sp_paper.json`` (self-play IPPO at 1,048,576 env
steps, the zoo report's learners) and ``configs/train/sp_paper_events.json`` (the same, every rollout episode
drawing the events of ``zoo3+drop+join``). Each seed's final learner of both is played with Zoo 3 and each
of its team-event protocols (``--episodes`` per protocol, evaluation seed 0, the same episodes for both):
SUC, SUC after the event, COL and the recovery time (REC, steps from the event to the next capture), mean ±
std (ddof 1) over the seeds, and the paired difference (with events - without) with a t-interval of
seeds - 1 degrees of freedom. The learners without events are the zoo report's (``runs_partners/sp_paper``),
trained here only where missing.

Resumable: a trained learner and an evaluated cell (benchmarks/results/events_training/cells/) are not done
again; a part-trained learner resumes from its checkpoint. Writes report.md and report.json beside the cells.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from atdrone.benchmark.stats import over_seeds, t_interval
from atdrone.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "events_training"
RUNS = ROOT / "runs_partners"
RECIPES = {"without": "sp_paper", "with": "sp_paper_events"}
PROTOCOLS = ("zoo3", "zoo3+swap", "zoo3+drop", "zoo3+drop+join")
METRICS = ("SUC", "SUC_post", "COL", "REC")


def write_json(path: Path, data: object) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(data, indent=1) + "\n")


def train(recipe: str, task: str, seed: int) -> Path:
    """The final learner of ``recipe`` on ``task`` with ``seed`` (trained, or resumed, when not finished)."""
    name = f"{recipe}_s{seed}"
    folder = RUNS / recipe / task
    run = folder / name
    done = run / "done.json"
    if not done.is_file():
        cmd = [str(Path(sys.executable).parent / "atdrone"), "train", str(ROOT / f"configs/train/{recipe}.json")]
        cmd += ["--task", task, "--seed", str(seed), "--name", name, "--out-dir", str(folder), "--no-progress"]
        if run.is_dir():
            cmd.append("--resume")
        env = dict(os.environ, MLFLOW_TRACKING_URI=f"sqlite:///{RUNS / recipe / 'mlflow.db'}", OMP_NUM_THREADS="1")
        start = time.time()
        folder.mkdir(parents=True, exist_ok=True)
        print(f"[events] training {name} on {task}", flush=True)
        with (RUNS / recipe / "train.log").open("a") as log:
            subprocess.run(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, check=True)
        write_json(done, {"wall_s_last_attempt": round(time.time() - start, 1)})
    return run / "last.pt"


def evaluate_cell(variant: str, task: str, seed: int, protocol: str, episodes: int, learner: Path) -> dict[str, Any]:
    """One learner with one protocol (or Zoo 3 alone); cached in cells/."""
    path = OUT / "cells" / f"{variant}_{task}_s{seed}_{protocol}.json"
    if path.is_file():
        return dict(json.loads(path.read_text()))
    from atdrone.models.checkpoint import read_header
    from atdrone.policies.zoo import load_checkpoint
    from atdrone.teams.evaluation import evaluate

    start = time.time()
    result = evaluate(
        load_checkpoint(learner),
        task,
        "zoo3",
        episodes=episodes,
        seeds=[0],
        protocol=None if protocol == "zoo3" else protocol,
    )
    cell = {
        "variant": variant,
        "task": task,
        "seed": seed,
        "protocol": protocol,
        "episodes": episodes,
        "learner_sha256": read_header(learner)["sha256"],
        "zoo_version": result.zoo_version,
        **{k: v for k, v in result.mean.items() if k in METRICS or k in ("AST", "REW", "EVT", "REC_none")},
        "env_steps": int(result.records["length"].sum()),
        "wall_s": round(time.time() - start, 1),
    }
    write_json(path, cell)
    print(f"[events] {variant} s{seed} {protocol}: SUC {cell['SUC']:.1f}", flush=True)
    return cell


def paired(with_: list[float], without: list[float]) -> dict[str, Any]:
    """Mean paired difference (with - without) and its 95 % t-interval over the seeds where both are finite."""
    found = t_interval(np.asarray(with_, float) - np.asarray(without, float))
    return {"diff": found["diff"], "ci95": found["ci95"] if found["n"] >= 2 else None, "n": found["n"]}


def _loss_rows(cells: dict[str, dict[str, Any]], seeds: list[int], doc: dict[str, Any]) -> list[str]:
    """What the events take away: each recipe's SUC on an event protocol minus its SUC on Zoo 3 (paired by seed),
    and the difference of those changes (with - without): the part of the gain that is the events'."""
    suc = {
        (v, p): np.array([float(cells.get(f"{v}|{s}|{p}", {}).get("SUC", np.nan)) for s in seeds])
        for v in RECIPES
        for p in PROTOCOLS
    }
    md = [
        "",
        "What a team change costs each recipe (SUC on the protocol minus SUC on Zoo 3, paired by seed), and the "
        "difference of the two costs: above 0, training with events loses less when the team changes than its gain "
        "on Zoo 3 alone accounts for.",
        "",
        "| protocol | without events: change [95 % CI] | with events: change [95 % CI] | difference [95 % CI] |",
        "|---|---|---|---|",
    ]
    doc["loss"] = {}
    for protocol in PROTOCOLS[1:]:
        change = {v: suc[(v, protocol)] - suc[(v, "zoo3")] for v in RECIPES}
        parts = [t_interval(change["without"]), t_interval(change["with"]), paired(change["with"], change["without"])]
        doc["loss"][protocol] = {"without": parts[0], "with": parts[1], "difference": parts[2]}
        text = [
            f"{q['diff']:+.1f} [{q['ci95'][0]:+.1f}, {q['ci95'][1]:+.1f}]" if q.get("ci95") and q["n"] >= 2 else "-"
            for q in parts
        ]
        md.append(f"| {protocol} | {' | '.join(text)} |")
    return md


def report(task: str, seeds: list[int], episodes: int) -> dict[str, Any]:
    cells: dict[str, dict[str, Any]] = {}
    for path in sorted((OUT / "cells").glob(f"*_{task}_s*.json")):
        cell = json.loads(path.read_text())
        if cell["seed"] in seeds:
            cells[f"{cell['variant']}|{cell['seed']}|{cell['protocol']}"] = cell
    doc: dict[str, Any] = {"task": task, "seeds": seeds, "episodes": episodes, "recipes": RECIPES, "protocols": {}}
    md = [
        "# Training with team events against training without",
        "",
        f"Self-play IPPO on {task} at 1,048,576 env steps: `configs/train/sp_paper.json` (without) and "
        "`configs/train/sp_paper_events.json` (the same, every rollout episode drawing the events of "
        f"`zoo3+drop+join`), seeds {', '.join(map(str, seeds))}. Each final learner played with Zoo 3 and its "
        f"team-event protocols, {episodes} episodes each (evaluation seed 0: the same episodes for both). "
        "Mean ± std (ddof 1) over the seeds; the difference is paired by seed (with - without), 95 % t-interval "
        f"with {len(seeds) - 1} degrees of freedom. REC: steps from the event to the next capture (episodes with "
        "a capture after the event). Re-run: `python benchmarks/events_training.py`.",
        "",
        "| protocol | metric | without events | with events | with - without [95 % CI] |",
        "|---|---|---|---|---|",
    ]
    for protocol in PROTOCOLS:
        rows: dict[str, Any] = {}
        for metric in METRICS:
            vals = {
                v: [float(cells.get(f"{v}|{s}|{protocol}", {}).get(metric, np.nan)) for s in seeds] for v in RECIPES
            }
            if all(np.isnan(vals[v]).all() for v in RECIPES):
                continue
            diff = paired(vals["with"], vals["without"])
            rows[metric] = {"without": vals["without"], "with": vals["with"], **diff}
            ci = f"[{diff['ci95'][0]:+.1f}, {diff['ci95'][1]:+.1f}]" if diff["ci95"] else "-"
            d = f"{diff['diff']:+.1f} {ci}" if diff["n"] else "-"
            md.append(f"| {protocol} | {metric} | {over_seeds(vals['without'])} | {over_seeds(vals['with'])} | {d} |")
        doc["protocols"][protocol] = rows
    md += _loss_rows(cells, seeds, doc)
    return write_report(OUT, list(cells.values()), md, doc)


def write_report(out: Path, cells: list[dict[str, Any]], md: list[str], doc: dict[str, Any]) -> dict[str, Any]:
    """Close a report with what its evaluation cost (``cells``' env steps and wall time) and write it to ``out``
    (report.md and report.json)."""
    steps = sum(int(c.get("env_steps", 0)) for c in cells)
    wall = sum(float(c.get("wall_s", 0.0)) for c in cells)
    md += ["", f"Evaluation: {len(cells)} cells, {steps:,} env steps, {wall / 60:.1f} min of wall time."]
    doc["evaluation"] = {"cells": len(cells), "env_steps": steps, "wall_s": round(wall, 1)}
    out.mkdir(parents=True, exist_ok=True)
    write_json(out / "report.json", doc)
    atomic_write_text(out / "report.md", "\n".join(md) + "\n")
    return doc


def arguments(doc: str) -> argparse.Namespace:
    """The command line of a recipe comparison (``doc``: its module docstring); with cells to compute, torch on one
    thread."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--task", default="4p2e1o")
    ap.add_argument("--seeds", type=int, nargs="+", default=[100, 101, 102])
    ap.add_argument("--episodes", type=int, default=500)
    ap.add_argument("--report-only", action="store_true")
    args = ap.parse_args()
    if not args.report_only:
        import torch

        torch.set_num_threads(1)
    return args


def main() -> None:
    args = arguments(__doc__)
    if not args.report_only:
        for seed in args.seeds:
            for variant, recipe in RECIPES.items():
                learner = train(recipe, args.task, seed)
                for protocol in PROTOCOLS:
                    evaluate_cell(variant, args.task, seed, protocol, args.episodes, learner)
    report(args.task, args.seeds, args.episodes)
    print((OUT / "report.md").read_text())


if __name__ == "__main__":
    main()
