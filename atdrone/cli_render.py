"""``atdrone render`` and ``atdrone gallery``: episodes drawn to GIFs."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from atdrone.cli_args import POLICY_HELP, add_episode_args, format_summary
from atdrone.cli_registry import add_member_location
from atdrone.config import TASK_NAMES
from atdrone.fileio import output_file


def add_render(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "render",
        help="render one episode to a GIF",
        description="Run one episode and save it as a GIF. Every pursuer follows --policy (default: the built-in "
        "chase-the-nearest-evader policy); with --zoo the policy drives the task's learner slots and partners drawn "
        "from the zoo (drawn green) the others.",
    )
    p.add_argument(
        "--task",
        default=None,
        help=f"task name ({', '.join(TASK_NAMES)}) or JSON path (default: the policy's task, else 4p2e5o)",
    )
    p.add_argument("--policy", default=None, help=f"{POLICY_HELP} (default: built-in chase)")
    p.add_argument("--zoo", default=None, help="fill the partner slots from this zoo (zoo1-zoo4, validation, a path)")
    p.add_argument("--out", type=Path, default=None, help="GIF path, *.gif (default: <task>.gif)")
    p.add_argument("--png", type=Path, default=None, help="also save the first frame as this PNG, *.png")
    add_episode_args(p)
    add_member_location(p)
    return p


def run_render(args: argparse.Namespace) -> int:
    from atdrone.config import load_task
    from atdrone.envs.render import save_gif, save_png
    from atdrone.policies.zoo import load_zoo
    from atdrone.resolve import resolve
    from atdrone.teams.replay import record_episode

    if args.out is not None:
        output_file(args.out, (".gif",))
    if args.png is not None:
        output_file(args.png, (".png",), "--png")
    found = resolve(args.policy, db=args.db, run=args.run, runs_dir=args.runs_dir) if args.policy else None
    cfg = load_task(args.task or (found.task if found is not None and found.task else "4p2e5o"))
    zoo = load_zoo(args.zoo, cfg) if args.zoo is not None else None
    policy = found.policy() if found is not None else None
    partners = zoo.policies() if zoo is not None else None
    frames, summary = record_episode(
        cfg, args.seed, policy=policy, partners=partners, max_steps=args.max_steps, frame_every=args.frame_every
    )
    out = save_gif(frames, args.out if args.out is not None else Path(f"{cfg.name}.gif"), fps=args.fps)
    print(f"wrote {out} ({len(frames)} frames)")
    if args.png is not None:
        print(f"wrote {save_png(frames[0], args.png)}")
    print(format_summary(summary))
    return 0


# --------------------------------------------------------------- gallery
DEMO_TASKS = ("4p2e1o", "4p2e3o", "4p2e5o", "4p3e5o")


def add_gallery(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "gallery",
        help="render an episode of each of the four tasks (the built-in chase policy)",
        description="Render one episode of each paper task to <out-dir>/<task>.gif and print a summary table. "
        "(`make demo` is something else: it trains a population.)",
    )
    p.add_argument("--out-dir", type=Path, default=Path("gallery"), help="output folder (default gallery)")
    add_episode_args(p)
    return p


def run_gallery(args: argparse.Namespace) -> int:
    from atdrone.envs.render import save_gif
    from atdrone.teams.replay import record_episode

    rows = []
    for n, task in enumerate(DEMO_TASKS, 1):
        print(f"[{n}/{len(DEMO_TASKS)}] {task}: running and drawing an episode ...", flush=True)
        frames, summary = record_episode(task, args.seed, max_steps=args.max_steps, frame_every=args.frame_every)
        out = save_gif(frames, args.out_dir / f"{task}.gif", fps=args.fps)
        print(f"[{n}/{len(DEMO_TASKS)}] {task}: {summary['outcome']} after {summary['steps']} steps -> {out}")
        rows.append(summary)
    print()
    print(f"{'task':<8} {'outcome':<10} {'steps':>6} {'return':>8} {'captured':>9}")
    for s in rows:
        captured = f"{s['captured']}/{s['num_e']}"
        print(f"{s['task']:<8} {s['outcome']:<10} {s['steps']:>6} {s['return']:>8.2f} {captured:>9}")
    print(f"\nGIFs in {args.out_dir}/ (seed {args.seed}, built-in chase policy)")
    return 0
