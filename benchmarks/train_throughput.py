"""End-to-end PPO training throughput (rollout + update) of the local trainer, in one process.

Prints JSON: pursuer-steps/s (learner drone-steps per second of wall time) and the split of
the time between simulation, inference and the PPO update. Target (issue 4): >= 20,000
pursuer-steps/s on a 2-core machine. With ``--reference DIR`` (a checkout of another
commit, e.g. ``git worktree add /tmp/before <commit>``) it measures both trees in
alternating subprocess rounds, each with its own code on PYTHONPATH, and prints the ratio
this tree / reference (issue 12: no slower than before the redesign).
Usage: python benchmarks/train_throughput.py [--task 4p2e1o] [--updates 8] [--epochs N] [--reference DIR --rounds 3]
       [--device cpu cuda --rounds 3]: the update on each device in turn, in one process
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
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent.parent


def measure(
    task: str, updates: int, mode: str = "self_play", device: str = "auto", update_threads: int = 2, **ppo: object
) -> dict[str, object]:
    import atdrone
    from atdrone.learn.trainer import Trainer, load_train_config

    with tempfile.TemporaryDirectory() as tmp:
        doc = {"name": "bench", "task": task, "mode": mode, "out_dir": tmp, "ppo": dict(ppo)}
        cfg = load_train_config({**doc, "device": device, "update_threads": update_threads})
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
        "device": str(trainer.learner.device),
        "atdrone": str(Path(atdrone.__file__).resolve().parent),
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


def _subprocess_rate(tree: Path, task: str, updates: int, epochs: int | None) -> dict[str, Any]:
    """One measurement by this script with the tree's atdrone first on the path: the same benchmark code
    times either tree's library (a reference checkout's own script may lack this one's options)."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    extra = ["--epochs", str(epochs)] if epochs is not None else []
    out = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--task", task, "--updates", str(updates), *extra],
        cwd=tree,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    result: dict[str, Any] = json.loads(out.stdout)["self_play"]
    if not result["atdrone"].startswith(str(tree)):
        raise RuntimeError(f"{tree}: measured the atdrone of {result['atdrone']}")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--updates", type=int, default=8)
    parser.add_argument("--reference", type=Path, default=None, help="another checkout to compare with")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds per tree with --reference")
    parser.add_argument("--epochs", type=int, default=None, help="PPO epochs (default: the default config's)")
    parser.add_argument(
        "--device", nargs="+", default=["auto"], help="the update's device; several (cpu cuda): --rounds alternating"
    )
    parser.add_argument("--update-threads", type=int, default=2, help="torch threads of a CPU update")
    args = parser.parse_args()
    if len(set(args.device)) != len(args.device):
        parser.error(f"--device names a device twice: {args.device}")
    if args.reference is not None and args.device != ["auto"]:
        parser.error("--reference compares two trees on the default device; --device compares devices in this tree")
    result: dict[str, object] = {"benchmark": "train_throughput", "task": args.task}
    result["target_pursuer_steps_per_s"] = 20000
    ppo = {"epochs": args.epochs} if args.epochs is not None else {}
    if args.reference is None and len(args.device) == 1:
        result["self_play"] = measure(
            args.task, args.updates, device=args.device[0], update_threads=args.update_threads, **ppo
        )
    elif args.reference is None:  # devices side by side, in one process (e.g. what a GPU update gives)
        import torch

        by: dict[str, list[dict[str, Any]]] = {d: [] for d in args.device}
        for _ in range(args.rounds):
            for d in args.device:
                by[d].append(measure(args.task, args.updates, device=d, update_threads=args.update_threads, **ppo))
        rate = {d: [float(r["pursuer_steps_per_s"]) for r in rs] for d, rs in by.items()}
        first = args.device[0]
        result.update(
            gpu=torch.cuda.get_device_name() if torch.cuda.is_available() else None,
            torch=torch.__version__,
            cpu_count=os.cpu_count(),
            update_threads=args.update_threads,
            rounds=args.rounds,
            pursuer_steps_per_s=rate,
            split_s={d: [r["split_s"] for r in rs] for d, rs in by.items()},
            ratio_over_first={d: round(float(np.mean(v)) / float(np.mean(rate[first])), 3) for d, v in rate.items()},
        )
    else:
        runs: dict[str, list[dict[str, Any]]] = {"this": [], "reference": []}
        for _ in range(args.rounds):
            runs["this"].append(_subprocess_rate(HERE, args.task, args.updates, args.epochs))
            runs["reference"].append(_subprocess_rate(args.reference.resolve(), args.task, args.updates, args.epochs))
        rates = {k: [float(r["pursuer_steps_per_s"]) for r in rs] for k, rs in runs.items()}
        this, ref = float(np.mean(rates["this"])), float(np.mean(rates["reference"]))
        result.update(
            reference=str(args.reference),
            rounds=args.rounds,
            epochs=runs["this"][0]["ppo"]["epochs"],
            pursuer_steps_per_s={k: [round(v, 1) for v in vs] for k, vs in rates.items()},
            split_s={k: [r["split_s"] for r in rs] for k, rs in runs.items()},
            per_round_ratio=[round(a / b, 3) for a, b in zip(rates["this"], rates["reference"], strict=True)],
            mean={"this": round(this, 1), "reference": round(ref, 1)},
            ratio_this_over_reference=round(this / ref, 3),
            target_ratio=1.0,
        )
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
