"""End-to-end PPO training throughput (rollout + update) of the local trainer, in one process.

Prints JSON: pursuer-steps/s (learner drone-steps per second of wall time) and the split of
the time between simulation, inference and the PPO update. Target (issue 4): >= 20,000
pursuer-steps/s on a 2-core machine. With ``--reference DIR`` (a checkout of another
commit, e.g. ``git worktree add /tmp/before <commit>``) it measures both trees in
alternating subprocess rounds, each with its own code on PYTHONPATH, and prints the ratio
this tree / reference (issue 12: no slower than before the redesign).
Usage: python benchmarks/train_throughput.py [--task 4p2e1o] [--updates 8] [--reference DIR --rounds 3]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent.parent


def measure(task: str, updates: int, mode: str = "self_play", **ppo: object) -> dict[str, object]:
    from atdrone.learn.trainer import Trainer, load_train_config

    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_train_config({"name": "bench", "task": task, "mode": mode, "out_dir": tmp, "ppo": dict(ppo)})
        trainer = Trainer(cfg)
        trainer.update_once()  # warm-up
        rows, start = [], time.perf_counter()
        for _ in range(updates):
            rows.append(trainer.update_once())
        wall = time.perf_counter() - start
    samples = updates * trainer.ppo.num_envs * trainer.ppo.rollout_steps * trainer.worker.match.num_ctrl
    split = {k: float(np.sum([r[f"perf/{k}_s"] for r in rows])) for k in ("simulation", "inference", "update")}
    return {
        "mode": mode,
        "pursuer_steps_per_s": round(samples / wall, 1),
        "env_steps_per_s": round(samples / trainer.worker.match.num_ctrl / wall, 1),
        "wall_s": round(wall, 2),
        "split_s": {k: round(v, 2) for k, v in split.items()},
        "split_fraction": {k: round(v / wall, 3) for k, v in split.items()},
        "ppo": {
            "num_envs": trainer.ppo.num_envs,
            "rollout_steps": trainer.ppo.rollout_steps,
            "epochs": trainer.ppo.epochs,
            "minibatch_size": trainer.ppo.minibatch_size,
        },
    }


def _subprocess_rate(tree: Path, task: str, updates: int) -> float:
    """Pursuer-steps/s of the tree's own benchmark script, run with the tree's code first on the path."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    out = subprocess.run(
        [sys.executable, str(tree / "benchmarks" / "train_throughput.py"), "--task", task, "--updates", str(updates)],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    return float(json.loads(out.stdout)["self_play"]["pursuer_steps_per_s"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--updates", type=int, default=8)
    parser.add_argument("--reference", type=Path, default=None, help="another checkout to compare with")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds per tree with --reference")
    args = parser.parse_args()
    result: dict[str, object] = {"benchmark": "train_throughput", "task": args.task}
    result["target_pursuer_steps_per_s"] = 20000
    if args.reference is None:
        result["self_play"] = measure(args.task, args.updates)
    else:
        rates: dict[str, list[float]] = {"this": [], "reference": []}
        for _ in range(args.rounds):
            rates["this"].append(_subprocess_rate(HERE, args.task, args.updates))
            rates["reference"].append(_subprocess_rate(args.reference.resolve(), args.task, args.updates))
        this, ref = float(np.mean(rates["this"])), float(np.mean(rates["reference"]))
        result.update(
            reference=str(args.reference),
            rounds=args.rounds,
            pursuer_steps_per_s={k: [round(v, 1) for v in vs] for k, vs in rates.items()},
            mean={"this": round(this, 1), "reference": round(ref, 1)},
            ratio_this_over_reference=round(this / ref, 3),
            target_ratio=1.0,
        )
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
