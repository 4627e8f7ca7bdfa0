"""Throughput of the Ray population service on this machine, printed as JSON.

1. Rollout scaling: pursuer-steps/s of rollout collection with 2 Ray rollout workers vs 1
   (same environments per worker, calls pipelined two deep per worker, 1- and 2-worker
   rounds alternating; target >= 1.7x, issue 12).
2. Self-play through the service (coordinator + 2 workers + a learner actor) vs the
   single-process trainer with the same environments and PPO settings (target >= 0.9x).
Usage: python benchmarks/service_throughput.py [--task 4p2e1o] [--updates 6] [--rounds 3]
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time

import ray


def collect_pipelined(workers: list, jobs: list, weights: object, steps: int, calls: int) -> tuple[int, float]:
    """(pursuer-steps, seconds) of ``calls`` collect calls per worker, two in flight per worker.

    Keeping a second call queued on every actor means no worker waits for the driver to
    fetch a fragment, as in a service that keeps its rollout workers busy.
    """
    start = time.perf_counter()
    pending = {}
    left = dict.fromkeys(range(len(workers)), calls)
    for i, w in enumerate(workers):
        for _ in range(min(2, calls)):
            pending[w.collect.remote(jobs[i], weights, steps)] = i
            left[i] -= 1
    samples = 0
    while pending:
        [ref], _ = ray.wait(list(pending), num_returns=1)
        i = pending.pop(ref)
        samples += ray.get(ref).samples
        if left[i] > 0:
            pending[workers[i].collect.remote(jobs[i], weights, steps)] = i
            left[i] -= 1
    return samples, time.perf_counter() - start


def rollout_scaling(workers: list, jobs: list, weights: object, steps: int, rounds: int) -> tuple[float, float]:
    """Pursuer-steps/s of 1 and of 2 workers, measured in alternating rounds (drift hits both alike)."""
    collect_pipelined(workers, jobs, weights, steps, 1)  # warm-up: builds both workers' environments
    totals = {1: [0.0, 0.0], 2: [0.0, 0.0]}
    for _ in range(rounds):
        for n in (1, 2):
            samples, seconds = collect_pipelined(workers[:n], jobs, weights, steps, 4)
            totals[n][0] += samples
            totals[n][1] += seconds
    return totals[1][0] / totals[1][1], totals[2][0] / totals[2][1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--updates", type=int, default=6)
    parser.add_argument("--envs-per-worker", type=int, default=32)
    parser.add_argument("--rounds", type=int, default=3, help="alternating 1-worker / 2-worker rollout rounds")
    args = parser.parse_args()

    from atdrone.config import load_task
    from atdrone.learn.learner import Learner, LearnerSpec
    from atdrone.learn.ppo import ppo_config
    from atdrone.learn.trainer import Trainer, load_train_config
    from atdrone.registry_ray import registry_actor
    from atdrone.service.actors import RolloutJob, RolloutWorkerActor
    from atdrone.service.coordinator import Coordinator
    from atdrone.service.driver import init_ray
    from atdrone.service.experiment import load_experiment, registry_name

    init_ray(None, num_cpus=2)
    task = load_task(args.task)
    num_envs = 2 * args.envs_per_worker
    ppo = ppo_config({"num_envs": num_envs})
    learner = Learner(LearnerSpec(ppo, task.players.num_e, task.players.num_p, seed=0, total_updates=1))
    arch = learner.model.architecture()
    weights = ray.put(learner.get_weights())
    workers = [RolloutWorkerActor.remote(task) for _ in range(2)]
    jobs = [RolloutJob(i, ppo, args.envs_per_worker, task.players.num_p, arch) for i in range(2)]
    one, two = rollout_scaling(workers, jobs, weights, ppo.rollout_steps, args.rounds)
    for w in workers:
        ray.kill(w)

    # self-play: the service path vs the single-process trainer, same environments and PPO settings
    with tempfile.TemporaryDirectory() as tmp:
        cfg = load_experiment(
            {
                "name": "bench",
                "algorithm": "sp",
                "task": args.task,
                "num_workers": 2,
                "updates_per_generation": args.updates,
                "ppo": {"num_envs": num_envs},
                "out_dir": tmp,
            },
        )
        from atdrone.population import ALGORITHMS

        registry = registry_actor(f"{tmp}/registry.db", name=registry_name(cfg.name))
        coord = Coordinator.remote(cfg, ALGORITHMS["sp"], f"{tmp}/bench", None, registry)
        report = ray.get(coord.run_generation.remote())
        service = [r["perf/pursuer_steps_per_s"] for r in report.training[0].history][1:]
        service_rate = sum(service) / len(service)
        ray.kill(coord)
        trainer = Trainer(
            load_train_config({"name": "bench", "task": args.task, "out_dir": tmp, "ppo": {"num_envs": num_envs}})
        )
        trainer.update_once()
        local = [trainer.update_once()["perf/pursuer_steps_per_s"] for _ in range(args.updates - 1)]
        local_rate = sum(local) / len(local)
    print(
        json.dumps(
            {
                "benchmark": "service_throughput",
                "task": args.task,
                "unit": "pursuer-steps/s",
                "rollout_1_worker": round(one, 1),
                "rollout_2_workers": round(two, 1),
                "rollout_scaling": round(two / one, 2),
                "service_self_play": round(service_rate, 1),
                "single_process_self_play": round(local_rate, 1),
                "service_vs_single_process": round(service_rate / local_rate, 2),
                "targets": {"rollout_scaling": 1.7, "service_vs_single_process": 0.9},
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
