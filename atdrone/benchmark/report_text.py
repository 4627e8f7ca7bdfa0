"""The benchmark report's text (report.md), from the report's tables."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pandas as pd

from atdrone.benchmark.cells import STALL_FACTOR
from atdrone.benchmark.config import MIN_HOLA_GENERATIONS, BenchmarkConfig
from atdrone.benchmark.report_gaps import gaps_text
from atdrone.benchmark.report_paper import diff_text, orderings_text, side_by_side_text
from atdrone.benchmark.stats import md_table, mean_std
from atdrone.teams.evaluation import METRICS

BOUNDS = ("br", "floor")
BUDGET_KEYS = ("env_steps", "learner_samples", "eval_env_steps", "benchmark_eval_env_steps")


@dataclass
class Tables:
    """Every table of a report (the CSV files), as :func:`atdrone.benchmark.report.write_report` builds them."""

    table: pd.DataFrame
    pairs: pd.DataFrame
    norm: pd.DataFrame
    agg: pd.DataFrame
    poi: pd.DataFrame
    spent: pd.DataFrame
    claims: pd.DataFrame = field(default_factory=pd.DataFrame)
    side: pd.DataFrame = field(default_factory=pd.DataFrame)
    gaps: pd.DataFrame = field(default_factory=pd.DataFrame)
    marks: dict[str, str] = field(default_factory=dict)


def order(cfg: BenchmarkConfig) -> list[str]:
    """The methods in the config's order, then the bounds."""
    return [*cfg.methods, *BOUNDS]


def _pm(mean: float, std: float) -> str:
    if not np.isfinite(mean):
        return "-"
    return f"{mean:.1f}" if not np.isfinite(std) else f"{mean:.1f} +- {std:.1f}"


def _norm_cell(x: np.ndarray) -> str:
    if not np.isfinite(x).all():
        return "-"
    mean, std = mean_std(x)
    return f"{mean:.2f}" if not np.isfinite(std) else f"{mean:.2f} +- {std:.2f}"


def _ppo_line(cfg: BenchmarkConfig) -> str:
    if "ppo" in cfg.experiment or "preset" in cfg.experiment:
        setting = {k: cfg.experiment[k] for k in ("preset", "ppo") if k in cfg.experiment}
        return f"PPO setting of every method and best response: `{json.dumps(setting, sort_keys=True)}`."
    return "PPO setting: each method's own experiment config (the benchmark sets none for all)."


def _header(cfg: BenchmarkConfig, t: Tables) -> list[str]:
    lines = [f"# Benchmark {cfg.name}", ""]
    if cfg.smoke_test:
        updates = cfg.updates_per_generation
        lines += [
            f"**A smoke test: it ranks nothing.** It checks that every cell trains, evaluates and reports at a "
            f"budget far below the paper's ({cfg.env_steps:,} env steps per run, {updates} updates per "
            "generation); no ordering, difference or aggregate below measures the methods.",
            "",
        ]
    for label, why in t.marks.items():
        lines += [
            f"**Marked: {label}.** {why} (at least {MIN_HOLA_GENERATIONS} are needed): its rows measure the "
            "self-play seeds of Pi_0, not the method.",
            "",
        ]
    extra = "".join(
        f"; {', '.join(e.methods)} on {', '.join(e.tasks)} also seeds {', '.join(map(str, e.seeds))}"
        for e in cfg.extra_seeds
    )
    lines += [
        f"Methods: {', '.join(cfg.methods)}; tasks: {', '.join(cfg.tasks)}; seeds: {', '.join(map(str, cfg.seeds))}"
        f"{extra}; test zoos: {', '.join(cfg.zoos)}; selection zoo: {cfg.select_zoo or 'none'} (choices only).",
        f"Budget of every training run: about {cfg.env_steps:,} env steps ({cfg.updates_per_generation} updates per "
        f"generation); each final learner evaluated with {cfg.eval_episodes:,} episodes per zoo, the same episodes "
        "for every method of a seed. " + _ppo_line(cfg) + " The budgets spent, per method and task (mean over runs):",
        "",
        "| method | task | runs | env steps | learner samples | eval env steps (training) | "
        "eval env steps (benchmark) | CPU-s | wall-s | wall-s median | stalled |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for _, b in t.spent.iterrows():
        counts = " | ".join(f"{b[k]:,.0f}" for k in BUDGET_KEYS)
        lines.append(
            f"| {b['method']} | {b['task']} | {b['runs']} | {counts} | {b['cpu_s']:,.0f} | {b['wall_s']:,.0f} | "
            f"{b['wall_median_s']:,.0f} | {b['stalled']} |"
        )
    keys = (*BUDGET_KEYS, "cpu_s", "wall_s", "steady_wall_s")
    total = {k: float((t.spent[k] * t.spent["runs"]).sum()) for k in keys}
    lines += [
        "",
        f"In all: {int(t.spent['runs'].sum()):,} cells, {total['env_steps']:,.0f} training env steps, "
        f"{total['eval_env_steps'] + total['benchmark_eval_env_steps']:,.0f} evaluation env steps, "
        f"{total['cpu_s']:,.0f} CPU-s, {total['wall_s']:,.0f} s of cell wall time as measured; "
        f"{total['steady_wall_s']:,.0f} s with each of the {int(t.spent['stalled'].sum())} stalled cells counted at "
        "its method's median (cells run side by side: the job's own wall time is shorter).",
        "",
        "CPU-s: the rollout workers' reserved CPU-seconds (wall time x workers) plus the CPU time of the cell's "
        "driver and evaluation in its last attempt; a resumed cell adds its earlier attempts' generations at one "
        "CPU per rollout worker (their drivers' CPU time is not kept). Wall-s: the training's generations over every "
        "attempt plus the evaluation, where the record keeps them (else the last attempt's; timing.csv has "
        f"each). A cell is stalled when its wall time is over {STALL_FACTOR:g} times its method's median over "
        "all tasks: its processes were stopped or starved for part of it (a paused or busy machine), so its wall "
        "time and reserved CPU-seconds measure the machine, not the method. Every other number is reproducible.",
    ]
    return lines


def _results(cfg: BenchmarkConfig, t: Tables) -> list[str]:
    zoos = cfg.played_zoos
    lines = [
        "",
        "## Results (Table 2 layout)",
        "",
        "SUC, COL (%), AST (steps), REW: mean +- std over seeds (ddof 1). br: the best response trained with "
        "that zoo (the upper bound); floor: a random learner with the zoo's partners.",
    ]
    for task in cfg.tasks:
        header = ["method"] + [f"{z} {m}" for z in zoos for m in METRICS]
        lines += ["", f"### {task}", "", "| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
        for method in order(cfg):
            sub = t.table[(t.table.method == method) & (t.table.task == task)].set_index("zoo")
            if sub.empty:
                continue
            cells = []
            for z in zoos:
                for m in METRICS:
                    cells.append(_pm(sub.loc[z, f"{m}_mean"], sub.loc[z, f"{m}_std"]) if z in sub.index else "")
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
    return lines


def _paired(cfg: BenchmarkConfig, pairs: pd.DataFrame) -> list[str]:
    if pairs.empty:
        return []
    lines = [
        "",
        "## Paired differences",
        "",
        "Method - reference over the same seeds: mean +- standard error [t-based 95 % interval, n - 1 degrees of "
        "freedom]; n: the seeds paired (AST: the seeds where both had a success, in brackets where fewer).",
    ]
    for task in cfg.tasks:
        sub = pairs[pairs.task == task]
        if sub.empty:
            continue
        lines += ["", f"### {task}", "", "| difference | zoo | n | " + " | ".join(METRICS) + " |"]
        lines.append("|---" * (3 + len(METRICS)) + "|")
        for (method, ref, zoo), g in sub.groupby(["method", "reference", "zoo"], sort=False):
            by = g.set_index("metric")
            paired_n = int(by["paired"].iloc[0])
            vals = []
            for m in METRICS:
                fewer = by.loc[m, "n"] < paired_n  # AST: seeds without a success on either side drop out
                vals.append(diff_text(by.loc[m]) + (f" (n {int(by.loc[m, 'n'])})" if fewer else ""))
            lines.append(f"| {method} - {ref} | {zoo} | {paired_n} | " + " | ".join(vals) + " |")
    return lines


def _normalised(norm: pd.DataFrame) -> list[str]:
    if norm.empty:
        return []
    lines = [
        "",
        "## Normalised SUC",
        "",
        "(SUC - floor) / (best response - floor) per run: 0 is the random learner, 1 the mean best response of the "
        "task and zoo; mean +- std over seeds. Only against a bound whose best response is above the floor by a "
        "one-sided Welch test at 5 % ('-': not significant, the scale is noise).",
        "",
    ]
    summary = norm.groupby(["method", "task", "zoo"], sort=False)["normalised_SUC"].agg(
        lambda s: _norm_cell(s.to_numpy(np.float64))
    )
    lines.append(md_table(summary.unstack("zoo")))
    bounds = norm.drop_duplicates(["task", "zoo"])
    marked = bounds[~bounds["bound_usable"].astype(bool)]
    lines += [
        "",
        f"Bounds usable: {len(bounds) - len(marked)} of {len(bounds)} (task, zoo)."
        + ("" if marked.empty else " Marked (best response not significantly above the floor):"),
    ]
    if len(marked):
        lines += ["", "| task | zoo | floor SUC | best response SUC (mean) | p |", "|---|---|---|---|---|"]
        for _, b in marked.iterrows():
            lines.append(
                f"| {b['task']} | {b['zoo']} | {b['floor_SUC']:.1f} | {b['br_SUC']:.1f} | {b['bound_p']:.3g} |"
            )
    return lines


def _aggregates(cfg: BenchmarkConfig, agg: pd.DataFrame, poi: pd.DataFrame) -> list[str]:
    lines: list[str] = []
    if len(agg):
        lines += [
            "",
            "## Aggregates (rliable)",
            "",
            "Over each method's runs x tasks x test zoos (seeds "
            f"{', '.join(map(str, cfg.seeds))}): interquartile mean (IQM) and mean with stratified bootstrap 95 % "
            f"intervals ({cfg.bootstrap_reps:,} resamples, seed {cfg.bootstrap_seed}; each task's runs resampled, "
            "each run kept together across its zoos); SUC as a fraction, and normalised SUC over the tasks whose "
            "every test zoo has a usable bound. Performance profiles: performance_profiles.png, profiles.csv.",
            "",
            "| score | method | statistic | value | 95 % interval | runs x tasks x zoos |",
            "|---|---|---|---|---|---|",
        ]
        for _, a in agg.iterrows():
            lines.append(
                f"| {a['score']} | {a['method']} | {a['statistic']} | {a['value']:.3f} | "
                f"[{a['ci95_low']:.3f}, {a['ci95_high']:.3f}] | {a['runs']} x {a['tasks']} x {a['zoos']} |"
            )
    if len(poi):
        lines += ["", "Probability of improvement (ties count half), stratified bootstrap 95 % interval:", ""]
        lines += ["| score | P(method > reference) | value | 95 % interval |", "|---|---|---|---|"]
        for _, p in poi.iterrows():
            lines.append(
                f"| {p['score']} | P({p['method']} > {p['reference']}) | {p['P(method > reference)']:.3f} | "
                f"[{p['ci95_low']:.3f}, {p['ci95_high']:.3f}] |"
            )
    return lines


def markdown(cfg: BenchmarkConfig, tables: Tables) -> str:
    """The report's text."""
    lines: list[Any] = [
        *_header(cfg, tables),
        *_results(cfg, tables),
        *side_by_side_text(tables.side),
        *gaps_text(cfg, tables.side, tables.gaps, tables.spent),
        *orderings_text(tables.claims),
        *_paired(cfg, tables.pairs),
        *_normalised(tables.norm),
        *_aggregates(cfg, tables.agg, tables.poi),
    ]
    return "\n".join(lines) + "\n"
