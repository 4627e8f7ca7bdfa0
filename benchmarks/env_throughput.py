"""Env-steps/s of BatchedPursuit, its PettingZoo view and MPE2 simple_tag, in one run.

Prints JSON. Usage: python benchmarks/env_throughput.py [--task 4p2e5o] [--seconds 3]
The targets (issue 2): best BatchedPursuit >= 100x MPE2 simple_tag, PettingZoo view at
one env >= MPE2 simple_tag.
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from collections.abc import Callable
from typing import Any

import numpy as np


def _rate(step: Callable[[int], int], seconds: float) -> float:
    """Env-steps per second of ``step(i) -> env-steps done``, after a short warm-up."""
    for i in range(3):
        step(i)
    done, i, start = 0, 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        done += step(i)
        i += 1
    return done / elapsed


def batched(task: str, num_envs: int, seconds: float) -> float:
    from atdrone.envs import BatchedPursuit

    env = BatchedPursuit(task, num_envs=num_envs, seed=0)
    env.reset()
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-0.3, 0.3, (num_envs, env.num_p)) for _ in range(16)]

    def step(i: int) -> int:
        env.step(actions[i % 16])
        return num_envs

    return _rate(step, seconds)


def parallel_env_rate(env: Any, actions: list[dict], seconds: float) -> float:
    """Steps/s of a PettingZoo ParallelEnv stepped with ``actions`` in turn, reset at episode ends."""

    def step(i: int) -> int:
        env.step(actions[i % len(actions)])
        if not env.agents:
            env.reset()
        return 1

    return _rate(step, seconds)


def pettingzoo_view(task: str, seconds: float) -> float:
    from atdrone.envs import PursuitParallelEnv

    env = PursuitParallelEnv(task, seed=0)
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    actions = [{a: rng.uniform(-0.3, 0.3, 1).astype(np.float32) for a in env.possible_agents} for _ in range(16)]
    return parallel_env_rate(env, actions, seconds)


def mpe2_simple_tag(seconds: float) -> float:
    from mpe2 import simple_tag_v3

    env = simple_tag_v3.parallel_env(
        num_adversaries=4, num_good=2, num_obstacles=3, continuous_actions=True, max_cycles=25
    )
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    spaces = {a: env.action_space(a) for a in env.possible_agents}
    actions = [{a: rng.uniform(s.low, s.high).astype(np.float32) for a, s in spaces.items()} for _ in range(16)]
    return parallel_env_rate(env, actions, seconds)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e5o")
    parser.add_argument("--seconds", type=float, default=3.0, help="measuring time per configuration")
    parser.add_argument("--num-envs", type=int, nargs="+", default=[1, 64, 1024, 4096])
    args = parser.parse_args()
    mpe = mpe2_simple_tag(args.seconds)
    ours = {str(n): batched(args.task, n, args.seconds) for n in args.num_envs}
    pz = pettingzoo_view(args.task, args.seconds)
    best_n = max(ours, key=ours.__getitem__)
    result = {
        "benchmark": "env_throughput",
        "task": args.task,
        "unit": "env-steps/s",
        "machine": {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()},
        "batched_pursuit": {n: round(v, 1) for n, v in ours.items()},
        "pettingzoo_view_1env": round(pz, 1),
        "mpe2_simple_tag": round(mpe, 1),
        "best_num_envs": int(best_n),
        "ratio_best_batched_vs_mpe2": round(ours[best_n] / mpe, 2),
        "ratio_pettingzoo_view_vs_mpe2": round(pz / mpe, 2),
        "targets": {"ratio_best_batched_vs_mpe2": 100.0, "ratio_pettingzoo_view_vs_mpe2": 1.0},
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
