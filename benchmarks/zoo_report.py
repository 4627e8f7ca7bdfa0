"""The zoo report: how hard each task's zoos are for self-play at the paper's budget, beside the paper.

    python benchmarks/zoo_report.py [--tasks ...] [--seeds 100 101 102] [--episodes 500] [--report-only]

For every task: (1) every trained partner drone of Zoos 2-4, the validation zoo and the
default pool with the self-play SUC/COL of its last evaluation in training (300 episodes,
from its checkpoint header; a best response's is with its training zoo); (2) self-play
(configs/train/sp_paper.json: IPPO, 1,048,576 env steps, the partners' PPO recipe) trained
with three seeds no partner uses, each final learner evaluated with every zoo (``--episodes``
per zoo, evaluation seed 0): SUC/COL/AST/REW, mean ± std (ddof 1) over the seeds, and the
share of episodes ended by a crash with the learner in it and by the partners alone; beside
the paper's Table 2 SP column (Zoos 1-3; the paper gives COL, AST, REW). The zoo difficulty
ordering by COL, ours and the paper's.

Resumable: a trained learner (runs_partners/sp_paper/<task>/) and an evaluated cell
(benchmarks/results/zoo_report/cells/) are not done again. Writes
benchmarks/results/zoo_report/report.md and report.json.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "zoo_report"
RUNS = ROOT / "runs_partners" / "sp_paper"
TASKS = ("4p2e1o", "4p2e3o", "4p2e5o", "4p3e5o")
ZOOS = ("zoo1", "zoo2", "zoo3", "zoo4", "validation")
SETS = ("zoo2", "zoo3", "zoo4", "validation")
METRICS = ("SUC", "COL", "AST", "REW")


def _write(path: Path, data: object) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(data, indent=1) + "\n")
    os.replace(tmp, path)


def train(task: str, seed: int) -> Path:
    """The SP learner of ``task`` and ``seed`` (trained, or resumed, when its run has not finished)."""
    name = f"sp_paper_s{seed}"
    run = RUNS / task / name
    done = run / "done.json"
    if not done.is_file():
        cmd = [str(Path(sys.executable).parent / "atdrone"), "train", str(ROOT / "configs/train/sp_paper.json")]
        cmd += ["--task", task, "--seed", str(seed), "--name", name, "--out-dir", str(RUNS / task), "--no-progress"]
        if run.is_dir():
            cmd.append("--resume")
        env = dict(os.environ, MLFLOW_TRACKING_URI=f"sqlite:///{RUNS / 'mlflow.db'}", OMP_NUM_THREADS="1")
        start = time.time()
        RUNS.mkdir(parents=True, exist_ok=True)
        with (RUNS / "train.log").open("a") as log:
            subprocess.run(cmd, cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT, check=True)
        _write(done, {"wall_s_last_attempt": round(time.time() - start, 1)})
    return run / "last.pt"


def evaluate_cell(task: str, seed: int, zoo: str, episodes: int, learner: Path) -> dict:
    """One learner x zoo on its task; cached in cells/."""
    path = OUT / "cells" / f"{task}_s{seed}_{zoo}.json"
    if path.is_file():
        return json.loads(path.read_text())
    from atdrone.policies.zoo import load_checkpoint, load_zoo
    from atdrone.teams.evaluation import crash_breakdown, crash_shares, evaluate

    zoo_obj = load_zoo(zoo, task)
    if zoo_obj.missing:
        return {"missing": zoo_obj.missing}
    start = time.time()
    result = evaluate(load_checkpoint(learner), task, zoo_obj, episodes=episodes, seeds=[0])
    cell = {
        "task": task,
        "seed": seed,
        "zoo": zoo,
        "zoo_version": result.zoo_version,
        "episodes": episodes,
        **result.mean,
        **crash_shares(result.records),
        "crashes": crash_breakdown(result.records),
        "env_steps": int(result.records["length"].sum()),
        "wall_s": round(time.time() - start, 1),
    }
    _write(path, cell)
    return cell


def partners(task: str) -> list[dict]:
    from atdrone.models.checkpoint import read_header
    from atdrone.policies.zoo import checkpoint_path, load_zoo
    from atdrone.teams.pools import load_pool

    rows, seen = [], set()
    for zoo in [load_zoo(z, task) for z in SETS] + [load_pool("train_pool").resolve(task)]:
        for spec in zoo.spec.members:
            if spec.kind != "checkpoint" or spec.name in seen:
                continue
            seen.add(spec.name)
            path = checkpoint_path(spec)
            row: dict = {"set": zoo.name, "name": spec.name, "trained": path.is_file()}
            if path.is_file():
                head = read_header(path)
                metrics = head.get("metrics", {})
                row.update(
                    trained_on=head["task"],
                    recipe=f"configs/train/{head['config']['name']}.json",
                    seed=head["seed"],
                    env_steps=head["step"],
                    stop_at_suc=head["config"]["stop_at_suc"],
                    SUC=metrics.get("eval/SUC"),
                    COL=metrics.get("eval/COL"),
                    with_partners=head["config"].get("zoo") or "itself",
                )
            rows.append(row)
    return rows


def _fmt(values: list[float]) -> str:
    if not values:
        return "-"
    arr = np.array(values, float)
    if len(arr) == 1:
        return f"{arr[0]:.1f} (1 seed)"
    return f"{arr.mean():.1f} ± {arr.std(ddof=1):.1f}"


def report(tasks: list[str], seeds: list[int], episodes: int) -> None:
    from atdrone.benchmark.paper import TABLE2
    from atdrone.policies.manifest import task_version

    doc: dict = {"seeds": seeds, "episodes": episodes, "tasks": {}}
    md = [
        "# The zoos per task: partners, and self-play at the paper's budget with each zoo",
        "",
        f"Made by `python benchmarks/zoo_report.py` ({time.strftime('%Y-%m-%d')}). Self-play: "
        "`configs/train/sp_paper.json` (IPPO, 1,048,576 env steps, 2 epochs, lr 3e-4), seeds "
        f"{', '.join(map(str, seeds))}; each final learner plays {episodes} episodes with each zoo "
        "(evaluation seed 0). Values: mean ± std (ddof 1) over the seeds that finished. Paper: Table 2's SP "
        "column (mean ± std over its seeds; no SUC there). Crash shares: % of episodes ended by a "
        "collision with a learner in it / with partners only.",
        "",
    ]
    for task in tasks:
        cells = {}
        for zoo in ZOOS:
            found = [OUT / "cells" / f"{task}_s{s}_{zoo}.json" for s in seeds]
            cells[zoo] = [json.loads(p.read_text()) for p in found if p.is_file()]
            cells[zoo] = [c for c in cells[zoo] if "missing" not in c]
        rows = partners(task)
        doc["tasks"][task] = {"zoo_version": task_version(task), "partners": rows, "cells": cells}
        md += [
            f"## {task} (zoo version {task_version(task)})",
            "",
            "Trained partners (last evaluation in training):",
            "",
        ]
        md += ["| set | drone | recipe | seed | env steps | stop at SUC | SUC | COL | with |", "|" + "---|" * 9]
        for r in rows:
            if not r["trained"]:
                md.append(f"| {r['set']} | {r['name']} | not trained yet | | | | | | |")
                continue
            md.append(
                f"| {r['set']} | {r['name']} | {r['recipe']} | {r['seed']} | {r['env_steps']:,} | {r['stop_at_suc']} "
                f"| {r['SUC']:.1f} | {r['COL']:.1f} | {r['with_partners']} |"
            )
        md += ["", "SP with each zoo:", ""]
        md += [
            "| zoo | seeds | SUC | COL | paper COL | AST | paper AST | REW | paper REW | learner crash "
            "| partners-only crash |"
        ]
        md += ["|" + "---|" * 11]
        order = {}
        for zoo in ZOOS:
            c = cells[zoo]
            paper = TABLE2.get(task, {}).get(zoo, {}).get("sp")

            def p(metric: str, paper: dict | None = paper) -> str:
                return f"{paper[metric][0]:.1f} ± {paper[metric][1]:.1f}" if paper else "-"

            vals = {m: [x[m] for x in c if x.get(m) is not None and not np.isnan(x[m])] for m in METRICS}
            if c:
                order[zoo] = float(np.mean(vals["COL"]))
            md.append(
                f"| {zoo} | {len(c)} | {_fmt(vals['SUC'])} | {_fmt(vals['COL'])} | {p('COL')} | {_fmt(vals['AST'])} "
                f"| {p('AST')} | {_fmt(vals['REW'])} | {p('REW')} | {_fmt([x['learner_crash'] for x in c])} "
                f"| {_fmt([x['partner_only_crash'] for x in c])} |"
            )
        ours = [z for z in sorted(order, key=order.get) if z in ("zoo1", "zoo2", "zoo3")]  # type: ignore[arg-type]
        theirs = sorted(("zoo1", "zoo2", "zoo3"), key=lambda z: TABLE2[task][z]["sp"]["COL"][0])
        doc["tasks"][task]["ordering"] = {"ours_by_COL": ours, "paper_by_COL": theirs}
        md += [
            "",
            f"Zoos 1-3 from easiest to hardest by SP's COL: ours {' < '.join(ours) or '-'}; "
            f"the paper's {' < '.join(theirs)}.",
            *_swaps(task, ours, theirs, cells),
            "",
        ]
    _write(OUT / "report.json", doc)
    (OUT / "report.md").write_text("\n".join(md) + "\n")
    print(f"wrote {OUT / 'report.md'}")


def _swaps(task: str, ours: list[str], theirs: list[str], cells: dict[str, list[dict]]) -> list[str]:
    """For each pair of zoos that ours and the paper's orderings put the other way round: both gaps in COL and
    the crash shares (who collided) that make ours."""
    from atdrone.benchmark.paper import TABLE2

    lines = []
    for i, a in enumerate(ours):
        for b in ours[i + 1 :]:  # ours: a easier than b
            if theirs.index(a) < theirs.index(b):
                continue
            pa, pb = (TABLE2[task][z]["sp"]["COL"] for z in (a, b))
            gap = pa[0] - pb[0]
            noise = ", within one standard deviation over its seeds" if abs(gap) < max(pa[1], pb[1]) else ""

            def mean(zoo: str, key: str) -> float:
                return float(np.mean([x[key] for x in cells[zoo]]))

            lines.append(
                f"{a} and {b} swap places. The paper's COL: {pa[0]:.1f} ± {pa[1]:.1f} and {pb[0]:.1f} ± {pb[1]:.1f} "
                f"({abs(gap):.1f} points apart{noise}); ours: {mean(a, 'COL'):.1f} and {mean(b, 'COL'):.1f}. "
                f"With {b}, a crash involves SP's own drones in {mean(b, 'learner_crash'):.1f} % of episodes "
                f"against {mean(a, 'learner_crash'):.1f} % with {a}; partners alone crash in "
                f"{mean(b, 'partner_only_crash'):.1f} % against {mean(a, 'partner_only_crash'):.1f} %."
            )
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument("--seeds", nargs="+", type=int, default=[100, 101, 102])
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--report-only", action="store_true", help="only write the report from what is done")
    args = parser.parse_args()
    if not args.report_only:
        for seed in args.seeds:
            for task in args.tasks:
                learner = train(task, seed)
                for zoo in ZOOS:
                    evaluate_cell(task, seed, zoo, args.episodes, learner)
                print(f"{time.strftime('%T')} {task} seed {seed}: trained and evaluated", flush=True)
    report(args.tasks, args.seeds, args.episodes)
    return 0


if __name__ == "__main__":
    sys.exit(main())
