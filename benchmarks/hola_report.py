"""HOLA-Drone V2 vs HOLA-Drone V2 w/o g vs SP with the same env-step budget, evaluated on Zoo 3.

For each algorithm and seed, the population service trains on the task (default 4p2e5o);
the run's final learner is then evaluated with Zoo 3 partners (the unseen drones) by the
evaluation protocol. Prints the SUC / COL / AST / REW table as mean +- std over seeds and
writes it as JSON (and the per-run rows as CSV) to --out.
Usage: python benchmarks/hola_report.py [--task 4p2e5o] [--seeds 0 1 2] [--generations 4]
       [--updates 12] [--episodes 500] [--out reports/hola_vs_sp]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import pandas as pd

ALGORITHMS = ("hola", "hola_no_g", "sp")
METRICS = ("SUC", "COL", "AST", "REW")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e5o")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--generations", type=int, default=4)
    parser.add_argument("--updates", type=int, default=12, help="PPO updates per generation")
    parser.add_argument("--envs-per-worker", type=int, default=32)
    parser.add_argument("--episodes", type=int, default=500, help="Zoo 3 evaluation episodes per run")
    parser.add_argument("--zoo", default="zoo3")
    parser.add_argument("--out", default="reports/hola_vs_sp")
    args = parser.parse_args()

    from atdrone.policies.neural import load_policy
    from atdrone.service.driver import init_ray, run_experiment
    from atdrone.service.experiment import load_experiment
    from atdrone.teams.evaluation import evaluate

    init_ray(None, num_cpus=2)
    out = Path(args.out)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    rows = []
    for algorithm in ALGORITHMS:
        for seed in args.seeds:
            cfg = load_experiment(
                {
                    "name": f"report-{algorithm}-s{seed}-{stamp}",
                    "algorithm": algorithm,
                    "task": args.task,
                    "seed": seed,
                    "generations": args.generations,
                    "updates_per_generation": args.updates,
                    "ppo": {"num_envs": 2 * args.envs_per_worker},
                    "final_zoo": "",
                    "gif": False,
                    "out_dir": str(out / "runs"),
                }
            )
            t0 = time.perf_counter()
            summary = run_experiment(cfg, progress=False)
            final = summary["reports"][-1].learners[-1]
            policy = load_policy(Path(summary["run_dir"]) / "members" / f"{final}.pt")
            result = evaluate(policy, args.task, args.zoo, episodes=args.episodes, seeds=[seed])
            row = {"algorithm": algorithm, "seed": seed, "member": final, **result.mean}
            row["wall_s"] = time.perf_counter() - t0
            rows.append(row)
            print(json.dumps(row), flush=True)
    frame = pd.DataFrame(rows)
    table = frame.groupby("algorithm")[list(METRICS)].agg(["mean", "std"]).reindex(list(ALGORITHMS))
    env_steps = args.generations * args.updates * 2 * args.envs_per_worker * 128
    lines = [
        f"{args.task}, {env_steps} env steps per run, {len(args.seeds)} seeds, {args.zoo} partners "
        f"({args.episodes} episodes per run): mean +- std over seeds"
    ]
    lines.append(f"{'algorithm':<10} " + " ".join(f"{m:>16}" for m in METRICS))
    for algorithm in ALGORITHMS:
        cells = [
            f"{table.loc[algorithm, (m, 'mean')]:7.1f} +- {table.loc[algorithm, (m, 'std')]:5.1f}" for m in METRICS
        ]
        lines.append(f"{algorithm:<10} " + " ".join(f"{c:>16}" for c in cells))
    text = "\n".join(lines)
    print(text)
    out.mkdir(parents=True, exist_ok=True)
    from atdrone.fileio import atomic_write_bytes

    atomic_write_bytes(out / "runs.csv", frame.to_csv(index=False).encode())
    doc = {
        "task": args.task,
        "zoo": args.zoo,
        "env_steps_per_run": env_steps,
        "seeds": args.seeds,
        "table": {
            a: {m: {"mean": table.loc[a, (m, "mean")], "std": table.loc[a, (m, "std")]} for m in METRICS}
            for a in ALGORITHMS
        },
        "text": text,
    }
    atomic_write_bytes(out / "table.json", json.dumps(doc, indent=2, default=float).encode())


if __name__ == "__main__":
    main()
