"""Ray job entrypoint: evaluate a policy with zoos of unseen partners on tasks.

    ray job submit --address http://HEAD:8265 --working-dir . -- \
        python jobs/evaluate.py --policy greedy|vicsek|PATH --task 4p2e1o|all --zoo zoo1|all \
            --episodes 500 --out-dir DIR

The same protocol and files as ``atdrone evaluate``: every task x zoo cell plays
--episodes episodes per seed with the policy in the task's learner slots and partners
drawn from the zoo (``atdrone.teams.evaluation.evaluate_grid``); prints the SUC / COL / AST /
REW table and writes ``DIR/<policy>_<task>_<zoo>.json`` (per cell: summary and per-seed
metrics) and ``.csv`` (one row per episode) through ``atdrone.teams.reports``. It runs in the
job's driver process; on a cluster give --out-dir an absolute path you can read afterwards.
Bad input exits with status 2 and a one-line error; SIGTERM (``ray job stop``) and SIGINT end it
with one line (the command that runs it again) and status 143 and 130.
"""

from __future__ import annotations

import argparse
import re
import shlex
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:  # `--working-dir .` on nodes that only have the dependencies
    sys.path.insert(0, str(REPO_ROOT))

PROG = "jobs/evaluate.py"
EXIT_USAGE = 2


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--policy",
        required=True,
        help="the learner: a rule (greedy, vicsek), a registry member id, models:/NAME@alias, a checkpoint PATH "
        "or a zoo member",
    )
    p.add_argument("--task", default="4p2e1o", help="task name (4p2e1o, 4p2e3o, 4p2e5o, 4p3e5o), JSON path, or all")
    p.add_argument("--zoo", default="zoo1", help="zoo name (zoo1-zoo4, validation), JSON path, or all (zoo1-zoo4)")
    p.add_argument("--episodes", type=_positive_int, default=500, help="episodes per seed and cell (default 500)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="evaluation seeds (default: 0)")
    p.add_argument("--cross-task", action="store_true", help="let a policy trained on one task play another")
    p.add_argument("--out-dir", type=Path, default=Path("eval_out"), help="output folder (default eval_out)")
    return p


def _fail(message: object) -> int:
    print(f"{PROG}: error: {message}".splitlines()[0], file=sys.stderr)
    return EXIT_USAGE


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from atdrone.errors import interrupt_exit_code, interrupt_on_signals, interrupted

    interrupt_on_signals()  # SIGTERM as Ctrl-C: one line, not a traceback (nor a silent kill)
    try:
        return _evaluate(args)
    except BaseException as exc:
        if not interrupted(exc):
            raise
        again = shlex.join(["python", PROG, *(argv if argv is not None else sys.argv[1:])])
        print(
            f"{PROG}: interrupted; the report is written once every cell has played; run it again with: {again}",
            file=sys.stderr,
        )
        return interrupt_exit_code(exc)


def _evaluate(args: argparse.Namespace) -> int:
    """Play every cell, print the table and write the report (the module docstring); the exit status."""
    from atdrone.config import TASK_NAMES, ConfigError, load_task
    from atdrone.policies.zoo import ZOO_NAMES, PolicyError, load_zoo
    from atdrone.resolve import resolve
    from atdrone.teams.evaluation import evaluate_grid, task_fit
    from atdrone.teams.reports import format_table, write_report

    try:
        tasks = [load_task(t) for t in (TASK_NAMES if args.task == "all" else [args.task])]
        one_task = tasks[0] if len(tasks) == 1 else None  # with --task all, each task's drones are found per cell
        zoos = [load_zoo(z, one_task) for z in (ZOO_NAMES if args.zoo == "all" else [args.zoo])]
        found = resolve(args.policy)  # a rule, member id, models:/ URI, checkpoint file or zoo member
        learner = found.policy()
        task_fit(learner, tasks, cross_task=args.cross_task)  # a policy of another task only when asked
    except (ConfigError, PolicyError) as exc:
        return _fail(exc)
    for zoo in zoos:
        if zoo.missing:
            print(f"{PROG}: warning: zoo {zoo.name} is missing {', '.join(zoo.missing)}; skipped", file=sys.stderr)
    if all(zoo.missing for zoo in zoos):
        return _fail(f"no zoo has all its members ({', '.join(z.name for z in zoos)}); nothing to evaluate")
    cells = evaluate_grid(learner, tasks, zoos, args.episodes, args.seeds, cross_task=args.cross_task)
    print(format_table(cells, args.policy, args.episodes, args.seeds))
    label = re.sub(r"[^A-Za-z0-9._-]+", "_", Path(found.label).stem if found.kind == "checkpoint" else found.label)
    stem = f"{label}_{'all' if args.task == 'all' else tasks[0].name}_{'all' if args.zoo == 'all' else zoos[0].name}"
    try:
        json_path, csv_path = write_report(args.out_dir, stem, cells, args.policy, args.episodes, args.seeds)
    except OSError as exc:
        print(f"{PROG}: error: cannot write the report to {args.out_dir}: {exc}", file=sys.stderr)
        return 1
    played = [c for c in cells if c.evaluation is not None]
    episodes = sum(len(c.evaluation.records) for c in played if c.evaluation is not None)
    print(f"\n{PROG}: {label} evaluated on {len(played)} of {len(cells)} task x zoo cells, {episodes} episodes")
    print(f"wrote {json_path} and {csv_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
