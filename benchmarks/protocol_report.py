"""Open-teaming report: learners on zoo3 and its team-event protocols, every split of the team, other team sizes.

Usage (after the learners are trained, e.g. ``atdrone benchmark configs/benchmarks/paper.json``, whose kept
weights are ``weights:METHOD/TASK``):

    python benchmarks/protocol_report.py --methods sp hola mappo naht_d --tasks 4p2e1o 4p2e5o \
        --episodes 500 --seeds 0 1 2 --out benchmarks/results/protocols

``--learner LABEL=POLICY`` adds a learner by any name ``atdrone evaluate`` takes (e.g. one trained with
``"protocol": "zoo3+drop+join"`` and the same recipe without). Per learner and task it writes the SUC and
recovery time (with 95 % intervals) on zoo3, zoo3+swap, zoo3+drop and zoo3+drop+join, the per-k table of
every split (on zoo3), and SUC in teams of 3-6 pursuers (zoo1 partners, the learner as a cross-task
player); report.json holds every number, report.md the tables. Cells already in report.json are kept.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from atdrone.fileio import atomic_write_text
from atdrone.resolve import resolve
from atdrone.teams.evaluation import evaluate
from atdrone.teams.splits import evaluate_splits

PROTOCOLS = ("zoo3", "zoo3+swap", "zoo3+drop", "zoo3+drop+join")
SIZES = ("configs/tasks/3p2e1o.json", "configs/tasks/5p2e1o.json", "configs/tasks/6p2e1o.json")


def cells(label: str, policy_name: str, task: str, episodes: int, seeds: list[int]) -> dict[str, Any]:
    """Every number of one learner on one task."""
    learner = resolve(policy_name).policy()
    out: dict[str, Any] = {"learner": label, "policy": policy_name, "task": task, "protocols": {}, "sizes": {}}
    for name in PROTOCOLS:
        protocol = None if name == "zoo3" else name
        summary = evaluate(learner, task, "zoo3", episodes, seeds, protocol=protocol).summary()
        out["protocols"][name] = {k: summary[k] for k in summary if k.split("_ci95")[0] in _WANTED}
    split = evaluate_splits(learner, task, "zoo3", episodes, seeds)
    out["splits"] = split.per_k().reset_index().to_dict(orient="records")
    for size in SIZES:
        summary = evaluate(learner, size, "zoo1", episodes, seeds, cross_task=True).summary()
        out["sizes"][summary["task"]] = {k: summary[k] for k in ("SUC", "SUC_ci95", "COL")}
    return out


_WANTED = {"SUC", "COL", "EVT", "SUC_pre", "SUC_post", "COL_post", "REC", "REC_none"}


def markdown(report: list[dict[str, Any]]) -> str:
    """The report's tables: protocols (SUC, SUC after the event, REC), splits (SUC per k), sizes (SUC)."""
    lines = ["# Open teaming", "", "| learner | task | " + " | ".join(PROTOCOLS) + " | REC (steps) per protocol |"]
    lines.append("|" + " --- |" * (len(PROTOCOLS) + 3))
    for r in report:
        suc = [f"{r['protocols'][p]['SUC']:.1f}" for p in PROTOCOLS]
        rec = [f"{r['protocols'][p].get('REC', float('nan')):.0f}" for p in PROTOCOLS[1:]]
        lines.append(f"| {r['learner']} | {r['task']} | " + " | ".join(suc) + f" | {', '.join(rec)} |")
    lines += ["", "| learner | task | SUC with k learners (k = 1, 2, 3) |", "| --- | --- | --- |"]
    for r in report:
        lines.append(
            f"| {r['learner']} | {r['task']} | " + ", ".join(f"{row['SUC']:.1f}" for row in r["splits"]) + " |"
        )
    if report:
        sizes = list(report[0]["sizes"])
        lines += ["", "| learner | task | " + " | ".join(sizes) + " |", "|" + " --- |" * (len(sizes) + 2)]
    for r in report:
        lines.append(
            f"| {r['learner']} | {r['task']} | " + " | ".join(f"{v['SUC']:.1f}" for v in r["sizes"].values()) + " |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", nargs="*", default=["sp", "hola", "mappo", "naht_d"])
    parser.add_argument("--tasks", nargs="+", default=["4p2e1o", "4p2e5o"])
    parser.add_argument("--learner", action="append", default=[], help="LABEL=POLICY, played on every task")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/protocols"))
    args = parser.parse_args()
    learners = [(m, f"weights:{m}/{{task}}") for m in args.methods]
    learners += [tuple(item.split("=", 1)) for item in args.learner]  # type: ignore[misc]
    args.out.mkdir(parents=True, exist_ok=True)
    path = args.out / "report.json"
    report: list[dict[str, Any]] = json.loads(path.read_text()) if path.exists() else []
    done = {(r["learner"], r["task"]) for r in report}
    for label, name in learners:
        for task in args.tasks:
            if (label, task) in done:
                continue
            report.append(cells(label, name.format(task=task), task, args.episodes, args.seeds))
            atomic_write_text(path, json.dumps(report, indent=2, default=float))
            atomic_write_text(args.out / "report.md", markdown(report))
            print(f"{label} {task}: done", flush=True)


if __name__ == "__main__":
    main()
