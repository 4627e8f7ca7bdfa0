"""HOLA-Drone V2's min step on real policies: its hyperedges played one match at a time against all in one batch.

    python benchmarks/hola_eval_batch.py [--task 4p2e5o] [--members 8] [--episodes 32] [--rounds 3]

G'_t of one learner and ``--members`` partners of the task's training pool and validation zoo (every pair: 28 hyperedges
with 8), ``--episodes`` episodes a hyperedge, as a rollout worker plays them: one ``run_episodes`` per
hyperedge (the reference), or one ``evaluate_lineups`` for all. Both in one process, alternating rounds,
one torch thread. Prints JSON: env steps per second of each and the median time ratio (one at a time /
batched), and whether both played the same episodes (same metrics).
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import time

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e5o")
    parser.add_argument("--members", type=int, default=8)
    parser.add_argument("--episodes", type=int, default=32)
    parser.add_argument("--rounds", type=int, default=3)
    args = parser.parse_args()
    import torch

    from atdrone.config import load_task
    from atdrone.policies.zoo import load_zoo
    from atdrone.teams.evaluation import metrics, run_episodes
    from atdrone.teams.lineups import evaluate_lineups
    from atdrone.teams.pools import load_pool

    torch.set_num_threads(1)
    task = load_task(args.task)
    # the training pool, then the validation zoo's members: as many distinct policies as asked
    pool = load_pool("train_pool").resolve(task).policies() + load_zoo("validation").resolve(task).policies()
    if len(pool) < args.members + 1:
        parser.error(f"--members: at most {len(pool) - 1} on {args.task}")
    learner, partners = pool[0], pool[1 : 1 + args.members]
    slots = task.players.num_unctrl
    lineups = [list(c) for c in itertools.combinations(range(len(partners)), slots)]
    counts = [args.episodes] * len(lineups)

    def one_at_a_time() -> tuple[list[dict[str, float]], int]:
        out, steps = [], 0
        for i, lineup in enumerate(lineups):
            plan = np.tile(lineup, (args.episodes, 1))
            rec = run_episodes(learner, task, partners, args.episodes, seed=i, lineups=plan)
            out.append(metrics(rec))
            steps += int(rec["length"].sum())
        return out, steps

    def batched() -> tuple[list[dict[str, float]], int]:
        out = evaluate_lineups(learner, task, partners, lineups, counts, seed=0)
        return out, sum(int(r["steps"]) for r in out)

    rates: dict[str, list[float]] = {"one_at_a_time": [], "batched": []}
    seconds: dict[str, list[float]] = {"one_at_a_time": [], "batched": []}
    for _ in range(args.rounds):
        for name, fn in (("one_at_a_time", one_at_a_time), ("batched", batched)):
            start = time.perf_counter()
            _, steps = fn()
            elapsed = time.perf_counter() - start
            seconds[name].append(elapsed)
            rates[name].append(steps / elapsed)
    ratios = [a / b for a, b in zip(seconds["one_at_a_time"], seconds["batched"], strict=True)]
    print(
        json.dumps(
            {
                "benchmark": "hola_eval_batch",
                "task": args.task,
                "hyperedges": len(lineups),
                "episodes_per_hyperedge": args.episodes,
                "env_steps_per_s": {k: round(statistics.median(v)) for k, v in rates.items()},
                "seconds": {k: [round(s, 2) for s in v] for k, v in seconds.items()},
                "median_time_ratio": round(statistics.median(ratios), 2),
            },
            indent=1,
        )
    )


if __name__ == "__main__":
    main()
