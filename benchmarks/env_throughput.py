"""Env-steps/s of BatchedPursuit, its PettingZoo view and MPE2 simple_tag, in one run.

Prints JSON. Usage: python benchmarks/env_throughput.py [--task 4p2e5o] [--seconds 3]
The targets (issue 2): best BatchedPursuit >= 100x MPE2 simple_tag, PettingZoo view at
one env >= MPE2 simple_tag.

With ``--reference DIR`` (a checkout of another commit, e.g. ``git worktree add --detach
/tmp/before <commit>``) it measures BatchedPursuit of both trees on ``--tasks`` x
``--num-envs`` in alternating subprocess rounds, each with its own code on PYTHONPATH, and
MPE2 simple_tag in the same rounds, and prints the ratios this tree / reference (issue 26:
>= 1.3x) and this tree / MPE2.
Usage: python benchmarks/env_throughput.py --reference DIR [--rounds 3] [--tasks ...] [--num-envs 256 4096]

With ``--events-ratio PROTOCOL`` it times BatchedPursuit's step with the protocol's team events
against without, in one process, alternating rounds (``--rounds``, ``--seconds`` each) for each
``--num-envs`` (default 64 256 4096), both driven by the demo policy so episodes last as in an
evaluation, and prints the median ratio (the target: at most 1.10 with one event per episode,
e.g. benchmarks/protocols/drop_early.json, a drone short for nearly the whole episode).
Usage: python benchmarks/env_throughput.py --events-ratio benchmarks/protocols/drop_early.json [--rounds 15]

With ``--fixed-steps N`` it steps BatchedPursuit N times (one ``--num-envs`` size,
``--task``), with the team events of ``--protocol`` when given, and prints the rate: a
fixed amount of work for timing whole processes against each other (``farm-bench --vs``),
e.g. this tree with one event per episode against this tree without, or against a
checkout of the commit before (PYTHONPATH=DIR).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent.parent
TASKS = ("4p2e1o", "4p2e3o", "4p2e5o", "4p3e5o")


def _rate(step: Callable[[int], int], seconds: float) -> float:
    """Env-steps per second of ``step(i) -> env-steps done``, after a short warm-up."""
    for i in range(3):
        step(i)
    done, i, start = 0, 0, time.perf_counter()
    while (elapsed := time.perf_counter() - start) < seconds:
        done += step(i)
        i += 1
    return done / elapsed


def fixed_steps(task: str, num_envs: int, steps: int, protocol: str = "") -> dict[str, Any]:
    """Step ``steps`` times (with ``protocol``'s team events): the rate and how many events happened."""
    from atdrone.envs import BatchedPursuit

    kwargs: dict[str, Any] = {}
    if protocol:
        from atdrone.teams.protocols import load_protocol

        kwargs["events"] = load_protocol(protocol).plan
    env = BatchedPursuit(task, num_envs=num_envs, seed=0, **kwargs)
    env.reset()
    rng = np.random.default_rng(0)
    actions = [rng.uniform(-0.3, 0.3, (num_envs, env.num_p)) for _ in range(16)]
    changes = episodes = 0
    start = time.perf_counter()
    for i in range(steps):
        _, _, done, info = env.step(actions[i % 16])
        episodes += int(done.sum())
        if "team_changed" in info:
            changes += int(info["team_changed"].sum())
    elapsed = time.perf_counter() - start
    return {"env_steps_per_s": round(num_envs * steps / elapsed, 1), "episodes_ended": episodes, "events": changes}


def events_ratio(task: str, num_envs: int, protocol: str, rounds: int, seconds: float) -> dict[str, Any]:
    """The time of BatchedPursuit's step with ``protocol``'s team events over its time without, in one process:
    both simulators driven by the demo policy (:func:`~atdrone.policies.rules.chase_nearest`, episodes as
    long as an evaluation's, unlike random actions' few steps), only ``step`` timed, in alternating rounds of
    about ``seconds`` each; the median of the rounds' ratios (robust to a machine whose speed drifts)."""
    from atdrone.envs import BatchedPursuit
    from atdrone.policies.rules import chase_nearest
    from atdrone.teams.protocols import load_protocol

    plan = load_protocol(protocol).plan
    envs = {
        "plain": BatchedPursuit(task, num_envs=num_envs, seed=0),
        "events": BatchedPursuit(task, num_envs=num_envs, seed=0, events=plan),
    }
    obs = {k: e.reset() for k, e in envs.items()}
    counts = {"episodes": 0, "events": 0}
    # a round's steps: about ``seconds`` of the plain simulator, from a short calibration
    t0, calib = time.perf_counter(), 5
    for _ in range(calib):
        obs["plain"], *_ = envs["plain"].step(chase_nearest(obs["plain"], envs["plain"].num_e))
    steps = max(5, int(seconds / ((time.perf_counter() - t0) / calib)))
    ratios, spent = [], {"plain": 0.0, "events": 0.0}
    for r in range(rounds):
        took = {}
        for name in ("plain", "events") if r % 2 == 0 else ("events", "plain"):
            env, t = envs[name], 0.0
            for _ in range(steps):
                actions = chase_nearest(obs[name], env.num_e)
                start = time.perf_counter()
                obs[name], _, done, info = env.step(actions)
                t += time.perf_counter() - start
                if name == "events":
                    counts["episodes"] += int(done.sum())
                    counts["events"] += int(info["team_changed"].sum())
            took[name] = t
            spent[name] += t
        ratios.append(took["events"] / took["plain"])
    return {
        "task": task,
        "num_envs": num_envs,
        "protocol": load_protocol(protocol).name,
        "rounds": rounds,
        "steps_per_round": steps,
        "time_ratio_events_over_plain": {
            "median": round(float(np.median(ratios)), 3),
            "min": round(min(ratios), 3),
            "max": round(max(ratios), 3),
        },
        "env_steps_per_s": {k: round(num_envs * steps * rounds / v, 1) for k, v in spent.items()},
        "events_per_episode": round(counts["events"] / (counts["episodes"] + num_envs), 3),  # per episode begun
        "target": "median <= 1.10",
    }


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


def _tree_rates(tree: Path, tasks: list[str], num_envs: list[int], seconds: float) -> dict[str, Any]:
    """BatchedPursuit env-steps/s of ``tree``'s code (first on PYTHONPATH), measured by this script in a subprocess."""
    sizes = [str(n) for n in num_envs]
    cmd = [
        sys.executable,
        __file__,
        "--batched-only",
        "--tasks",
        *tasks,
        "--seconds",
        str(seconds),
        "--num-envs",
        *sizes,
    ]
    out = subprocess.run(
        cmd,
        cwd=tree,
        env={**os.environ, "PYTHONPATH": str(tree)},
        capture_output=True,
        text=True,
        check=True,
    )
    result: dict[str, Any] = json.loads(out.stdout)
    if not Path(result["atdrone"]).is_relative_to(tree):
        raise RuntimeError(f"measured {result['atdrone']}, not the code of {tree}")
    return result


def compare(reference: Path, tasks: list[str], num_envs: list[int], seconds: float, rounds: int) -> dict[str, Any]:
    """Both trees' BatchedPursuit and MPE2 simple_tag in alternating rounds; means, ratios and every round."""
    trees = {"this": HERE, "reference": reference.resolve()}
    runs: dict[str, list[dict[str, dict[str, float]]]] = {"this": [], "reference": []}
    mpe: list[float] = []
    for r in range(rounds):
        order = ("this", "reference") if r % 2 == 0 else ("reference", "this")
        for name in order:
            runs[name].append(_tree_rates(trees[name], tasks, num_envs, seconds)["batched_pursuit"])
        mpe.append(mpe2_simple_tag(seconds))
    mpe_mean = float(np.mean(mpe))
    table: dict[str, dict[str, Any]] = {}
    for task in tasks:
        for n in map(str, num_envs):
            this = float(np.mean([run[task][n] for run in runs["this"]]))
            ref = float(np.mean([run[task][n] for run in runs["reference"]]))
            table[f"{task}/{n}"] = {
                "this": round(this, 1),
                "reference": round(ref, 1),
                "ratio_this_over_reference": round(this / ref, 3),
                "ratio_this_over_mpe2": round(this / mpe_mean, 1),
                "rounds_this": [round(run[task][n], 1) for run in runs["this"]],
                "rounds_reference": [round(run[task][n], 1) for run in runs["reference"]],
            }
    ratios = [row["ratio_this_over_reference"] for row in table.values()]
    return {
        "reference": str(reference),
        "rounds": rounds,
        "seconds_per_measurement": seconds,
        "mpe2_simple_tag": {"mean": round(mpe_mean, 1), "rounds": [round(v, 1) for v in mpe]},
        "batched_pursuit": table,
        "ratio_this_over_reference": {
            "min": round(min(ratios), 3),
            "geometric_mean": round(float(np.exp(np.mean(np.log(ratios)))), 3),
            "max": round(max(ratios), 3),
        },
        "target_ratio": 1.3,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e5o")
    parser.add_argument("--seconds", type=float, default=3.0, help="measuring time per configuration")
    parser.add_argument(
        "--num-envs", type=int, nargs="+", default=None, help="default 1 64 1024 4096; 256 4096 with --reference"
    )
    parser.add_argument("--reference", type=Path, default=None, help="another checkout to compare with")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds per tree with --reference")
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), help="the tasks measured with --reference")
    parser.add_argument("--batched-only", action="store_true", help=argparse.SUPPRESS)  # one tree's round
    parser.add_argument("--fixed-steps", type=int, default=0, help="step this many times and print the rate")
    parser.add_argument("--protocol", default="", help="with --fixed-steps: the team events of this protocol")
    parser.add_argument(
        "--events-ratio", default="", metavar="PROTOCOL", help="time step() with this protocol's events over without"
    )
    args = parser.parse_args()
    machine = {"python": platform.python_version(), "cpu": platform.processor() or platform.machine()}
    if args.events_ratio:
        sizes = args.num_envs or [64, 256, 4096]
        rows = [events_ratio(args.task, n, args.events_ratio, args.rounds, args.seconds) for n in sizes]
        print(json.dumps({"machine": platform.processor() or platform.machine(), "results": rows}, indent=1))
        return
    if args.fixed_steps:
        num_envs = (args.num_envs or [4096])[0]
        rate = fixed_steps(args.task, num_envs, args.fixed_steps, args.protocol)
        print(json.dumps({"task": args.task, "num_envs": num_envs, "protocol": args.protocol, **rate}))
        return
    if args.batched_only:
        import atdrone

        rates = {t: {str(n): round(batched(t, n, args.seconds), 1) for n in args.num_envs} for t in args.tasks}
        print(json.dumps({"atdrone": atdrone.__file__, "batched_pursuit": rates}))
        return
    if args.reference is not None:
        num_envs = args.num_envs or [256, 4096]
        result: dict[str, Any] = {"benchmark": "env_throughput", "unit": "env-steps/s", "machine": machine}
        result.update(compare(args.reference, args.tasks, num_envs, args.seconds, args.rounds))
        print(json.dumps(result, indent=2))
        return
    args.num_envs = args.num_envs or [1, 64, 1024, 4096]
    mpe = mpe2_simple_tag(args.seconds)
    ours = {str(n): batched(args.task, n, args.seconds) for n in args.num_envs}
    pz = pettingzoo_view(args.task, args.seconds)
    best_n = max(ours, key=ours.__getitem__)
    result = {
        "benchmark": "env_throughput",
        "task": args.task,
        "unit": "env-steps/s",
        "machine": machine,
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
