"""How fast can the local trainer get on this CPU? The matrix products' and the simulation's share of a training update.

Runs the local trainer (default PPO config, 4p2e1o self-play, ``update_threads`` as the trainer's default)
and reads each of ``--updates`` updates (rollout + PPO update) with torch's profiler. For each it reports
the wall time, the time in matrix products (the self CPU time of ``aten::mm``, ``aten::addmm``,
``aten::bmm`` and ``aten::baddbmm``, in the update and in the rollout's inference; the profiler times an
op on the thread that calls it, so a product run on two threads counts its wall time), and the
trainer's own split into simulation, inference and update.

The products and the simulation are the floor: work that only fewer FLOPs, lower precision or a faster
simulator can shorten. Prints JSON with the pursuer-steps/s that floor allows and, given
``--reference-steps-per-s`` (a previous commit's end-to-end rate from train_throughput.py), the time
per update a ``--target-ratio`` asks for and how much of the rest (everything but the floor) it leaves.
The profiler adds a few per cent to the wall time; the floor is what it cannot add to.

Usage: python benchmarks/update_floor.py [--updates 3] [--reference-steps-per-s 18962.2 --target-ratio 1.6]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from typing import Any

import numpy as np

PRODUCTS = ("aten::mm", "aten::addmm", "aten::bmm", "aten::baddbmm")


def measure(updates: int) -> dict[str, Any]:
    from torch.profiler import ProfilerActivity, profile

    from atdrone.learn.trainer import Trainer, load_train_config

    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(load_train_config({"name": "bench", "task": "4p2e1o", "mode": "self_play", "out_dir": tmp}))
        trainer.update_once()  # warm-up
        for _ in range(updates):
            with profile(activities=[ProfilerActivity.CPU]) as prof:
                start = time.perf_counter()
                row = trainer.update_once()
                wall = time.perf_counter() - start
            self_s = {e.key: e.self_cpu_time_total / 1e6 for e in prof.key_averages()}
            rows.append(
                {
                    "wall_s": wall,
                    "products_s": sum(self_s.get(k, 0.0) for k in PRODUCTS),
                    "simulation_s": row["perf/simulation_s"],
                    "inference_s": row["perf/inference_s"],
                    "update_s": row["perf/update_s"],
                }
            )
        ppo = trainer.ppo
        samples = ppo.num_envs * ppo.rollout_steps * trainer.worker.match.num_ctrl
    return {
        "samples_per_update": samples,
        "epochs": ppo.epochs,
        "update_threads": trainer.cfg.update_threads,
        "updates": [{k: round(v, 3) for k, v in r.items()} for r in rows],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--updates", type=int, default=3)
    parser.add_argument("--reference-steps-per-s", type=float, help="a previous commit's end-to-end pursuer-steps/s")
    parser.add_argument("--target-ratio", type=float, default=1.6)
    args = parser.parse_args()
    if args.updates < 1:
        raise SystemExit("--updates must be at least 1")
    out = measure(args.updates)
    med = {k: float(np.median([u[k] for u in out["updates"]])) for k in out["updates"][0]}
    floor = med["products_s"] + med["simulation_s"]
    samples = out["samples_per_update"]
    out["median"] = {k: round(v, 3) for k, v in med.items()}
    out["floor_s"] = round(floor, 3)
    out["rest_s"] = round(med["wall_s"] - floor, 3)
    out["pursuer_steps_per_s"] = {"profiled": round(samples / med["wall_s"]), "floor": round(samples / floor)}
    if args.reference_steps_per_s:
        target_s = samples / (args.reference_steps_per_s * args.target_ratio)
        out["target"] = {
            "reference_steps_per_s": args.reference_steps_per_s,
            "ratio": args.target_ratio,
            "update_s": round(target_s, 3),
            "rest_allowed_s": round(target_s - floor, 3),
        }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
