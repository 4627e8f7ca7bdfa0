"""Evaluation speed: greedy-team episodes (greedy learner + zoo1 partners) per second.

Prints JSON. Usage: python benchmarks/eval_speed.py [--task 4p2e1o] [--episodes 1000] [--seed 0]
The target (issue 3): 1,000 episodes of 4p2e1o in under 30 s on the 2-core machine.
The time is one call of ``atdrone.teams.evaluation.evaluate`` (all episodes in parallel on
one BatchedPursuit), imports excluded.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

TARGET_SECONDS = 30.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--zoo", default="zoo1")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    from atdrone.policies import GreedyPolicy
    from atdrone.teams.evaluation import evaluate

    start = time.perf_counter()
    result = evaluate(GreedyPolicy(), args.task, args.zoo, episodes=args.episodes, seeds=(args.seed,))
    wall = time.perf_counter() - start
    records = result.records
    out = {
        "benchmark": "eval_speed",
        "task": args.task,
        "zoo": args.zoo,
        "learner": "greedy",
        "episodes": len(records),
        "seed": args.seed,
        "wall_seconds": round(wall, 2),
        "episodes_per_second": round(len(records) / wall, 1),
        "env_steps": int(records["length"].sum()),
        "steps_of_longest_episode": int(records["length"].max()),
        "metrics": {k: round(v, 2) for k, v in result.mean.items()},
        "machine": {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()},
        "cpus": os.cpu_count(),
        "target": {"episodes": 1000, "wall_seconds_below": TARGET_SECONDS},
        "meets_target": bool(wall < TARGET_SECONDS * len(records) / 1000),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
