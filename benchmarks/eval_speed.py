"""Evaluation speed: greedy-learner episodes (greedy learner + zoo partners) per second.

Prints JSON. Usage: python benchmarks/eval_speed.py [--task 4p2e1o] [--zoo zoo1] [--episodes 1000] [--seed 0]
The target (issue 3): 1,000 episodes of 4p2e1o in under 30 s on the 2-core machine.
The time is one call of ``atdrone.teams.evaluation.evaluate``, imports excluded.

With ``--reference DIR`` (a checkout of another commit, e.g. ``git worktree add
/tmp/ref-b1d060d b1d060d``) it runs this script's measurement with this tree's and
with the reference's atdrone in alternating subprocess rounds (round r plays seed ``--seed`` + r in both
trees, for every ``--zoos`` zoo), each with its code first on PYTHONPATH, and prints
episodes/s of both, the ratio this / reference, and both trees' metrics with their
spread over seeds and a z-score of the difference (issue 26: evaluation that stops
at the end, at least 2x faster, metrics within noise).
Usage: python benchmarks/eval_speed.py --reference /tmp/ref-b1d060d [--rounds 5] [--zoos zoo1 zoo2]
(issue 26's run: OMP_NUM_THREADS=1, so that zoo2's networks do not fight for a busy machine's two cores).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

TARGET_SECONDS = 30.0
HERE = Path(__file__).resolve().parent.parent
METRICS = ("SUC", "COL", "AST", "REW")


def measure(task: str, zoo: str, episodes: int, seed: int) -> dict[str, Any]:
    """One timed evaluation in this process."""
    import atdrone
    from atdrone.policies import GreedyPolicy
    from atdrone.teams.evaluation import evaluate

    start = time.perf_counter()
    result = evaluate(GreedyPolicy(), task, zoo, episodes=episodes, seeds=(seed,))
    wall = time.perf_counter() - start
    records = result.records
    success = records["success"].to_numpy(bool)
    return {
        "benchmark": "eval_speed",
        "task": task,
        "zoo": zoo,
        "learner": "greedy",
        "episodes": len(records),
        "seed": seed,
        "wall_seconds": round(wall, 2),
        "episodes_per_second": round(len(records) / wall, 1),
        "env_steps": int(records["length"].sum()),
        "steps_of_longest_episode": int(records["length"].max()),
        "metrics": {k: round(v, 2) for k, v in result.mean.items()},
        # for the comparison's standard errors
        "spread": {
            "AST_sd": float(records["length"][success].std(ddof=1)) if success.sum() > 1 else float("nan"),
            "REW_sd": float(records["return"].std(ddof=1)),
            "successes": int(success.sum()),
        },
        "atdrone": str(Path(atdrone.__file__).resolve().parent),
        "machine": {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()},
        "cpus": os.cpu_count(),
        "target": {"episodes": 1000, "wall_seconds_below": TARGET_SECONDS},
        "meets_target": bool(wall < TARGET_SECONDS * len(records) / 1000),
    }


def _run_tree(tree: Path, task: str, zoo: str, episodes: int, seed: int) -> dict[str, Any]:
    """This script's :func:`measure` in a subprocess, with the tree's atdrone first on the path."""
    cmd = [sys.executable, str(Path(__file__).resolve()), "--task", task, "--zoo", zoo]
    cmd += ["--episodes", str(episodes), "--seed", str(seed)]
    out = subprocess.run(cmd, cwd=tree, env={**os.environ, "PYTHONPATH": str(tree)}, capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(f"{tree}: {out.stderr.strip().splitlines()[-1:]}")
    run = json.loads(out.stdout)
    if not Path(run["atdrone"]).is_relative_to(tree):
        raise RuntimeError(f"the run for {tree} imported atdrone from {run['atdrone']}")
    return run


def _summary(runs: list[dict[str, Any]]) -> dict[str, Any]:
    """Speed and metrics of one tree over its rounds: per-seed values, mean and std over seeds."""
    rates = [r["episodes_per_second"] for r in runs]
    per_seed = {m: [r["metrics"][m] for r in runs] for m in METRICS}
    return {
        "episodes_per_second": rates,
        "wall_seconds": [r["wall_seconds"] for r in runs],
        "env_steps": [r["env_steps"] for r in runs],
        "steps_of_longest_episode": [r["steps_of_longest_episode"] for r in runs],
        "mean_episodes_per_second": round(float(np.mean(rates)), 1),
        "metrics_per_seed": per_seed,
        "metrics_mean": {m: round(float(np.nanmean(v)), 2) for m, v in per_seed.items()},
        "metrics_std_over_seeds": {m: round(float(np.nanstd(v)), 2) for m, v in per_seed.items()},
    }


def _z_scores(this: list[dict[str, Any]], ref: list[dict[str, Any]]) -> dict[str, float]:
    """Difference this - reference of each metric over all their episodes, in standard errors.

    SUC and COL: two-proportion z; AST and REW: difference of means over its standard
    error from the per-episode spread (pooled over seeds).
    """

    def pooled(runs: list[dict[str, Any]]) -> dict[str, float]:
        n = sum(r["episodes"] for r in runs)
        succ = sum(r["spread"]["successes"] for r in runs)
        mean = {m: sum(r["metrics"][m] * r["episodes"] for r in runs) / n for m in ("SUC", "COL", "REW")}
        mean["AST"] = sum(r["metrics"]["AST"] * r["spread"]["successes"] for r in runs) / max(succ, 1)
        se2 = {
            "SUC": mean["SUC"] * (100 - mean["SUC"]) / n,
            "COL": mean["COL"] * (100 - mean["COL"]) / n,
            "REW": float(np.mean([r["spread"]["REW_sd"] ** 2 for r in runs])) / n,
            "AST": float(np.mean([r["spread"]["AST_sd"] ** 2 for r in runs])) / max(succ, 1),
        }
        return {**{m: mean[m] for m in METRICS}, **{f"{m}_se2": se2[m] for m in METRICS}}

    a, b = pooled(this), pooled(ref)
    return {m: round((a[m] - b[m]) / max(np.sqrt(a[f"{m}_se2"] + b[f"{m}_se2"]), 1e-12), 2) for m in METRICS}


def compare(reference: Path, task: str, zoos: list[str], episodes: int, seed: int, rounds: int) -> dict[str, Any]:
    """Alternating rounds of both trees; speed ratio and metrics per zoo."""
    runs: dict[str, dict[str, list[dict[str, Any]]]] = {z: {"this": [], "reference": []} for z in zoos}
    for r in range(rounds):
        for zoo in zoos:
            for name, tree in (
                (("reference", reference), ("this", HERE)) if r % 2 else (("this", HERE), ("reference", reference))
            ):
                runs[zoo][name].append(_run_tree(tree, task, zoo, episodes, seed + r))
                print(f"round {r} {zoo} {name}: {runs[zoo][name][-1]['wall_seconds']} s", file=sys.stderr)
    out: dict[str, Any] = {}
    for zoo in zoos:
        this, ref = _summary(runs[zoo]["this"]), _summary(runs[zoo]["reference"])
        ratios = [a / b for a, b in zip(this["episodes_per_second"], ref["episodes_per_second"], strict=True)]
        out[zoo] = {
            "this": this,
            "reference": ref,
            "ratio_this_over_reference": round(this["mean_episodes_per_second"] / ref["mean_episodes_per_second"], 2),
            "ratio_per_round": [round(x, 2) for x in ratios],
            "metric_difference_z": _z_scores(runs[zoo]["this"], runs[zoo]["reference"]),
        }
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--zoo", default="zoo1")
    parser.add_argument("--episodes", type=int, default=1000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--reference", type=Path, default=None, help="another checkout to compare with")
    parser.add_argument("--rounds", type=int, default=5, help="alternating rounds (seeds) per tree with --reference")
    parser.add_argument("--zoos", nargs="+", default=["zoo1", "zoo2"], help="zoos to compare with --reference")
    args = parser.parse_args()
    if args.reference is None:
        print(json.dumps(measure(args.task, args.zoo, args.episodes, args.seed), indent=2))
        return
    ref = args.reference.resolve()
    result = {
        "benchmark": "eval_speed",
        "task": args.task,
        "learner": "greedy",
        "episodes": args.episodes,
        "seeds": list(range(args.seed, args.seed + args.rounds)),
        "this": subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=HERE, capture_output=True, text=True
        ).stdout.strip(),
        "reference": str(ref),
        "reference_commit": subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], cwd=ref, capture_output=True, text=True
        ).stdout.strip(),
        "rounds": args.rounds,
        "target_ratio": 2.0,
        "zoos": compare(ref, args.task, args.zoos, args.episodes, args.seed, args.rounds),
        "machine": {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()},
        "cpus": os.cpu_count(),
        "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),  # torch's threads in both trees' subprocesses
        "load_average_at_end": [round(x, 2) for x in os.getloadavg()],
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
