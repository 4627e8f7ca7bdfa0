"""Learning benchmark: self-play IPPO on 4p2e1o to 70 % SUC within 20 minutes of wall time.

Trains with the default PPO config in one process and evaluates the deterministic policy
on --episodes self-play episodes every --eval-every updates (evaluation time counts in
the wall time). Stops at the target or the time limit; with --env-steps, at that budget
instead (the SUC there, whatever the target). Prints JSON (the curve, the time to target,
the last evaluation's SUC) and writes the learning curve PNG and the final checkpoint to --out.
Usage: python benchmarks/learning_sp.py [--minutes 20] [--target 70] [--env-steps N] [--device auto|cpu|cuda]
       [--out reports/learning_sp]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import pandas as pd


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--minutes", type=float, default=20.0)
    parser.add_argument("--target", type=float, default=70.0, help="SUC %% to reach")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--eval-every", type=int, default=40, help="updates between evaluations")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--env-steps", type=int, default=0, help="train to this budget, not to the target (0: off)")
    parser.add_argument("--out", default="reports/learning_sp")
    parser.add_argument("--ppo", default="{}", help="PPO overrides as JSON, e.g. '{\"lr\": 1e-4}'")
    parser.add_argument("--update-threads", type=int, default=2, help="torch threads of the update")
    parser.add_argument("--device", default="auto", help="the update's device: auto (CUDA when there), cpu, cuda")
    args = parser.parse_args()

    from atdrone.learn.trainer import Trainer, load_train_config, plot_curve

    out = Path(args.out)
    cfg = load_train_config(
        {
            "name": "learning_sp",
            "task": args.task,
            "seed": args.seed,
            "total_env_steps": 10**9,
            "out_dir": str(out),
            "ppo": json.loads(args.ppo),
            "update_threads": args.update_threads,
            "device": args.device,
        }
    )
    trainer = Trainer(cfg)
    start = time.perf_counter()
    rows, reached = [], None
    while time.perf_counter() - start < args.minutes * 60:
        row = trainer.update_once()
        row.update(env_steps=trainer.env_steps, wall_s=time.perf_counter() - start)
        if trainer.updates % args.eval_every == 0:
            ev = trainer.evaluate(args.episodes)
            row.update({f"eval/{k}": v for k, v in ev.items()}, wall_s=time.perf_counter() - start)
            print(json.dumps({"wall_s": round(row["wall_s"]), "env_steps": trainer.env_steps, **ev}), flush=True)
            if ev["SUC"] >= args.target and reached is None:
                reached = row["wall_s"]
        rows.append(row)
        done = trainer.env_steps >= args.env_steps if args.env_steps else reached is not None
        if done:
            break
    history = pd.DataFrame(rows)
    trainer.history = rows
    trainer.save()
    plot_curve(history, out / "curve.png", title=f"self-play IPPO on {args.task}: eval SUC ({args.episodes} episodes)")
    evals = history.dropna(subset=["eval/SUC"]) if "eval/SUC" in history else history.iloc[:0]  # none: too short
    result = {
        "benchmark": "learning_sp",
        "task": args.task,
        "target_SUC": args.target,
        "time_limit_s": args.minutes * 60,
        "reached_target": reached is not None,
        "time_to_target_s": None if reached is None else round(reached, 1),
        "best_SUC": float(evals["eval/SUC"].max()) if len(evals) else None,
        "final_SUC": float(evals["eval/SUC"].iloc[-1]) if len(evals) else None,
        "env_steps": trainer.env_steps,
        "device": str(trainer.learner.device),
        "curve": [
            {"wall_s": round(r["wall_s"]), "env_steps": int(r["env_steps"]), "SUC": r["eval/SUC"], "COL": r["eval/COL"]}
            for _, r in evals.iterrows()
        ],
        "curve_png": str(out / "curve.png"),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
