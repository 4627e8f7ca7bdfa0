"""Time to 70 % SUC against PPO settings: benchmarks/learning_sp.py, paired by seed (issue 26).

Runs learning_sp.py (self-play IPPO on 4p2e1o, the default PPO config with a variant's overrides)
for every (variant, seed) whose result file is missing in --out, the variants alternating within a
seed, then prints JSON: per variant and seed the time to the target (evaluation time included; a
time is the first evaluation at or above the target, so it is quantised by --eval-env-steps), the
env steps to the target, the SUC of the first evaluation and the wall seconds per update (of the
updates before the first evaluation, its evaluation included); per variant the median and worst
time and env steps; and the paired differences against the first variant with t-based 95 %
intervals. ``--epochs 2 4`` names the variants e2 and e4 (epochs only); ``--variant NAME=JSON``
(repeatable) names any PPO overrides instead. With --env-steps N every run trains to that budget
instead of the target, and the SUC of its last evaluation (at N env steps) is compared too: what a
setting does to what is learned, not only to how soon. ``--jobs 2`` runs two at a time (with
``--update-threads 1``): the env steps to the target stay comparable, the wall times do not.
Resumable: a finished run is read back, never run again.
Usage: python benchmarks/learning_epochs.py [--epochs 2 4 | --variant mb2048='{"minibatch_size": 2048}' ...]
       [--seeds 0 1 2] [--env-steps N] [--eval-env-steps 327680] [--jobs 1] [--out reports/learning_epochs]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pandas as pd

from atdrone.benchmark.stats import paired_difference
from atdrone.config import ConfigError
from atdrone.learn.ppo import ppo_config

HERE = Path(__file__).resolve().parent


def _result(path: Path) -> dict[str, Any]:
    """The final JSON document of a learning_sp.py output (after its one-line progress records)."""
    text = path.read_text()
    return dict(json.loads(text[text.index("{\n") :]))


def _eval_every(overrides: dict[str, Any], eval_env_steps: int) -> int:
    """Updates between evaluations so that they come every ``eval_env_steps`` env steps."""
    ppo = ppo_config(overrides)
    per_update = ppo.num_envs * ppo.rollout_steps
    if eval_env_steps % per_update:
        raise SystemExit(f"--eval-env-steps {eval_env_steps} is not a multiple of an update's {per_update} env steps")
    return eval_env_steps // per_update


def run(name: str, overrides: dict[str, Any], seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """One learning_sp.py run (or its saved result): ``{name}_s{seed}[_b{budget}].json`` in --out."""
    stem = f"{name}_s{seed}" + (f"_b{args.env_steps}" if args.env_steps else "")
    path = args.out / f"{stem}.json"
    if not path.exists():
        tmp = path.with_suffix(".json.tmp")
        cmd = [sys.executable, str(HERE / "learning_sp.py"), "--seed", str(seed), "--minutes", str(args.minutes)]
        cmd += ["--ppo", json.dumps(overrides), "--out", str(args.out / stem), "--env-steps", str(args.env_steps)]
        cmd += ["--eval-every", str(_eval_every(overrides, args.eval_env_steps))]
        cmd += ["--update-threads", str(args.update_threads)]
        with tmp.open("w") as f:
            subprocess.run(cmd, stdout=f, check=True)
        tmp.replace(path)
    return _result(path)


def _row(name: str, seed: int, r: dict[str, Any], eval_every: int) -> dict[str, Any]:
    first = r["curve"][0]
    hit = [p for p in r["curve"] if p["SUC"] >= r["target_SUC"]]
    return {
        "variant": name,
        "seed": seed,
        "time_to_target_s": r["time_to_target_s"],
        "env_steps_to_target": hit[0]["env_steps"] if hit else None,
        "first_eval_SUC": round(first["SUC"], 1),
        "first_eval_env_steps": first["env_steps"],
        "s_per_update": round(first["wall_s"] / eval_every, 3),
        "final_SUC": round(r["curve"][-1]["SUC"], 1),
        "final_env_steps": r["curve"][-1]["env_steps"],
    }


def _variants(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    if not args.variant:
        return {f"e{e}": {"epochs": e} for e in args.epochs}
    variants = {}
    for item in args.variant:
        name, sep, text = item.partition("=")
        if not sep or not name:
            raise SystemExit(f"--variant {item!r}: expected NAME=JSON")
        overrides = json.loads(text)
        try:
            ppo_config(overrides)  # an unknown field or a value out of bounds fails here, before any run
        except ConfigError as exc:
            raise SystemExit(f"--variant {name}: {exc}") from None
        variants[name] = overrides
    return variants


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, nargs="+", default=[2, 4])
    parser.add_argument("--variant", action="append", default=[], help="NAME=JSON PPO overrides (repeatable)")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--minutes", type=float, default=8.0, help="time limit of one run")
    parser.add_argument("--env-steps", type=int, default=0, help="train every run to this budget (0: to the target)")
    parser.add_argument("--eval-env-steps", type=int, default=327_680, help="env steps between evaluations")
    parser.add_argument("--update-threads", type=int, default=2, help="torch threads of each run's update")
    parser.add_argument("--jobs", type=int, default=1, help="runs at a time")
    parser.add_argument("--out", type=Path, default=Path("reports/learning_epochs"))
    args = parser.parse_args()
    variants = _variants(args)
    args.out.mkdir(parents=True, exist_ok=True)
    order = [(name, seed) for seed in args.seeds for name in variants]
    with ThreadPoolExecutor(max_workers=args.jobs) as pool:
        results = list(pool.map(lambda key: run(key[0], variants[key[0]], key[1], args), order))
    rows = [
        _row(name, seed, r, _eval_every(variants[name], args.eval_env_steps))
        for (name, seed), r in zip(order, results, strict=True)
    ]
    table = pd.DataFrame(rows)
    per_variant = {}
    for name in variants:
        g = table[table["variant"] == name]
        times = g["time_to_target_s"].astype(float)
        steps = g["env_steps_to_target"].astype(float)
        per_variant[name] = {
            "ppo": variants[name],
            "median_time_s": float(times.median()),
            "worst_time_s": float(times.max()),
            "median_env_steps": float(steps.median()),
            "worst_env_steps": float(steps.max()),
            "reached": int(times.notna().sum()),
            "first_eval_SUC_mean": round(float(g["first_eval_SUC"].mean()), 1),
            "first_eval_SUC_std": round(float(g["first_eval_SUC"].std(ddof=1)), 1),
            "s_per_update_mean": round(float(g["s_per_update"].mean()), 3),
            "final_SUC_mean": round(float(g["final_SUC"].mean()), 1),
            "final_SUC_std": round(float(g["final_SUC"].std(ddof=1)), 1),
        }
    names = list(variants)
    base = table[table["variant"] == names[0]].set_index("seed")
    metrics = ["time_to_target_s", "env_steps_to_target", "first_eval_SUC", "s_per_update", "final_SUC"]
    paired = {
        f"{name}-{names[0]}": paired_difference(
            table[table["variant"] == name].set_index("seed")[metrics].astype(float),
            base[metrics].astype(float),
            metrics,
        )
        for name in names[1:]
    }
    print(
        json.dumps(
            {
                "benchmark": "learning_epochs",
                "task": "4p2e1o",
                "target_SUC": 70.0,
                "env_steps": args.env_steps or None,
                "eval_env_steps": args.eval_env_steps,
                "update_threads": args.update_threads,
                "jobs": args.jobs,
                "runs": rows,
                "per_variant": per_variant,
                "paired_vs_first": paired,
                "note": f"time to target is quantised by the evaluations every {args.eval_env_steps} env steps"
                " (500 episodes each)",
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
