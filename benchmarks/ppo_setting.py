"""The PPO setting of the paper-budget benchmark: the paper's values against the project's defaults.

Self-play (SP) on one task (default 4p2e1o), one local training run per (setting, seed) at the
benchmark's budget (default 1,048,576 env steps), each final learner evaluated on the
validation zoo (never a test zoo) with --episodes episodes from the benchmark's evaluation seed
(10,000 + seed, as every benchmark cell). The settings (``--setting NAME=PRESET[:JSON]``,
repeatable) default to the two presets of atdrone.learn.ppo: ``default`` (64 environments x
128 steps per update, 4 epochs, lr 1e-3 linear) and ``paper`` (the paper's batch 1024,
minibatch 256, 20 epochs, constant lr 3e-4, value coefficient 1, entropy 0.01).

Prints JSON and writes ``summary.json`` in --out: per setting the validation SUC mean +- std over
seeds (ddof 1) and the wall seconds per run; per other setting the paired difference against
the first (t-based 95 % interval, n - 1 degrees of freedom); and the choice: the setting whose
validation SUC is higher where the paired interval excludes 0, otherwise the one with the lower
median wall time (equal results, less compute). The chosen setting goes into
configs/benchmarks/paper_budget.json's ``experiment`` (``preset`` and every ``ppo`` key written
out) by hand, with the summary committed beside it.
With ``--cost S`` it measures instead the CPU seconds per env step of each setting's training (alternating
rounds of S CPU-seconds, ``--rounds``) and writes ``cost.json``: what a run, and so the benchmark, costs.
Resumable: a run whose result file exists in --out is read back, never run again; a run killed before
its end resumes from its last save (every 32 updates) in --out/runs.
Usage: python benchmarks/ppo_setting.py [--task 4p2e1o] [--seeds 0 1 2 3 4] [--env-steps 1048576]
       [--episodes 500] [--setting paper=paper ...] [--minutes 0] [--out benchmarks/results/ppo_setting]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from atdrone.benchmark.cells import EVAL_SEED
from atdrone.benchmark.stats import mean_std, paired_difference
from atdrone.config import ConfigError
from atdrone.fileio import atomic_write_text
from atdrone.learn.ppo import ppo_config

SAVE_EVERY = 32  # updates between a run's saves
SETTINGS: dict[str, tuple[str, dict[str, Any]]] = {"default": ("default", {}), "paper": ("paper", {})}


def _settings(items: list[str]) -> dict[str, tuple[str, dict[str, Any]]]:
    if not items:
        return dict(SETTINGS)
    out = {}
    for item in items:
        name, sep, spec = item.partition("=")
        preset, _, text = spec.partition(":")
        if not sep or not name or not preset:
            raise SystemExit(f"--setting {item!r}: expected NAME=PRESET[:JSON]")
        overrides = json.loads(text) if text else {}
        try:
            ppo_config(overrides, preset)  # an unknown preset, key or a value out of bounds fails before any run
        except ConfigError as exc:
            raise SystemExit(f"--setting {name}: {exc}") from None
        out[name] = (preset, overrides)
    return out


def run(name: str, preset: str, overrides: dict[str, Any], seed: int, args: argparse.Namespace) -> dict[str, Any]:
    """One SP run of a setting and seed, evaluated on the validation zoo (or its saved result)."""
    path = args.out / f"{name}_s{seed}_b{args.env_steps}_{args.task}.json"
    if path.exists():
        return dict(json.loads(path.read_text()))
    from atdrone.learn.trainer import Trainer, load_train_config
    from atdrone.teams.evaluation import evaluate

    cfg = load_train_config(
        {
            "name": f"ppo_setting_{name}_s{seed}",
            "task": args.task,
            "seed": seed,
            "total_env_steps": args.env_steps,
            "preset": preset,
            "ppo": overrides,
            "out_dir": str(args.out / "runs"),
            "update_threads": args.update_threads,
        }
    )
    trainer = Trainer(cfg)
    # a killed run resumes from its last save (every SAVE_EVERY updates) and collects what the uninterrupted
    # run would have (each save starts the next stretch alike); the wall seconds before the kill are kept
    wall_path = trainer.run_dir / "wall.json"
    resumed = trainer.resume()
    before = float(json.loads(wall_path.read_text())["train_wall_s"]) if resumed and wall_path.is_file() else 0.0
    start = time.perf_counter()
    while trainer.env_steps < args.env_steps:
        trainer.update_once()
        if args.minutes and time.perf_counter() - start > 60 * args.minutes:
            break
        if trainer.updates % SAVE_EVERY == 0:
            trainer.save()
            atomic_write_text(wall_path, json.dumps({"train_wall_s": before + time.perf_counter() - start}))
    train_s = before + time.perf_counter() - start
    result = evaluate(trainer.policy(), args.task, "validation", episodes=args.episodes, seeds=[EVAL_SEED + seed])
    doc = {
        "setting": name,
        "preset": preset,
        "ppo": dataclasses.asdict(ppo_config(overrides, preset)),
        "seed": seed,
        "task": args.task,
        "env_steps": trainer.env_steps,
        "updates": trainer.updates,
        "train_wall_s": round(train_s, 1),
        "complete": trainer.env_steps >= args.env_steps,
        "validation": {k: float(v) for k, v in result.mean.items()},
        "episodes": args.episodes,
    }
    atomic_write_text(path, json.dumps(doc, indent=1) + "\n")
    return doc


def summary(settings: dict[str, tuple[str, dict[str, Any]]], rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per setting the validation metrics over seeds, the paired differences against the first, the choice."""
    table = pd.DataFrame(
        [{"setting": r["setting"], "seed": r["seed"], "wall_s": r["train_wall_s"], **r["validation"]} for r in rows]
    )
    names = list(settings)
    out: dict[str, Any] = {"settings": {}, "paired": {}}
    for name in names:
        g = table[table.setting == name]
        suc_mean, suc_std = mean_std(g["SUC"])
        out["settings"][name] = {
            "preset": settings[name][0],
            "ppo": settings[name][1],
            "seeds": sorted(int(s) for s in g["seed"]),
            "SUC_mean": suc_mean,
            "SUC_std": suc_std,
            "median_wall_s": float(np.median(g["wall_s"])),
        }
    first = table[table.setting == names[0]].set_index("seed")
    choice, why = names[0], "the first setting (no other measured)"
    for name in names[1:]:
        other = table[table.setting == name].set_index("seed")
        diff = paired_difference(other, first, ["SUC", "COL", "REW"])
        out["paired"][f"{name} - {names[0]}"] = diff
        if diff is None:
            continue
        low, high = diff["SUC"]["ci95"]
        if low > 0:
            choice, why = name, f"validation SUC higher than {names[0]}'s (paired 95 % interval above 0)"
        elif high < 0:
            why = f"validation SUC of {name} lower (paired 95 % interval below 0)"
        else:
            walls = {n: out["settings"][n]["median_wall_s"] for n in (names[0], name)}
            choice = min(walls, key=walls.__getitem__)
            why = f"validation SUC undecided against {name} (interval holds 0): the lower median wall time"
    out["choice"] = {"setting": choice, "why": why, "preset": settings[choice][0], "ppo": settings[choice][1]}
    return out


def cost(settings: dict[str, tuple[str, dict[str, Any]]], args: argparse.Namespace) -> dict[str, Any]:
    """CPU seconds per env step of SP training under each setting (collection and update, ``--update-threads``),
    from alternating rounds of at least ``--cost`` seconds of CPU each in this process; per setting the median
    over rounds, the ratio to the first and the CPU minutes a run at ``--env-steps`` takes."""
    from atdrone.learn.trainer import Trainer, load_train_config

    trainers = {
        name: Trainer(
            load_train_config(
                {
                    "name": f"ppo_cost_{name}",
                    "task": args.task,
                    "seed": 0,
                    "total_env_steps": args.env_steps,
                    "preset": preset,
                    "ppo": overrides,
                    "out_dir": str(args.out / "runs"),
                    "update_threads": args.update_threads,
                }
            )
        )
        for name, (preset, overrides) in settings.items()
    }
    per_step: dict[str, list[float]] = {name: [] for name in trainers}
    for trainer in trainers.values():
        trainer.update_once()  # warm-up
    for _ in range(args.rounds):
        for name, trainer in trainers.items():
            cpu0, steps0 = time.process_time(), trainer.env_steps
            while time.process_time() - cpu0 < args.cost:
                trainer.update_once()
            per_step[name].append((time.process_time() - cpu0) / (trainer.env_steps - steps0))
    first = next(iter(per_step))
    med = {name: float(np.median(v)) for name, v in per_step.items()}
    return {
        "task": args.task,
        "update_threads": args.update_threads,
        "rounds": args.rounds,
        "cpu_us_per_env_step": {n: round(1e6 * v, 1) for n, v in med.items()},
        "ratio_to_" + first: {n: round(v / med[first], 2) for n, v in med.items()},
        "cpu_min_per_run": {n: round(v * args.env_steps / 60, 1) for n, v in med.items()},
        "env_steps_per_run": args.env_steps,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    parser.add_argument("--env-steps", type=int, default=1_048_576)
    parser.add_argument("--episodes", type=int, default=500, help="validation episodes per final learner")
    parser.add_argument("--setting", action="append", default=[], help="NAME=PRESET[:JSON] (repeatable)")
    parser.add_argument("--minutes", type=float, default=0.0, help="stop a run's training after this (0: off)")
    parser.add_argument("--update-threads", type=int, default=2)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/ppo_setting"))
    parser.add_argument("--cost", type=float, default=0.0, help="measure CPU per env step, rounds of this many s")
    parser.add_argument("--rounds", type=int, default=5, help="alternating rounds with --cost")
    args = parser.parse_args()
    settings = _settings(args.setting)
    args.out.mkdir(parents=True, exist_ok=True)
    if args.cost:
        doc = cost(settings, args)
        atomic_write_text(args.out / "cost.json", json.dumps(doc, indent=1) + "\n")
        print(json.dumps(doc, indent=1))
        return
    rows = [run(name, *settings[name], seed, args) for seed in args.seeds for name in settings]
    incomplete = [f"{r['setting']} s{r['seed']}" for r in rows if not r["complete"]]
    doc = summary(settings, rows) | {"task": args.task, "env_steps": args.env_steps, "episodes": args.episodes}
    doc["incomplete"] = incomplete  # stopped by --minutes: not a measurement at the budget
    atomic_write_text(args.out / "summary.json", json.dumps(doc, indent=1, default=float) + "\n")
    print(json.dumps(doc, indent=1, default=float))


if __name__ == "__main__":
    main()
