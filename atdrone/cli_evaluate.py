"""``atdrone evaluate``: a policy with unseen zoo partners, every metric with its interval."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from atdrone.cli_args import MAX_EPISODES, POLICY_HELP, episodes_count, seed_value
from atdrone.cli_registry import add_member_location
from atdrone.config import TASK_NAMES
from atdrone.errors import UserError


def add_evaluate(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "evaluate",
        help="SUC / COL / AST / REW of a policy teamed with unseen zoo partners",
        description="Play --episodes episodes per seed of the policy in the task's learner slots with partners drawn "
        "from the zoo; print SUC / COL / AST / REW (each with its 95 % confidence interval over episodes) as a table "
        "(rows tasks, columns zoos) and "
        "write <out>/<policy>_<task>_<zoo>.json (summary and per-seed metrics) and .csv (every episode).",
    )
    p.add_argument("--policy", required=True, help=f"the learner: {POLICY_HELP}")
    p.add_argument(
        "--task",
        default=None,
        help=f"task name ({', '.join(TASK_NAMES)}), JSON path, or all (default: the policy's task, else 4p2e1o)",
    )
    p.add_argument(
        "--zoo",
        default="zoo1",
        help="zoo name (zoo1-zoo4, validation), a protocol of team events (zoo3+swap, zoo3+drop, zoo3+drop+join), "
        "JSON path, or all (zoo1-zoo4)",
    )
    p.add_argument(
        "--episodes",
        type=episodes_count,
        default=500,
        help=f"episodes per seed and cell, <= {MAX_EPISODES:,} (default 500)",
    )
    p.add_argument(
        "--seeds", type=seed_value, nargs="+", default=[0], help="distinct evaluation seeds >= 0 (default: 0)"
    )
    p.add_argument(
        "--cross-task",
        action="store_true",
        help="let a policy trained on one task play another (labelled NAME@TASK in the report)",
    )
    p.add_argument(
        "--splits",
        action="store_true",
        help="play every split of the team instead of the task's: the learner in k of the N pursuer slots, every k "
        "from 1 to N-1 and every seat set (14 for 4 pursuers), --episodes each; prints one row per k",
    )
    p.add_argument("--out-dir", type=Path, default=Path("eval_out"), help="output folder (default eval_out)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--tracking-uri",
        default=None,
        help="also record the result as a run of the MLflow experiment 'evaluate' in this store (e.g. "
        "sqlite:///mlflow.db)",
    )
    add_member_location(p)
    return p


def run_evaluate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from atdrone.config import load_task
    from atdrone.policies.zoo import ZOO_NAMES, load_zoo
    from atdrone.resolve import resolve
    from atdrone.teams.evaluation import evaluate_grid, task_fit
    from atdrone.teams.protocols import is_protocol, load_protocol
    from atdrone.teams.reports import format_table, write_report

    if len(set(args.seeds)) != len(args.seeds):
        raise UserError(f"--seeds: each seed once, got {args.seeds} (a repeated seed replays the same episodes)")
    found = resolve(args.policy, db=args.db, run=args.run, runs_dir=args.runs_dir)
    task_arg = args.task or found.task or "4p2e1o"
    tasks = [load_task(t) for t in (TASK_NAMES if task_arg == "all" else [task_arg])]
    one_task = tasks[0] if len(tasks) == 1 else None  # with --task all, each task's drones are found per cell
    names = ZOO_NAMES if args.zoo == "all" else [args.zoo]
    protocols = [load_protocol(z) if is_protocol(z) else None for z in names]  # a protocol plays its zoo
    zoos = [load_zoo(p.zoo if p else z, one_task) for z, p in zip(names, protocols, strict=True)]
    learner = found.policy()
    notes = task_fit(learner, tasks, cross_task=args.cross_task)
    for note in notes:
        print(f"atdrone evaluate: warning: {note}", file=sys.stderr)
    trained_on = getattr(learner, "task", "")
    if trained_on and any(t.name != trained_on for t in tasks):
        learner.name = f"{learner.name}@{trained_on}"  # every record names the task it was trained on
    playable = [z for z in zoos if not z.missing]
    if not playable:  # nothing to play: the user's zoo is incomplete, one line and status 2
        missing = "; ".join(f"zoo {z.name} is missing {', '.join(z.missing)}" for z in zoos)
        raise UserError(f"no zoo has all its members ({missing}); nothing to evaluate")
    for zoo in zoos:
        if zoo.missing:
            print(
                f"atdrone evaluate: warning: zoo {zoo.name} is missing {', '.join(zoo.missing)}; its cells are skipped",
                file=sys.stderr,
            )
    label = "".join(c if c.isalnum() or c in "._-" else "_" for c in found.label)
    task_part = "all" if task_arg == "all" else tasks[0].name
    zoo_part = "all" if args.zoo == "all" else (protocols[0] or zoos[0]).name
    stem = f"{label}_{task_part}_{zoo_part}"
    if args.splits:
        return _run_splits(args, learner, tasks, zoos, protocols, stem)
    total = len(tasks) * len(playable) * args.episodes * len(args.seeds)
    cells: list[Any] = []
    with tqdm(total=total, unit="ep", desc="evaluate", file=sys.stderr, disable=args.no_progress) as bar:
        for task in tasks:  # the report is rewritten after each cell: a long grid keeps what it has played
            for zoo, protocol in zip(zoos, protocols, strict=True):
                cells += evaluate_grid(
                    learner,
                    [task],
                    [zoo],
                    args.episodes,
                    args.seeds,
                    on_progress=bar.update,
                    cross_task=args.cross_task,
                    protocol=protocol,
                )
                json_path, csv_path = write_report(args.out_dir, stem, cells, args.policy, args.episodes, args.seeds)
    print(format_table(cells, args.policy, args.episodes, args.seeds))
    for cell in cells:  # a protocol's team events: before / after the first event, recovery time
        if cell.evaluation is not None and cell.evaluation.protocol:
            print(f"\n{cell.task} {cell.zoo}: " + ", ".join(_event_line(cell.evaluation)))
    print(f"\nwrote {json_path} and {csv_path}")
    if args.tracking_uri:
        from atdrone.teams.reports import report_document
        from atdrone.tracking import record_evaluation

        document = report_document(cells, args.policy, args.episodes, args.seeds)
        run_id, link = record_evaluation(document, [json_path, csv_path], stem, args.tracking_uri)
        print(f"MLflow run {run_id} (experiment 'evaluate'): {link}")
    return 0


def _event_line(evaluation: Any) -> list[str]:
    """Each event metric of an evaluation with its 95 % interval, as text."""
    from atdrone.teams.protocols import EVENT_METRICS

    value, interval = evaluation.pooled, evaluation.interval
    unit = lambda m: " steps" if m == "REC" else " %"
    return [f"{m} {value[m]:.1f}{unit(m)} [{interval[m][0]:.1f}, {interval[m][1]:.1f}]" for m in EVENT_METRICS]


def _run_splits(
    args: argparse.Namespace, learner: Any, tasks: list[Any], zoos: list[Any], protocols: list[Any], stem: str
) -> int:
    """``--splits``: every seat set of every task x zoo; the per-k table printed, and written as
    ``<stem>_splits.csv`` (one row per task, zoo, k) and ``<stem>_splits_episodes.csv`` (every episode)."""
    import pandas as pd
    from tqdm import tqdm

    from atdrone.fileio import atomic_write_text
    from atdrone.teams.splits import evaluate_splits, seat_assignments

    cells = [(t, z, p) for t in tasks for z, p in zip(zoos, protocols, strict=True) if not z.missing]
    seat_sets = sum(len(seat_assignments(t.players.num_p)) for t, _, _ in cells)
    tables, episodes = [], []
    with tqdm(
        total=seat_sets * args.episodes * len(args.seeds),
        unit="ep",
        desc="splits",
        file=sys.stderr,
        disable=args.no_progress,
    ) as bar:
        for task, zoo, protocol in cells:
            split = evaluate_splits(
                learner,
                task,
                zoo,
                args.episodes,
                args.seeds,
                protocol=protocol,
                cross_task=args.cross_task,
                on_progress=bar.update,
            )
            table = split.per_k().reset_index()
            table.insert(0, "zoo", (protocol or zoo).name)
            table.insert(0, "task", task.name)
            tables.append(table)
            records = split.records()
            records.insert(0, "zoo", (protocol or zoo).name)
            records.insert(0, "task", task.name)
            episodes.append(records)
    table = pd.concat(tables, ignore_index=True)
    print(table.to_string(index=False, float_format=lambda v: f"{v:.1f}"))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    per_k = atomic_write_text(args.out_dir / f"{stem}_splits.csv", table.to_csv(index=False))
    every = atomic_write_text(
        args.out_dir / f"{stem}_splits_episodes.csv", pd.concat(episodes, ignore_index=True).to_csv(index=False)
    )
    print(f"\nwrote {per_k} and {every}")
    return 0
