"""End-to-end PPO training throughput (rollout + update) of the local trainer, in one process.

Prints JSON: pursuer-steps/s (learner drone-steps per second of wall time) and the split of
the time between simulation, inference and the PPO update. Target (issue 4): >= 20,000
pursuer-steps/s on a 2-core machine.
Usage: python benchmarks/train_throughput.py [--task 4p2e1o] [--updates 8]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time

import numpy as np


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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--updates", type=int, default=8)
    args = parser.parse_args()
    result = {"benchmark": "train_throughput", "task": args.task, "target_pursuer_steps_per_s": 20000}
    result["self_play"] = measure(args.task, args.updates)
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
