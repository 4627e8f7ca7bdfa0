"""Evaluation on one torch thread against torch's default (one per core): wall time, CPU time, metrics.

Each round plays the same evaluation (a published weight with a zoo's partners, one seed) in a subprocess of its own
twice, once on one torch thread and once on torch's default, in alternating order; prints JSON with the median
wall and CPU seconds of each, their ratios (one thread / default), and whether the two played the same metrics
to the last bit. ``atdrone evaluate`` keeps torch's default; the benchmark's cells evaluate on one thread.
Measure on an otherwise idle machine.

Usage: python benchmarks/eval_threads.py [--policy weights:sp/4p2e1o] [--task 4p2e1o] [--zoo zoo1]
       [--episodes 300] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent.parent


def measure(policy: str, task: str, zoo: str, episodes: int, threads: int) -> dict[str, Any]:
    """One evaluation in this process on ``threads`` torch threads (0: torch's default); its times and metrics."""
    import torch

    from atdrone.resolve import resolve_policy
    from atdrone.teams.evaluation import evaluate

    if threads:
        torch.set_num_threads(threads)
    learner = resolve_policy(policy)
    wall, cpu = time.perf_counter(), time.process_time()
    result = evaluate(learner, task, zoo, episodes=episodes, seeds=(0,))
    return {
        "threads": torch.get_num_threads(),
        "wall_s": time.perf_counter() - wall,
        "cpu_s": time.process_time() - cpu,
        "metrics": {k: float(v) for k, v in result.mean.items()},
    }


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--policy", default="weights:sp/4p2e1o")
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--zoo", default="zoo1")
    parser.add_argument("--episodes", type=int, default=300)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--one", type=int, default=None, help=argparse.SUPPRESS)  # a subprocess's measurement
    args = parser.parse_args(argv)
    if args.one is not None:
        print(json.dumps(measure(args.policy, args.task, args.zoo, args.episodes, args.one)))
        return
    runs: dict[str, list[dict[str, Any]]] = {"one": [], "default": []}
    for r in range(args.rounds):
        order = [("one", 1), ("default", 0)] if r % 2 == 0 else [("default", 0), ("one", 1)]
        for label, threads in order:
            cmd = [sys.executable, __file__, "--policy", args.policy, "--task", args.task, "--zoo", args.zoo]
            cmd += ["--episodes", str(args.episodes), "--one", str(threads)]
            env = {k: v for k, v in os.environ.items() if k != "OMP_NUM_THREADS"}  # torch's own default
            out = subprocess.run(cmd, cwd=HERE, env=env, capture_output=True, text=True, check=True)
            runs[label].append(json.loads(out.stdout.strip().splitlines()[-1]))
    median = {k: {m: statistics.median(x[m] for x in v) for m in ("wall_s", "cpu_s")} for k, v in runs.items()}
    print(
        json.dumps(
            {
                "benchmark": "eval_threads",
                "policy": args.policy,
                "task": args.task,
                "zoo": args.zoo,
                "episodes": args.episodes,
                "rounds": args.rounds,
                "cpus": os.cpu_count(),
                "default_threads": runs["default"][0]["threads"],
                "median": {k: {m: round(s, 2) for m, s in v.items()} for k, v in median.items()},
                "ratio_one_vs_default": {
                    m: round(median["one"][m] / median["default"][m], 3) for m in ("wall_s", "cpu_s")
                },
                "same_metrics": all(x["metrics"] == runs["one"][0]["metrics"] for v in runs.values() for x in v),
                "date": time.strftime("%Y-%m-%d"),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
