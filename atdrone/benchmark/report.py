"""The benchmark report: Markdown, CSV and PNG files in the results folder, from the cells' records.

Everything here is a pure function of the records and the config (the bootstrap draws
from ``bootstrap_seed``), so a benchmark resumed after a kill reports exactly what an
uninterrupted one does; only the timings (``timing.csv`` and the CPU-seconds column of
the budget table) differ between attempts. This module builds the tables;
:mod:`~atdrone.benchmark.report_text` writes them as text, :mod:`~atdrone.benchmark.report_paper`
sets them beside the paper, :mod:`~atdrone.benchmark.report_figures` draws them.

Files (``<results>/``):

- ``report.md``: the budget and the PPO setting, the paper's Table 2 layout per task (SUC,
  COL, AST, REW as mean +- std over seeds, ddof 1, per method x zoo, with the best response
  and the floor), the paper side by side and its orderings, paired differences against the
  reference methods (mean, standard error, t-based 95 % interval over seeds), normalised
  scores and rliable's aggregates; a smoke test says so first, and a HOLA method planned
  under :data:`~atdrone.benchmark.config.MIN_HOLA_GENERATIONS` hypergraph generations is marked;
- ``evaluations.csv`` (one row per run x zoo), ``table.csv`` (Table 2, long form),
  ``paired.csv``, ``normalised.csv`` (with each bound's test), ``aggregate.csv`` (IQM and mean
  with stratified bootstrap 95 % intervals), ``improvement.csv`` (probability of improvement),
  ``profiles.csv`` (performance profiles), ``paper.csv`` (the paper side by side), ``gaps.csv`` (the
  measurements that explain where ours differs from the paper: :mod:`~atdrone.benchmark.report_gaps`),
  ``orderings.csv`` (the paper's orderings, each with its verdict), ``budget.csv``, ``timing.csv``;
- ``suc_<task>.png``, ``fig3_without_teammate_modelling.png`` and ``fig4_with_teammate_modelling.png``
  (the paper's two figures, a panel per task), ``performance_profiles.png``.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from atdrone.benchmark.bounds import make_bound
from atdrone.benchmark.cells import STALL_FACTOR, cell_cpu, cell_wall
from atdrone.benchmark.config import HOLA_ALGORITHMS, BenchmarkConfig, check_hola_generations
from atdrone.benchmark.report_figures import FIGURES, family_figure, profile_figure, suc_figure
from atdrone.benchmark.report_gaps import gap_table
from atdrone.benchmark.report_paper import CLAIMS, orderings, side_by_side
from atdrone.benchmark.report_protocols import protocol_table, protocols_text
from atdrone.benchmark.report_text import BUDGET_KEYS, Tables, markdown, order
from atdrone.benchmark.stats import (
    PROFILE_TAUS,
    aggregate_intervals,
    mean_std,
    paired_difference,
    poi_interval,
    profile_interval,
)
from atdrone.fileio import atomic_write_bytes, atomic_write_text
from atdrone.teams.evaluation import METRICS

__all__ = ["CLAIMS", "FIGURES", "aggregates", "evaluations", "orderings", "side_by_side", "table2", "write_report"]


def evaluations(records: Sequence[dict[str, Any]]) -> pd.DataFrame:
    """One row per (cell, zoo evaluated): kind, method, task, zoo, seed, the metrics and the budget."""
    rows = []
    for rec in records:
        cell = rec["cell"]
        for zoo, values in rec["metrics"].items():
            row = {"kind": cell["kind"], "method": cell["method"], "task": cell["task"], "zoo": zoo}
            row.update(seed=cell["seed"], **{m: values[m] for m in METRICS})
            row.update({k: rec["budget"].get(k, 0) for k in BUDGET_KEYS})
            rows.append(row)
    frame = pd.DataFrame(rows)
    return frame.sort_values(["kind", "method", "task", "zoo", "seed"], kind="stable").reset_index(drop=True)


def table2(cfg: BenchmarkConfig, frame: pd.DataFrame) -> pd.DataFrame:
    """Mean and std (ddof 1) over seeds of every metric per method x task x zoo (bounds included)."""
    rows = []
    for method in order(cfg):
        for task in cfg.tasks:
            for zoo in cfg.played_zoos:
                g = frame[(frame.method == method) & (frame.task == task) & (frame.zoo == zoo)]
                if g.empty:
                    continue
                row: dict[str, Any] = {"method": method, "task": task, "zoo": zoo, "n": len(g)}
                for m in METRICS:
                    row[f"{m}_mean"], row[f"{m}_std"] = mean_std(g[m])
                rows.append(row)
    return pd.DataFrame(rows)


def paired(cfg: BenchmarkConfig, frame: pd.DataFrame) -> pd.DataFrame:
    """Every method minus each reference method, per task x zoo, over the seeds both ran; ``paired``: the seeds
    paired, ``n``: those with both values of the metric (the interval's degrees of freedom are n - 1)."""
    rows = []
    for ref in cfg.reference_methods:
        for method in [m for m in cfg.methods if m != ref]:
            for task in cfg.tasks:
                for zoo in cfg.played_zoos:
                    pick = (frame.task == task) & (frame.zoo == zoo)
                    a = frame[pick & (frame.method == method)].set_index("seed")
                    b = frame[pick & (frame.method == ref)].set_index("seed")
                    diff = paired_difference(a, b, METRICS) if len(a) and len(b) else None
                    if diff is None:
                        continue
                    for m in METRICS:
                        d = diff[m]
                        rows.append(
                            {"task": task, "zoo": zoo, "method": method, "reference": ref, "metric": m}
                            | {"paired": diff["n"], "n": d["n"], "diff": d["diff"], "se": d["se"]}
                            | {"ci95_low": d["ci95"][0], "ci95_high": d["ci95"][1]}
                        )
    return pd.DataFrame(rows)


def normalised(cfg: BenchmarkConfig, frame: pd.DataFrame) -> pd.DataFrame:
    """SUC per method run and test zoo scaled between the floor (random learner, 0) and the mean best response
    over seeds (1), only against a usable bound (:func:`atdrone.benchmark.bounds.make_bound`: the best response
    significantly above the floor); NaN, and the bound marked, otherwise."""
    rows = []
    for task in cfg.tasks:
        for zoo in cfg.zoos:
            pick = frame[(frame.task == task) & (frame.zoo == zoo)]
            floor = pick[pick.method == "floor"]["SUC"]
            br = pick[pick.method == "br"]["SUC"].to_numpy(np.float64)
            if floor.empty or len(br) == 0:
                continue
            successes = round(float(floor.mean()) * cfg.eval_episodes / 100.0)
            bound = make_bound(task, zoo, "", br, successes, cfg.eval_episodes)
            for _, r in pick[pick.kind == "method"].iterrows():
                rows.append(
                    {"method": r["method"], "task": task, "zoo": zoo, "seed": int(r["seed"]), "SUC": r["SUC"]}
                    | {"floor_SUC": bound.floor_suc, "br_SUC": bound.br_mean, "bound_p": bound.p_value}
                    | {"bound_usable": bound.usable, "normalised_SUC": bound.normalise(float(r["SUC"]))}
                )
    return pd.DataFrame(rows)


def score_arrays(cfg: BenchmarkConfig, data: pd.DataFrame, column: str, tasks: Sequence[str]) -> dict[str, np.ndarray]:
    """Per method, its runs x tasks x test zoos array of ``column`` over the benchmark's ``seeds`` (extra seeds
    are left out: every task must have the same runs); a seed missing anywhere is left out everywhere."""
    keep = pd.MultiIndex.from_tuples([(t, z) for t in tasks for z in cfg.zoos])
    out = {}
    for method in cfg.methods:
        sub = data[(data.method == method) & data.seed.isin(cfg.seeds) & data.task.isin(tasks)]
        if sub.empty:
            continue
        wide = sub.pivot_table(index="seed", columns=["task", "zoo"], values=column).reindex(columns=keep)
        x = wide.to_numpy(np.float64)
        x = x[np.isfinite(x).all(axis=1)]
        if len(x) >= 2:
            out[method] = x.reshape(len(x), len(tasks), len(cfg.zoos))
    return out


def _scored(cfg: BenchmarkConfig, frame: pd.DataFrame, norm: pd.DataFrame) -> list[tuple[str, dict[str, np.ndarray]]]:
    """The scores the aggregates are over: SUC as a fraction on every task, and the normalised SUC on the tasks
    whose every test zoo has a usable bound."""
    test = frame[(frame.kind == "method") & frame.zoo.isin(cfg.zoos)].assign(SUC_fraction=lambda f: f.SUC / 100.0)
    scored = [("SUC", score_arrays(cfg, test, "SUC_fraction", cfg.tasks))]
    if len(norm):
        usable = norm.groupby("task")["bound_usable"].agg(lambda s: bool(s.all()))
        zoos_seen = norm.groupby("task")["zoo"].nunique()
        tasks = [t for t in cfg.tasks if usable.get(t, False) and zoos_seen.get(t, 0) == len(cfg.zoos)]
        if tasks:
            scored.append(("normalised SUC", score_arrays(cfg, norm, "normalised_SUC", tasks)))
    return scored


def aggregates(cfg: BenchmarkConfig, frame: pd.DataFrame, norm: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """rliable's IQM and mean with stratified bootstrap 95 % intervals per method, and the probability of
    improvement of every method over each reference, per score of :func:`_scored`."""
    agg_rows, poi_rows = [], []
    for label, arrays in _scored(cfg, frame, norm):
        for method, stat in aggregate_intervals(arrays, cfg.bootstrap_reps, cfg.bootstrap_seed).items():
            runs, tasks, zoos = arrays[method].shape
            for name, (value, low, high) in stat.items():
                agg_rows.append(
                    {"score": label, "method": method, "statistic": name, "value": value, "ci95_low": low}
                    | {"ci95_high": high, "runs": runs, "tasks": tasks, "zoos": zoos}
                )
        for ref in [r for r in cfg.reference_methods if r in arrays]:
            for k, (method, x) in enumerate(arrays.items()):
                if method == ref:
                    continue
                value, low, high = poi_interval(x, arrays[ref], cfg.bootstrap_reps, cfg.bootstrap_seed + 1000 + k)
                poi_rows.append(
                    {"score": label, "method": method, "reference": ref, "P(method > reference)": value}
                    | {"ci95_low": low, "ci95_high": high}
                )
    return pd.DataFrame(agg_rows), pd.DataFrame(poi_rows)


def profiles(cfg: BenchmarkConfig, frame: pd.DataFrame, norm: pd.DataFrame) -> pd.DataFrame:
    """rliable's performance profiles (score distributions) per score and method, with bootstrap 95 % bands."""
    rows = []
    for label, arrays in _scored(cfg, frame, norm):
        for k, (method, x) in enumerate(arrays.items()):
            value, low, high = profile_interval(x, cfg.bootstrap_reps, cfg.bootstrap_seed + 2000 + k)
            for tau, v, lo, hi in zip(PROFILE_TAUS, value, low, high, strict=True):
                rows.append(
                    {"score": label, "method": method, "tau": float(tau), "value": float(v)}
                    | {"ci95_low": float(lo), "ci95_high": float(hi)}
                )
    return pd.DataFrame(rows)


def hola_marks(cfg: BenchmarkConfig, records: Sequence[dict[str, Any]]) -> dict[str, str]:
    """Method label -> why its HOLA runs are marked (planned under the minimum of hypergraph generations; only
    a smoke test gets this far with one)."""
    marks: dict[str, str] = {}
    if not cfg.smoke_test:  # any other config with such a method is refused at load
        return marks
    for rec in records:
        cell, algorithm = rec["cell"], str(rec.get("algorithm", ""))
        if cell["kind"] == "method" and algorithm in HOLA_ALGORITHMS and "generations" in rec:
            why = check_hola_generations(cfg, cell["method"], algorithm, int(rec["generations"]))
            if why:
                marks.setdefault(cell["method"], why)
    return marks


def stalled(walls: pd.Series, methods: pd.Series) -> tuple[pd.Series, pd.Series]:
    """Which cells stalled, and each cell's wall time without its stall. A cell stalled when its wall time is over
    :data:`STALL_FACTOR` times the median of its method's cells (every task: a method's cells cost about the same
    on each), as when the machine running them was paused or busy with other work; a method needs three cells for
    a median that one stall cannot move. A stalled cell's steady wall time is its method's median."""
    median = walls.groupby(methods).transform("median")
    counts = walls.groupby(methods).transform("size")
    flags = (walls > STALL_FACTOR * median) & (counts >= 3)
    return flags, walls.where(~flags, median)


def budget(cfg: BenchmarkConfig, records: Sequence[dict[str, Any]]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The budget per method (or bound) and task, mean over its runs (CPU-seconds too; wall seconds as mean and
    median, with the stalled cells counted); every cell's timing, with its wall time and whether it stalled."""
    rows, timing = [], []
    for rec in records:
        cell, spent = rec["cell"], rec.get("timing", {})
        row = {"method": cell["method"], "task": cell["task"], **{k: rec["budget"].get(k, 0) for k in BUDGET_KEYS}}
        wall, cpu = cell_wall(spent), cell_cpu(cfg, rec)
        rows.append({**row, "cpu_s": cpu, "wall_s": wall})
        machine = spent.get("machine", {})  # where the metrics replay bit for bit (older records: none)
        timing.append(
            {
                "cell": rec["name"],
                **{k: v for k, v in spent.items() if k != "machine"},
                "cell_wall_s": wall,
                "cell_cpu_s": cpu,
                "machine": "; ".join(f"{k} {v}" for k, v in machine.items()),
            }
        )
    frame = pd.DataFrame(rows)
    frame["stalled"], frame["steady_wall_s"] = stalled(frame["wall_s"], frame["method"])
    rank = {m: i for i, m in enumerate(order(cfg))}
    table = (
        frame.groupby(["method", "task"], sort=False)
        .agg(
            runs=("env_steps", "size"),
            **{k: (k, "mean") for k in (*BUDGET_KEYS, "cpu_s", "wall_s")},
            wall_median_s=("wall_s", "median"),
            stalled=("stalled", "sum"),
            steady_wall_s=("steady_wall_s", "mean"),
        )
        .reset_index()
    )
    table = table.assign(_order=table["method"].map(rank)).sort_values(["_order", "task"], kind="stable")
    times = pd.DataFrame(timing).assign(stalled=frame["stalled"].to_numpy())
    times = times.sort_values("cell", kind="stable").reset_index(drop=True)
    return table.drop(columns="_order").reset_index(drop=True), times


def write_report(cfg: BenchmarkConfig, records: Sequence[dict[str, Any]]) -> dict[str, Path]:
    """Write every report file to ``cfg.results``; the paths by name."""
    frame = evaluations(records)
    norm = normalised(cfg, frame)
    agg, poi = aggregates(cfg, frame, norm)
    spent, timing = budget(cfg, records)
    tables = Tables(
        table=table2(cfg, frame),
        pairs=paired(cfg, frame),
        norm=norm,
        agg=agg,
        poi=poi,
        spent=spent,
        claims=orderings(cfg, frame),
        side=side_by_side(cfg, frame),
        gaps=gap_table(cfg, frame, records),
        marks=hola_marks(cfg, records),
    )
    prof = profiles(cfg, frame, norm)
    out = cfg.results
    files: dict[str, Path] = {}
    for name, data in (
        ("evaluations", frame),
        ("table", tables.table),
        ("paired", tables.pairs),
        ("normalised", norm),
        ("aggregate", agg),
        ("improvement", poi),
        ("profiles", prof),
        ("paper", tables.side),
        ("gaps", tables.gaps),
        ("budget", spent),
        ("timing", timing),
        ("orderings", tables.claims),
    ):
        files[f"{name}.csv"] = atomic_write_bytes(out / f"{name}.csv", data.to_csv(index=False).encode())
    changes = protocol_table(records)
    text = markdown(cfg, tables) + "".join(f"{line}\n" for line in protocols_text(changes, cfg.eval_episodes))
    if len(changes):
        files["protocols.csv"] = atomic_write_bytes(out / "protocols.csv", changes.to_csv(index=False).encode())
    files["report.md"] = atomic_write_text(out / "report.md", text)
    for task in cfg.tasks:
        files[f"suc_{task}.png"] = suc_figure(cfg, tables.table, task, out / f"suc_{task}.png")
    for name, (title, family) in FIGURES.items():
        methods = [m for m in family if m in cfg.methods]
        if methods:
            files[f"{name}.png"] = family_figure(cfg, tables.table, title, methods, out / f"{name}.png")
    if len(prof):
        files["performance_profiles.png"] = profile_figure(cfg, prof, out / "performance_profiles.png")
    return files
