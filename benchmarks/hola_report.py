"""Algorithms of the service at equal budgets, evaluated on the unseen zoos (HOLA-Drone V2 vs its
"w/o g" ablation vs SP vs PBT; MAPPO vs NAHT-D vs NAHT-D w/o Dec vs FCP vs SP).

Three resumable phases, each skipping what is already on disk (run it again, or with
``--resume`` after a kill, and it continues where it stopped):

1. train: for every task x algorithm x seed, a population-service run of about
   ``--env-steps`` environment steps (same PPO preset, same updates of 64 x 128 env
   steps; the budget per algorithm is stated in the report: env steps, learner samples
   and evaluation env steps). An interrupted run is resumed from its last generation.
2. evaluate: each run's final learner (HOLA: the last generation's learner; SP: the last
   member; PBT: the final member with the best fitness) with partners drawn from Zoos
   1-3, ``--episodes`` episodes per zoo, the same evaluation seed for every algorithm.
   SP is also evaluated at the generation whose learner samples are closest to HOLA's
   (SP trains all four slots, HOLA two): "sp@samples".
3. report: SUC / COL / AST / REW as mean +- std over seeds; paired differences against SP
   (the same seed's runs) with standard errors over seeds; the cross-play matrix of the
   final learners (row: learner, column: the member filling both partner slots); rho
   entropy over generations; figures.

Usage: python benchmarks/hola_report.py [--tasks 4p2e5o 4p3e5o] [--seeds 0 1 2]
       [--algorithms hola hola_no_g sp pbt] [--phases train evaluate report]
       [--out reports/hola_report] [--results benchmarks/results/hola_report]

The teammate-modelling comparison (MAPPO, NAHT-D and its ablation, FCP, SP; paired
differences against SP and MAPPO; the training pool is the algorithms' default,
configs/pools/train_pool.json; FCP's frozen pool counts in its budget):

    python benchmarks/hola_report.py --tasks 4p2e1o 4p2e5o --algorithms sp mappo naht_d naht_d_no_dec fcp \
        --references sp mappo --updates 32 --title "Teammate modelling" \
        --out reports/teammate_report --results benchmarks/results/teammate_report
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import scipy.stats

from atdrone.benchmark.budget import plan as budget_plan
from atdrone.benchmark.stats import md_table, mean_std, paired_difference
from atdrone.learn.ppo import PPOConfig
from atdrone.population.hola import HolaConfig
from atdrone.teams.evaluation import METRICS

ALGORITHMS = ("hola", "hola_no_g", "sp", "pbt", "mappo", "naht_d", "naht_d_no_dec", "fcp")
ZOOS = ("zoo1", "zoo2", "zoo3")  # the default --zoos: the paper's unseen zoos (zoo4: the diverse held-out zoo)
UPDATE_ENV_STEPS = PPOConfig().num_envs * PPOConfig().rollout_steps  # of the default preset: 64 x 128


def plan(
    algorithm: str, env_steps: int, updates: int, hola: dict[str, Any], fcp: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Generations and the algorithm section giving about ``env_steps`` env steps per run
    (:func:`atdrone.benchmark.budget.plan` with this script's sections)."""
    section = {"hola": dict(hola), "hola_no_g": dict(hola), "fcp": dict(fcp or {"seeds": 3, "levels": 3})}.get(
        algorithm, {"population_size": 2} if algorithm == "pbt" else {}
    )
    return {**budget_plan(algorithm, section, env_steps, updates, UPDATE_ENV_STEPS), algorithm: section}


def experiment(task: str, algorithm: str, seed: int, args: argparse.Namespace) -> dict[str, Any]:
    hola = {
        "pi0_seeds": args.pi0_seeds,
        "pi0_levels": args.pi0_levels,
        "learner_start": args.learner_start,
        "weight": args.weight,
        "eta_prior": args.eta_prior,
        "min_episodes": 32,
        "max_episodes": 128,
        "max_hyperedges": 12,
    }
    doc = {
        "name": run_name(task, algorithm, seed, args.tag),
        "algorithm": algorithm,
        "task": task,
        "seed": seed,
        "updates_per_generation": args.updates,
        "num_workers": 2,
        "eval_episodes": 48,
        "final_zoo": "",
        "gif": False,
        "out_dir": str(Path(args.out) / "runs"),
    }
    if args.ppo_epochs is not None:
        doc["ppo"] = {"epochs": args.ppo_epochs}
    doc.update(
        plan(algorithm, args.env_steps, args.updates, hola, {"seeds": args.fcp_seeds, "levels": args.fcp_levels})
    )
    return doc


def run_name(task: str, algorithm: str, seed: int, tag: str = "") -> str:
    """A run's name; a variant (``--tag``) is a separate run next to the main ones."""
    return f"{task}-{algorithm}{'+' + tag if tag else ''}-s{seed}"


def machine_cpu_seconds() -> float:
    """CPU seconds the whole machine has spent (user + nice + system + irq, /proc/stat) since boot.

    A Ray run's work is spread over actor processes that come and go, so a run's CPU time is
    read as the machine's over the run: exact when the run is alone on the machine, an upper
    bound when anything else ran beside it (the report says which).
    """
    fields = Path("/proc/stat").read_text().splitlines()[0].split()[1:8]
    user, nice, system, _idle, _iowait, irq, softirq = (int(f) for f in fields)
    return (user + nice + system + irq + softirq) / os.sysconf("SC_CLK_TCK")


def write_json(path: Path, data: Any) -> None:
    from atdrone.fileio import atomic_write_bytes

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(path, json.dumps(data, indent=2, default=float).encode())


# ------------------------------------------------------------------ phase 1
def train(args: argparse.Namespace) -> None:
    from atdrone.service.driver import init_ray, run_experiment
    from atdrone.service.experiment import load_experiment

    init_ray(None, num_cpus=2)
    tracking = f"sqlite:///{Path(args.out).resolve() / 'mlflow.db'}"
    for task in args.tasks:
        for seed in args.seeds:
            for algorithm in args.algorithms:
                cfg = load_experiment(experiment(task, algorithm, seed, args))
                run_dir = Path(cfg.out_dir) / cfg.name
                if (run_dir / "population.csv").exists():
                    continue
                resume = (run_dir / "service_state.json").exists()
                print(
                    f"[train] {cfg.name}: {'resuming' if resume else 'starting'} ({cfg.generations} generations)",
                    flush=True,
                )
                t0, cpu0 = time.perf_counter(), machine_cpu_seconds()
                run_experiment(cfg, resume=resume, tracking_uri=tracking, progress=True)
                wall, cpu = time.perf_counter() - t0, machine_cpu_seconds() - cpu0
                # a resumed run's compute counts from its resume only: marked so
                write_json(
                    run_dir / "compute.json",
                    {"wall_s": wall, "machine_cpu_s": cpu, "resumed": resume, "load_avg_1min_end": os.getloadavg()[0]},
                )
                print(f"[train] {cfg.name}: done in {wall:.0f}s ({cpu:.0f} machine CPU s)", flush=True)


# ------------------------------------------------------------------ phase 2
def final_member(run_dir: Path, algorithm: str) -> str:
    state = json.loads((run_dir / "service_state.json").read_text())["coordinator"]
    alg = state["algorithm"]
    if algorithm == "pbt":
        last = sorted((run_dir / "generations").iterdir())[-1] / "pbt.json"
        fitness = json.loads(last.read_text())["fitness"]
        return max(alg["population"], key=lambda m: (fitness.get(m, -1.0), m))
    if algorithm in ("hola", "hola_no_g"):
        return str(alg["learners"][-1])
    return str(alg["population"][-1])


def evaluate_runs(args: argparse.Namespace) -> None:
    from atdrone.policies.neural import load_policy
    from atdrone.teams.evaluation import evaluate

    for task in args.tasks:
        for seed in args.seeds:
            for algorithm in args.algorithms:
                run_dir = Path(args.out) / "runs" / run_name(task, algorithm, seed, args.tag)
                target = Path(args.out) / "eval" / f"{run_dir.name}.json"
                if target.exists() or not (run_dir / "population.csv").exists():
                    continue
                label = f"{algorithm}+{args.tag}" if args.tag else algorithm
                members: dict[str, str | None] = {label: final_member(run_dir, algorithm)}
                if algorithm == "sp" and not args.tag:
                    members["sp@samples"] = sp_at_samples(run_dir, task, seed, args)
                rows: list[dict[str, Any]] = []
                profiles: list[dict[str, Any]] = []
                for label, member in members.items():
                    if member is None:
                        continue
                    policy = load_policy(run_dir / "members" / f"{member}.pt")
                    for zoo in args.zoos:
                        t0, cpu0 = time.perf_counter(), time.process_time()
                        result = evaluate(policy, task, zoo, episodes=args.episodes, seeds=[1000 + seed])
                        compute = {"eval_wall_s": time.perf_counter() - t0, "eval_cpu_s": time.process_time() - cpu0}
                        rows.append({"algorithm": label, "member": member, "zoo": zoo, **result.mean, **compute})
                        profiles += by_profile(result.records, label, member, zoo)
                        print(
                            f"[evaluate] {run_dir.name} {label} {member} {zoo}: SUC {result.mean['SUC']:.1f} "
                            f"({time.perf_counter() - t0:.0f}s)",
                            flush=True,
                        )
                write_json(
                    target,
                    {
                        "task": task,
                        "seed": seed,
                        "episodes": args.episodes,
                        "rows": rows,
                        "profiles": profiles,
                        "budget": budget_of(run_dir),
                        "compute": compute_of(run_dir),
                    },
                )


def by_profile(records: pd.DataFrame, label: str, member: str, zoo: str) -> list[dict[str, Any]]:
    """The metrics per partner profile (the partners' names, sorted, '+'-joined) of one evaluation."""
    from atdrone.teams.evaluation import metrics

    profile = records["partners"].map(lambda team: "+".join(sorted(str(team).split(","))))
    return [
        {"algorithm": label, "member": member, "zoo": zoo, "profile": name, "episodes": len(g), **metrics(g)}
        for name, g in records.groupby(profile, sort=True)
    ]


def compute_of(run_dir: Path) -> dict[str, Any]:
    """The training run's wall and machine CPU seconds (compute.json; {} for runs trained before it existed)."""
    path = run_dir / "compute.json"
    return json.loads(path.read_text()) if path.exists() else {}


def budget_of(run_dir: Path) -> dict[str, Any]:
    state = json.loads((run_dir / "service_state.json").read_text())["coordinator"]
    return dict(state.get("budget", {}))


def sp_at_samples(run_dir: Path, task: str, seed: int, args: argparse.Namespace) -> str | None:
    """The SP member whose learner samples are closest to the HOLA run's (same task and seed)."""
    hola_dir = Path(args.out) / "runs" / run_name(task, "hola", seed)
    if not (hola_dir / "service_state.json").exists():
        return None
    target = budget_of(hola_dir)["learner_samples"]
    state = json.loads((run_dir / "service_state.json").read_text())["coordinator"]
    members = state["algorithm"]["population"]
    per_member = budget_of(run_dir)["learner_samples"] / len(members)  # SP: equal samples per generation
    index = int(np.clip(round(target / per_member) - 1, 0, len(members) - 1))
    return str(members[index])


def crossplay(args: argparse.Namespace) -> None:
    """Final learners of the algorithms with each other: row learner, column partner (both partner slots)."""
    from atdrone.policies.neural import load_policy
    from atdrone.teams.evaluation import metrics, run_episodes

    if args.tag:
        return
    for task in args.tasks:
        for seed in args.seeds:
            target = Path(args.out) / "crossplay" / f"{task}-s{seed}.json"
            runs = {a: Path(args.out) / "runs" / run_name(task, a, seed) for a in args.algorithms}
            if target.exists() or not all((d / "population.csv").exists() for d in runs.values()):
                continue
            policies = {a: load_policy(d / "members" / f"{final_member(d, a)}.pt") for a, d in runs.items()}
            matrix: dict[str, dict[str, float]] = {}
            for a, learner in policies.items():
                matrix[a] = {}
                for b, partner in policies.items():
                    records = run_episodes(
                        learner,
                        task,
                        [partner],
                        args.crossplay_episodes,
                        seed=2000 + seed,
                        sampler=lambda rng, n: np.zeros((n, 2), dtype=np.int64),
                    )
                    matrix[a][b] = metrics(records)["SUC"]
            print(f"[crossplay] {task} seed {seed}: {matrix}", flush=True)
            write_json(target, {"task": task, "seed": seed, "episodes": args.crossplay_episodes, "SUC": matrix})


# ------------------------------------------------------------------ phase 3
def noise_null(graph: dict[str, Any], temperature: float, seed: int, trials: int = 200) -> dict[str, float]:
    """rho (softmin) when every learner hyperedge has one true outcome and they differ by measurement noise
    alone: each weight drawn as the hyperedges' mean weight plus its measured standard error times N(0, 1).

    Returns the mean entropy and largest rho over ``trials`` draws, and the gap between the two lowest
    measured weights in standard errors of their difference: how far the worst profile stands out. Empty
    with fewer than two hyperedges."""
    import atdrone.population.hypergraph as hg

    edges = graph.get("hyperedges", [])
    key = graph.get("weight", "return")
    if len(edges) < 2:
        return {}
    teams = [tuple(e["team"]) for e in edges]
    w = np.array([e[key] for e in edges], dtype=np.float64)
    se = np.array([e[f"{key}_se"] for e in edges], dtype=np.float64)
    partners = len(teams[0]) - sum(m in graph["learners"] for m in teams[0])
    rng = np.random.default_rng(seed)

    def rho() -> dict[str, float]:
        drawn = dict(zip(teams, (w.mean() + se * rng.standard_normal(len(w))).tolist(), strict=True))
        return hg.softmin_rho(drawn, graph["learners"], graph["rho"], partners, temperature)[0]

    stats = hg.rho_statistics(rho() for _ in range(trials))
    low = np.argsort(w)[:2]
    diff, sd = float(w[low[1]] - w[low[0]]), float(np.hypot(se[low[0]], se[low[1]]))
    gap = diff / sd if sd > 0 else (math.inf if diff > 0 else 0.0)
    return {"noise_entropy": stats["entropy"], "noise_max_rho": stats["max_rho"], "gap_z": gap}


def pi0_members(generations: Path) -> tuple[set[str], set[str]] | None:
    """Pi_0's members and its snapshots before each seed's last (the lower skill levels), from generation 0's
    pi0.json; None without it. Members are seed by seed, one per level: a seed's last level ends each block."""
    path = generations / "000" / "pi0.json"
    if not path.exists():
        return None
    doc = json.loads(path.read_text())
    levels = len(doc["levels"])
    return set(doc["members"]), {m for i, m in enumerate(doc["members"]) if i % levels != levels - 1}


def rho_entropy(args: argparse.Namespace) -> pd.DataFrame:
    rows = []
    temperatures = {}  # HOLA runs whose rho is the softmin: its temperature
    for d in (Path(args.out) / "runs").glob("*-hola-s*"):
        hola = json.loads((d / "config.json").read_text()).get("hola", {}) if (d / "config.json").exists() else {}
        if hola.get("rho", HolaConfig.rho) == "softmin":
            temperatures[d] = float(hola.get("temperature", HolaConfig.temperature))
    for task in args.tasks:
        for seed in args.seeds:
            for run_dir in sorted((Path(args.out) / "runs").glob(f"{task}-hola*-s{seed}")):
                algorithm, gens = run_dir.name[len(task) + 1 : -len(f"-s{seed}")], run_dir / "generations"
                pi0 = pi0_members(gens)
                for doc in sorted(gens.glob("*/hypergraph.json")) if gens.exists() else []:
                    graph = json.loads(doc.read_text())
                    rho = np.array(list(graph["rho"].values()))
                    null = graph.get("null", {})  # rho of random weights on the same hyperedges (older runs: none)
                    noise = noise_null(graph, temperatures[run_dir], seed) if run_dir in temperatures else {}
                    rows.append(
                        {
                            "task": task,
                            "algorithm": algorithm,
                            "seed": seed,
                            "generation": int(doc.parent.name),
                            "rho_entropy": float(-(rho * np.log(rho)).sum()),
                            "max_entropy": float(np.log(len(rho))),
                            "max_rho": float(rho.max()),
                            "contested_return": graph["resolution"]["return"]["contested_nodes"]
                            / max(graph["resolution"]["return"]["nodes"], 1),
                            "contested_SUC": graph["resolution"]["SUC"]["contested_nodes"]
                            / max(graph["resolution"]["SUC"]["nodes"], 1),
                            "null_entropy": null.get("entropy", float("nan")),
                            "null_entropy_sd": null.get("entropy_sd", float("nan")),
                            "null_max_rho": null.get("max_rho", float("nan")),
                            **noise,
                            **(
                                {
                                    "pi0_rho": float(sum(v for m, v in graph["rho"].items() if m in pi0[0])),
                                    "pi0_early_rho": float(sum(v for m, v in graph["rho"].items() if m in pi0[1])),
                                }
                                if pi0 is not None
                                else {}
                            ),
                        }
                    )
    return pd.DataFrame(rows)


def report(args: argparse.Namespace) -> None:
    evals = []
    budget_rows = []
    profile_rows: list[dict[str, Any]] = []
    for path in sorted((Path(args.out) / "eval").glob("*.json")):
        ev = json.loads(path.read_text())
        for row in ev["rows"]:
            evals.append({"task": ev["task"], "seed": ev["seed"], **row})
        profile_rows += [{"task": ev["task"], "seed": ev["seed"], **row} for row in ev.get("profiles", [])]
        # evaluations written before compute was recorded have none: left out, shown as '-'
        spent = {
            k: sum(r[k] for r in ev["rows"])
            for k in ("eval_wall_s", "eval_cpu_s")
            if ev["rows"] and all(k in r for r in ev["rows"])
        }
        budget_rows.append({"run": path.stem, **ev["budget"], "compute": ev.get("compute", {}), **spent})
    if not evals:
        print("[report] nothing evaluated yet")
        return
    frame = pd.DataFrame(evals)
    lines = [f"# {args.title}: {', '.join(args.tasks)}", ""]
    lines.append(
        f"Evaluation: {args.episodes} episodes per run and zoo; mean +- std (ddof 1) over seeds "
        f"(n: seeds). Paired differences: algorithm - reference of the same seed "
        "(sp: equal env steps; sp@samples: SP's generation with the learner samples closest to HOLA's), "
        f"mean +- standard error over seeds [t-based 95% confidence interval]."
    )
    doc: dict[str, Any] = {"episodes": args.episodes, "cells": [], "paired": [], "budget": budget_rows}
    for (task, zoo), cell in frame.groupby(["task", "zoo"], sort=True):
        lines += [
            "",
            f"## {task}, {zoo}",
            "",
            "| algorithm | n | " + " | ".join(METRICS) + " |",
            "|---" * (len(METRICS) + 2) + "|",
        ]
        for algorithm, g in cell.groupby("algorithm", sort=False):
            stats = {m: mean_std(g[m]) for m in METRICS}
            doc["cells"].append(
                {
                    "task": task,
                    "zoo": zoo,
                    "algorithm": algorithm,
                    "n": len(g),
                    **{m: {"mean": v[0], "std": v[1]} for m, v in stats.items()},
                }
            )
            lines.append(
                f"| {algorithm} | {len(g)} | " + " | ".join(f"{v[0]:.1f} +- {v[1]:.1f}" for v in stats.values()) + " |"
            )
        # SP at equal env steps and at equal learner samples; HOLA against its ablation; a variant
        # with its own SP runs (e.g. a doubled budget, "sp+2M") against those
        tagged_sp = sorted(a for a in cell.algorithm.unique() if a.startswith("sp+"))
        for reference in (*args.references, *tagged_sp):
            ref = cell[cell.algorithm == reference].set_index("seed")
            if ref.empty:
                continue
            others = cell[~cell.algorithm.isin(["sp", "sp@samples", reference])]
            if reference == "hola_no_g":
                others = others[others.algorithm.str.startswith("hola")]
            elif reference in tagged_sp:
                others = others[others.algorithm.str.endswith(reference[2:])]
            for algorithm, g in others.groupby("algorithm", sort=False):
                diff = paired_difference(g.set_index("seed"), ref, METRICS)
                if diff is None:
                    continue
                doc["paired"].append(
                    {
                        "task": task,
                        "zoo": zoo,
                        "algorithm": algorithm,
                        "reference": reference,
                        **diff,
                    }
                )
                diffs = {m: (diff[m]["diff"], diff[m]["se"]) for m in METRICS}
                t95 = float(scipy.stats.t.ppf(0.975, diff["n"] - 1))
                lines.append(
                    f"| {algorithm} - {reference} | {diff['n']} | "
                    + " | ".join(
                        f"{d:+.1f} +- {s:.1f} [{d - t95 * s:+.1f}, {d + t95 * s:+.1f}]" for d, s in diffs.values()
                    )
                    + " |"
                )
    if profile_rows:
        lines += profile_tables(pd.DataFrame(profile_rows), doc)
    if budget_rows:
        lines += [
            "",
            "## Budgets per run",
            "",
            "Training: env steps, learner samples and the service's evaluation-match env steps of the run; wall and "
            "machine CPU seconds of its training (the machine's /proc/stat over the run: exact when the run was "
            "alone on the machine, an upper bound otherwise; '-' for runs trained before this was recorded; "
            "'resumed': counted from the resume). Evaluation: wall and CPU seconds of the report's zoo evaluations "
            "of the run (this process).",
            "",
            "| run | env steps | learner samples | eval env steps | train wall s | train machine CPU s "
            "| zoo-eval wall s | zoo-eval CPU s |",
            "|---|---|---|---|---|---|---|---|",
        ]
        for b in budget_rows:
            c = b.get("compute", {})
            train = [f"{c[k]:.0f}{' (resumed)' if c.get('resumed') else ''}" if k in c else "-" for k in COMPUTE]
            ev = [f"{b[k]:.0f}" if k in b else "-" for k in ("eval_wall_s", "eval_cpu_s")]
            counts = [f"{b.get(k, 0):,}" for k in ("env_steps", "learner_samples", "eval_env_steps")]
            lines.append("| " + " | ".join([b["run"], *counts, *train, *ev]) + " |")
    cross = []
    for path in sorted((Path(args.out) / "crossplay").glob("*.json")):
        c = json.loads(path.read_text())
        cross += [
            {"task": c["task"], "seed": c["seed"], "learner": a, "partner": b, "SUC": v}
            for a, row in c["SUC"].items()
            for b, v in row.items()
        ]
    if cross:
        cp = pd.DataFrame(cross).groupby(["task", "learner", "partner"])["SUC"].mean().unstack()
        doc["crossplay"] = {t: cp.loc[t].to_dict(orient="index") for t in cp.index.get_level_values(0).unique()}
        for t in doc["crossplay"]:
            lines += [
                "",
                f"## Cross-play SUC on {t} (row: learner; column: partner in both partner slots; mean over seeds)",
                "",
                md_table(cp.loc[t].round(1)),
            ]
    ent = rho_entropy(args)
    if len(ent):
        doc["rho_entropy"] = ent.to_dict(orient="records")
        summary = (
            ent.groupby(["task", "algorithm", "generation"])[
                [
                    "rho_entropy",
                    "null_entropy",
                    "null_entropy_sd",
                    "max_entropy",
                    "max_rho",
                    "null_max_rho",
                    "noise_entropy",
                    "noise_max_rho",
                    "gap_z",
                    "pi0_rho",
                    "pi0_early_rho",
                    "contested_return",
                    "contested_SUC",
                ]
            ]
            .mean()
            .round(3)
        )
        lines += [
            "",
            "## rho over generations (mean over seeds)",
            "",
            "rho_entropy and max_rho: the run's rho over Pi - N_t (nats; the largest share). null_*: the same weights "
            "permuted over the hyperedges (the run's own null, 200 trials). noise_*: the learner's hyperedges with one "
            "true outcome, differing by their measured standard errors only (softmin runs). gap_z: the two lowest "
            "hyperedge weights' difference in standard errors. pi0_rho: rho's mass on Pi_0 (w/o g: its uniform "
            "share); pi0_early_rho: on Pi_0's snapshots before each seed's last. contested_*: the share of nodes "
            "whose preference stayed within z standard errors.",
            "",
            md_table(summary),
        ]
        plot_entropy(ent, Path(args.results) / "rho_entropy.png")
    text = "\n".join(lines)
    print(text)
    doc["text"] = text
    results = Path(args.results)
    write_json(results / "report.json", doc)
    (results / "report.md").write_text(text + "\n")
    frame.to_csv(results / "evaluations.csv", index=False)


COMPUTE = ("wall_s", "machine_cpu_s")


def profile_tables(profiles: pd.DataFrame, doc: dict[str, Any]) -> list[str]:
    """Zoos with several members, split by partner profile: SUC mean +- std over seeds per algorithm, and the
    same grouped by how many trained (checkpoint) partners the team had."""
    from atdrone.policies.zoo import load_zoo

    lines: list[str] = []
    doc["profiles"] = profiles.to_dict(orient="records")
    for (task, zoo), cell in profiles.groupby(["task", "zoo"], sort=True):
        if cell["profile"].nunique() < 2:
            continue
        learned = {m.name for m in load_zoo(zoo).spec.members if m.kind == "checkpoint"}
        counts = [sum(n in learned for n in p.split("+")) for p in cell["profile"]]
        cell = cell.assign(trained=counts)
        for key, title in (("profile", "partner profile"), ("trained", "trained partners in the team")):
            if cell[key].nunique() < 2:  # e.g. Zoo 2: every team has two trained partners
                continue
            # per seed first (episodes pooled within a seed), then mean +- std over seeds
            per_seed = cell.groupby(["algorithm", key, "seed"]).apply(
                lambda g: 100.0 * float((g["SUC"] / 100.0 * g["episodes"]).sum() / g["episodes"].sum()),
                include_groups=False,
            )
            stats = per_seed.groupby(["algorithm", key]).agg(["mean", "std", "count"])
            table = stats.apply(lambda r: f"{r['mean']:.1f} +- {r['std']:.1f} (n {int(r['count'])})", axis=1)
            lines += [
                "",
                f"## {task}, {zoo} by {title}: SUC mean +- std over seeds",
                "",
                md_table(table.unstack(key).fillna("-")),
            ]
    return lines


def plot_entropy(ent: pd.DataFrame, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    tasks = sorted(ent.task.unique())
    fig, axes = plt.subplots(1, len(tasks), figsize=(5 * len(tasks), 3.5), squeeze=False)
    for ax, task in zip(axes[0], tasks, strict=True):
        sub = ent[ent.task == task]
        for algorithm, g in sub.groupby("algorithm"):
            m = g.groupby("generation")["rho_entropy"].agg(["mean", "std"])
            ax.errorbar(m.index, m["mean"], yerr=m["std"].fillna(0), label=algorithm, capsize=3)
        drawn = sub[~sub.algorithm.str.startswith("hola_no_g")]  # the nulls of rho's rule (w/o g's rho is uniform)
        null = drawn.groupby("generation")["null_entropy"].mean()
        if null.notna().any():
            ax.plot(null.index, null.values, "k--", label="null: weights permuted over the hyperedges")
        if "noise_entropy" in drawn and drawn["noise_entropy"].notna().any():
            noise = drawn.groupby("generation")["noise_entropy"].mean()
            ax.plot(noise.index, noise.values, "k-.", label="null: equal outcomes + measured noise")
        m = sub.groupby("generation")["max_entropy"].mean()
        ax.plot(m.index, m.values, "k:", label="log |Pi - N_t| (uniform)")
        ax.set_title(f"rho entropy, {task}")
        ax.set_xlabel("generation")
        ax.set_ylabel("nats")
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=["4p2e5o", "4p3e5o"])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--algorithms", nargs="+", default=list(ALGORITHMS), choices=ALGORITHMS)
    parser.add_argument(
        "--phases", nargs="+", default=["train", "evaluate", "report"], choices=["train", "evaluate", "report"]
    )
    parser.add_argument("--env-steps", type=int, default=1_048_576, help="training env steps per run (about)")
    parser.add_argument(
        "--ppo-epochs", type=int, default=None, help="PPO epochs per update (default: the preset's; pin a study's)"
    )
    parser.add_argument("--updates", type=int, default=16, help="PPO updates per learner per generation")
    parser.add_argument("--weight", default="return", choices=["return", "SUC"], help="HOLA hyperedge weight")
    parser.add_argument("--learner-start", default="last", choices=["last", "scratch"])
    parser.add_argument("--pi0-seeds", type=int, default=2, help="HOLA: self-play seeds of Pi_0")
    parser.add_argument("--pi0-levels", type=int, default=2, help="HOLA: skill levels per Pi_0 seed")
    parser.add_argument("--eta-prior", type=float, default=1.0, help="HOLA: the prior count of rho's eta")
    parser.add_argument("--fcp-seeds", type=int, default=3, help="FCP: self-play runs of the frozen pool")
    parser.add_argument("--fcp-levels", type=int, default=3, help="FCP: skill levels frozen per run")
    parser.add_argument(
        "--references", nargs="+", default=["sp", "sp@samples", "hola_no_g"], help="paired differences against these"
    )
    parser.add_argument("--crossplay", action="store_true", help="also play the final learners with each other")
    parser.add_argument("--title", default="HOLA-Drone V2 vs SP", help="the report's heading")
    parser.add_argument("--tag", default="", help="a variant's name: its runs and rows are '<algorithm>+<tag>'")
    parser.add_argument("--episodes", type=int, default=500, help="evaluation episodes per run and zoo")
    parser.add_argument("--zoos", nargs="+", default=list(ZOOS), help="evaluation zoos (configs/zoos)")
    parser.add_argument("--crossplay-episodes", type=int, default=200)
    parser.add_argument("--resume", action="store_true", help="accepted for clarity: every phase always resumes")
    parser.add_argument("--out", default="reports/hola_report", help="runs, evaluations (not committed)")
    parser.add_argument("--results", default="benchmarks/results/hola_report", help="the committed report")
    args = parser.parse_args()
    if "train" in args.phases:
        train(args)
    if "evaluate" in args.phases:
        import torch

        torch.set_num_threads(1)  # beside a training run on the same cores
        evaluate_runs(args)
        if args.crossplay or "hola" in args.algorithms:
            crossplay(args)
    if "report" in args.phases:
        report(args)


if __name__ == "__main__":
    main()
