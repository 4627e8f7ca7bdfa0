"""Time to 70 % SUC against the PPO epochs per update: benchmarks/learning_sp.py, paired by seed (issue 26).

Runs learning_sp.py (self-play IPPO on 4p2e1o, the default PPO config but ``epochs``) for every
(epochs, seed) whose result file is missing in --out, the epochs alternating within a seed, then
prints JSON: per epochs value and seed the time to the target (evaluation time included; the
evaluations come every 40 updates, so a time is the first evaluation at or above the target),
the SUC of the first evaluation (40 updates, 327,680 env steps) and the wall seconds per update
(of the first 40 updates, their evaluation included);
per value the median and worst time; and the paired differences against the first value with
t-based 95 % intervals. With --env-steps N every run trains to that budget instead of the target, and
the SUC of its last evaluation (at N env steps) is compared too: what the epochs do to what is learned,
not only to how soon. Resumable: a finished run is read back, never run again.
Usage: python benchmarks/learning_epochs.py [--epochs 2 4] [--seeds 0 1 2] [--env-steps N]
       [--out reports/learning_epochs]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import pandas as pd

from atdrone.benchmark.stats import paired_difference

HERE = Path(__file__).resolve().parent


def _result(path: Path) -> dict:
    """The final JSON document of a learning_sp.py output (after its one-line progress records)."""
    text = path.read_text()
    return json.loads(text[text.index("{\n") :])


def run(epochs: int, seed: int, out: Path, minutes: float, env_steps: int = 0) -> dict:
    name = f"e{epochs}_s{seed}" + (f"_b{env_steps}" if env_steps else "")
    path = out / f"{name}.json"
    if not path.exists():
        tmp = path.with_suffix(".json.tmp")
        cmd = [sys.executable, str(HERE / "learning_sp.py"), "--seed", str(seed), "--minutes", str(minutes)]
        cmd += ["--ppo", json.dumps({"epochs": epochs}), "--out", str(out / name), "--env-steps", str(env_steps)]
        with tmp.open("w") as f:
            subprocess.run(cmd, stdout=f, check=True)
        tmp.replace(path)
    return _result(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--epochs", type=int, nargs="+", default=[2, 4])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--minutes", type=float, default=8.0, help="time limit of one run")
    parser.add_argument("--env-steps", type=int, default=0, help="train every run to this budget (0: to the target)")
    parser.add_argument("--out", type=Path, default=Path("reports/learning_epochs"))
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.seeds:
        for epochs in args.epochs:
            r = run(epochs, seed, args.out, args.minutes, args.env_steps)
            first = r["curve"][0]
            rows.append(
                {
                    "epochs": epochs,
                    "seed": seed,
                    "time_to_target_s": r["time_to_target_s"],
                    "first_eval_SUC": round(first["SUC"], 1),
                    "first_eval_env_steps": first["env_steps"],
                    "s_per_update": round(first["wall_s"] / 40, 3),
                    "final_SUC": round(r["curve"][-1]["SUC"], 1),
                    "final_env_steps": r["curve"][-1]["env_steps"],
                }
            )
    table = pd.DataFrame(rows)
    per_value = {}
    for epochs, g in table.groupby("epochs"):
        times = g["time_to_target_s"].astype(float)
        per_value[int(epochs)] = {
            "median_time_s": float(times.median()),
            "worst_time_s": float(times.max()),
            "reached": int(times.notna().sum()),
            "first_eval_SUC_mean": round(float(g["first_eval_SUC"].mean()), 1),
            "first_eval_SUC_std": round(float(g["first_eval_SUC"].std(ddof=1)), 1),
            "s_per_update_mean": round(float(g["s_per_update"].mean()), 3),
            "final_SUC_mean": round(float(g["final_SUC"].mean()), 1),
            "final_SUC_std": round(float(g["final_SUC"].std(ddof=1)), 1),
        }
    base = table[table["epochs"] == args.epochs[0]].set_index("seed")
    metrics = ["time_to_target_s", "first_eval_SUC", "s_per_update", "final_SUC"]
    paired = {
        f"{e}-{args.epochs[0]}": paired_difference(
            table[table["epochs"] == e].set_index("seed").astype(float), base.astype(float), metrics
        )
        for e in args.epochs[1:]
    }
    print(
        json.dumps(
            {
                "benchmark": "learning_epochs",
                "task": "4p2e1o",
                "target_SUC": 70.0,
                "env_steps": args.env_steps or None,
                "runs": rows,
                "per_epochs": per_value,
                "paired_vs_first": paired,
                "note": "time to target is quantised by the evaluations every 40 updates (500 episodes each)",
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
