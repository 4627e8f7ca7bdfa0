"""The benchmark report: Markdown, CSV and PNG files in the results folder, from the cells' records.

Everything here is a pure function of the records and the config (the bootstrap draws
from ``bootstrap_seed``), so a benchmark resumed after a kill reports exactly what an
uninterrupted one does; only the timings (``timing.csv`` and the CPU-seconds column of
the budget table) differ between attempts.

Files (``<results>/``):

- ``report.md``: the budget, the paper's Table 2 layout per task (SUC, COL, AST, REW as
  mean +- std over seeds, ddof 1, per method x zoo, with the best response and the floor),
  paired differences against the reference methods (mean, standard error, t-based 95 %
  interval over seeds), normalised scores and the aggregates;
- ``evaluations.csv`` (one row per run x zoo), ``table.csv`` (Table 2, long form),
  ``paired.csv``, ``normalised.csv``, ``aggregate.csv`` (IQM and mean with stratified
  bootstrap 95 % intervals), ``improvement.csv`` (probability of improvement),
  ``budget.csv``, ``timing.csv``, ``orderings.csv`` (the paper's orderings of methods, each comparison
  paired over seeds with its verdict: :func:`orderings`);
- ``suc_<task>.png``: SUC per zoo and method, the best response and the floor as lines;
  ``fig3_without_teammate_modelling.png`` and ``fig4_with_teammate_modelling.png``: the paper's two figures,
  a panel per task (:data:`FIGURES`).
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from atdrone.benchmark.config import BenchmarkConfig
from atdrone.benchmark.stats import (
    bootstrap_interval,
    iqm,
    md_table,
    mean_score,
    mean_std,
    normalise,
    paired_difference,
    poi_interval,
)
from atdrone.fileio import atomic_write_bytes, atomic_write_text
from atdrone.teams.evaluation import METRICS

BOUNDS = ("br", "floor")
BUDGET_KEYS = ("env_steps", "learner_samples", "eval_env_steps", "benchmark_eval_env_steps")


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


def _order(cfg: BenchmarkConfig) -> list[str]:
    return [*cfg.methods, *BOUNDS]


def table2(cfg: BenchmarkConfig, frame: pd.DataFrame) -> pd.DataFrame:
    """Mean and std (ddof 1) over seeds of every metric per method x task x zoo (bounds included)."""
    rows = []
    for method in _order(cfg):
        for task in cfg.tasks:
            for zoo in [*cfg.zoos, cfg.select_zoo]:
                g = frame[(frame.method == method) & (frame.task == task) & (frame.zoo == zoo)]
                if g.empty:
                    continue
                row: dict[str, Any] = {"method": method, "task": task, "zoo": zoo, "n": len(g)}
                for m in METRICS:
                    row[f"{m}_mean"], row[f"{m}_std"] = mean_std(g[m])
                rows.append(row)
    return pd.DataFrame(rows)


def paired(cfg: BenchmarkConfig, frame: pd.DataFrame) -> pd.DataFrame:
    """Every method minus each reference method, per task x zoo, over the seeds both ran."""
    rows = []
    for ref in cfg.reference_methods:
        for method in cfg.methods:
            if method == ref:
                continue
            for task in cfg.tasks:
                for zoo in [*cfg.zoos, cfg.select_zoo]:
                    pick = (frame.task == task) & (frame.zoo == zoo)
                    a = frame[pick & (frame.method == method)].set_index("seed")
                    b = frame[pick & (frame.method == ref)].set_index("seed")
                    if a.empty or b.empty:
                        continue
                    diff = paired_difference(a, b, METRICS)
                    if diff is None:
                        continue
                    for m in METRICS:
                        d = diff[m]
                        rows.append(
                            {
                                "task": task,
                                "zoo": zoo,
                                "method": method,
                                "reference": ref,
                                "metric": m,
                                "n": diff["n"],
                                "diff": d["diff"],
                                "se": d["se"],
                                "ci95_low": d["ci95"][0],
                                "ci95_high": d["ci95"][1],
                            }
                        )
    return pd.DataFrame(rows)


# The paper's orderings (Sec. 5, Figs. 3-4): (claim, better, worse, tasks, zoos); None: every task or test zoo.
# "br" is the best response of each (task, zoo); the easy tasks are 4p2e3o and 4p2e1o, the hard 4p2e5o and 4p3e5o.
EASY, HARD = ("4p2e3o", "4p2e1o"), ("4p2e5o", "4p3e5o")
CLAIMS: tuple[tuple[str, str, tuple[str, ...] | None, tuple[str, ...] | None, tuple[str, ...] | None], ...] = (
    (
        "HOLA-Drone V2 ahead of SP, PBT and w/o g on Zoo 3 in the hard tasks",
        "hola",
        ("sp", "pbt", "hola_no_g"),
        HARD,
        ("zoo3",),
    ),
    ("the best response is the upper bound", "br", None, None, None),
    ("NAHT-D ahead of MAPPO on the easy tasks", "naht_d", ("mappo",), EASY, None),
    ("NAHT-D w/o Dec ahead of MAPPO on the easy tasks", "naht_d_no_dec", ("mappo",), EASY, None),
    ("NAHT-D w/o Dec ahead of NAHT-D on the hard tasks", "naht_d_no_dec", ("naht_d",), HARD, None),
)


def _verdict(diff: float, low: float, high: float) -> str:
    if not np.isfinite(low):
        return "-"
    if low > 0:
        return "holds"
    if high < 0:
        return "reversed"
    return "ahead, undecided" if diff > 0 else "behind, undecided"


def orderings(cfg: BenchmarkConfig, frame: pd.DataFrame) -> pd.DataFrame:
    """The paper's orderings (:data:`CLAIMS`) checked where the config has both sides: SUC of the better
    side minus the worse over the seeds both ran (paired, t-based 95 % interval), and a verdict: holds
    (the interval above 0), reversed (below 0), or ahead / behind but undecided."""
    rows = []
    for claim, better, worse, tasks, zoos in CLAIMS:
        others = [m for m in (worse or tuple(cfg.methods)) if m in cfg.methods and m != better]
        if better != "br" and better not in cfg.methods:
            continue
        for task in [t for t in cfg.tasks if tasks is None or t in tasks]:
            for zoo in [z for z in cfg.zoos if zoos is None or z in zoos]:
                pick = (frame.task == task) & (frame.zoo == zoo)
                a = frame[pick & (frame.method == better)].set_index("seed")
                for other in others:
                    b = frame[pick & (frame.method == other)].set_index("seed")
                    diff = paired_difference(a, b, ["SUC"]) if len(a) and len(b) else None
                    if diff is None:
                        continue
                    d = diff["SUC"]
                    low, high = d["ci95"]
                    rows.append(
                        {"claim": claim, "task": task, "zoo": zoo, "better": better, "worse": other, "n": diff["n"]}
                        | {"diff": d["diff"], "se": d["se"], "ci95_low": low, "ci95_high": high}
                        | {"verdict": _verdict(d["diff"], low, high)}
                    )
    return pd.DataFrame(rows)


def normalised(cfg: BenchmarkConfig, frame: pd.DataFrame) -> pd.DataFrame:
    """SUC per method run and test zoo scaled between the floor (random learner, 0) and the mean best
    response over seeds (1); NaN where the best response does not beat the floor."""
    rows = []
    for task in cfg.tasks:
        for zoo in cfg.zoos:
            pick = frame[(frame.task == task) & (frame.zoo == zoo)]
            floor = pick[pick.method == "floor"]["SUC"].mean()
            ceiling = pick[pick.method == "br"]["SUC"].mean()
            for _, r in pick[pick.kind == "method"].iterrows():
                value = normalise(float(r["SUC"]), float(floor), float(ceiling))
                rows.append(
                    {"method": r["method"], "task": task, "zoo": zoo, "seed": int(r["seed"]), "SUC": r["SUC"]}
                    | {"floor_SUC": floor, "br_SUC": ceiling, "normalised_SUC": value}
                )
    return pd.DataFrame(rows)


def _matrix(
    frame: pd.DataFrame, method: str, column: str, cfg: BenchmarkConfig, keep: list[tuple[str, str]]
) -> np.ndarray:
    """A method's seeds x (task, zoo) matrix of ``column``."""
    sub = frame[frame.method == method].pivot_table(index="seed", columns=["task", "zoo"], values=column)
    return sub.reindex(columns=pd.MultiIndex.from_tuples(keep)).to_numpy(np.float64)


def aggregates(cfg: BenchmarkConfig, frame: pd.DataFrame, norm: pd.DataFrame) -> tuple[pd.DataFrame, pd.DataFrame]:
    """IQM and mean with stratified bootstrap 95 % intervals per method, and the probability of improvement
    of every method over each reference, for two scores over the test (task, zoo) pairs: SUC as a fraction,
    and the normalised SUC (over the pairs where it is defined)."""
    test = frame[(frame.kind == "method") & frame.zoo.isin(cfg.zoos)].assign(SUC_fraction=lambda f: f.SUC / 100.0)
    pairs = [(t, z) for t in cfg.tasks for z in cfg.zoos]
    scored = [("SUC", test, "SUC_fraction", pairs)]
    if len(norm):
        finite = norm.groupby(["task", "zoo"])["normalised_SUC"].apply(lambda s: bool(np.isfinite(s).all()))
        keep = [p for p in pairs if finite.get(p, False)]
        if keep:
            scored.append(("normalised SUC", norm.assign(kind="method"), "normalised_SUC", keep))
    agg_rows, poi_rows = [], []
    for label, data, column, keep in scored:
        mats = {m: _matrix(data, m, column, cfg, keep) for m in cfg.methods}
        mats = {m: x for m, x in mats.items() if x.size and np.isfinite(x).all()}
        for i, (method, x) in enumerate(mats.items()):
            for j, (stat, fn) in enumerate((("IQM", iqm), ("mean", mean_score))):
                value, low, high = bootstrap_interval(x, fn, cfg.bootstrap_reps, cfg.bootstrap_seed + 2 * i + j)
                agg_rows.append(
                    {"score": label, "method": method, "statistic": stat, "value": value, "ci95_low": low}
                    | {"ci95_high": high, "runs": x.shape[0], "tasks": x.shape[1]}
                )
        for ref in cfg.reference_methods:
            for k, (method, x) in enumerate(mats.items()):
                if method == ref or ref not in mats:
                    continue
                value, low, high = poi_interval(x, mats[ref], cfg.bootstrap_reps, cfg.bootstrap_seed + 1000 + k)
                poi_rows.append(
                    {"score": label, "method": method, "reference": ref, "P(method > reference)": value}
                    | {"ci95_low": low, "ci95_high": high}
                )
    return pd.DataFrame(agg_rows), pd.DataFrame(poi_rows)


def budget(cfg: BenchmarkConfig, records: Sequence[dict[str, Any]]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The budget per method (or bound) and task, mean over its runs (CPU-seconds too); every cell's timing."""
    rows, timing = [], []
    for rec in records:
        cell, spent = rec["cell"], rec.get("timing", {})
        row = {"method": cell["method"], "task": cell["task"], **{k: rec["budget"].get(k, 0) for k in BUDGET_KEYS}}
        rows.append({**row, "cpu_s": spent.get("cpu_s", float("nan"))})
        timing.append({"cell": rec["name"], **spent})
    order = {m: i for i, m in enumerate(_order(cfg))}
    table = (
        pd.DataFrame(rows)
        .groupby(["method", "task"], sort=False)
        .agg(runs=("env_steps", "size"), **{k: (k, "mean") for k in (*BUDGET_KEYS, "cpu_s")})
        .reset_index()
    )
    table = table.assign(_order=table["method"].map(order)).sort_values(["_order", "task"], kind="stable")
    times = pd.DataFrame(timing).sort_values("cell", kind="stable").reset_index(drop=True)
    return table.drop(columns="_order").reset_index(drop=True), times


def _pm(mean: float, std: float) -> str:
    if not np.isfinite(mean):
        return "-"
    return f"{mean:.1f}" if not np.isfinite(std) else f"{mean:.1f} +- {std:.1f}"


def markdown(
    cfg: BenchmarkConfig,
    table: pd.DataFrame,
    pairs: pd.DataFrame,
    norm: pd.DataFrame,
    agg: pd.DataFrame,
    poi: pd.DataFrame,
    spent: pd.DataFrame,
    claims: pd.DataFrame | None = None,
) -> str:
    """The report's text."""
    zoos = [*cfg.zoos, cfg.select_zoo]
    lines = [
        f"# Benchmark {cfg.name}",
        "",
        f"Methods: {', '.join(cfg.methods)}; tasks: {', '.join(cfg.tasks)}; seeds: {', '.join(map(str, cfg.seeds))}; "
        f"test zoos: {', '.join(cfg.zoos)}; selection zoo: {cfg.select_zoo or 'none'} (choices only).",
        f"Budget of every training run: about {cfg.env_steps:,} env steps ({cfg.updates_per_generation} updates per "
        f"generation); each final learner evaluated with {cfg.eval_episodes:,} episodes per zoo, the same episodes "
        "for every method of a seed. The budgets spent, per method and task (mean over runs):",
        "",
        "| method | task | runs | env steps | learner samples | eval env steps (training) | "
        "eval env steps (benchmark) | CPU-s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for _, b in spent.iterrows():
        counts = " | ".join(f"{b[k]:,.0f}" for k in BUDGET_KEYS)
        lines.append(f"| {b['method']} | {b['task']} | {b['runs']} | {counts} | {b['cpu_s']:,.0f} |")
    lines += [
        "",
        "CPU-s: the rollout workers' reserved CPU-seconds (wall time x workers) plus the CPU time of the cell's "
        "driver and evaluation, of the last attempt of each cell (timing.csv); every other number is "
        "reproducible.",
        "",
        "## Results (Table 2 layout)",
        "",
        "SUC, COL (%), AST (steps), REW: mean +- std over seeds (ddof 1). br: the best response trained with "
        "that zoo (the upper bound); floor: a random learner with the zoo's partners.",
    ]
    for task in cfg.tasks:
        header = ["method"] + [f"{z} {m}" for z in zoos for m in METRICS]
        lines += ["", f"### {task}", "", "| " + " | ".join(header) + " |", "|---" * len(header) + "|"]
        for method in _order(cfg):
            sub = table[(table.method == method) & (table.task == task)].set_index("zoo")
            if sub.empty:
                continue
            cells = []
            for z in zoos:
                for m in METRICS:
                    cells.append(_pm(sub.loc[z, f"{m}_mean"], sub.loc[z, f"{m}_std"]) if z in sub.index else "")
            lines.append(f"| {method} | " + " | ".join(cells) + " |")
    if len(pairs):
        lines += [
            "",
            "## Paired differences",
            "",
            "Method - reference over the same seeds: mean +- standard error [t-based 95 % interval].",
        ]
        for task in cfg.tasks:
            sub = pairs[pairs.task == task]
            if sub.empty:
                continue
            lines += ["", f"### {task}", "", "| difference | zoo | n | " + " | ".join(METRICS) + " |"]
            lines.append("|---" * (3 + len(METRICS)) + "|")
            for (method, ref, zoo), g in sub.groupby(["method", "reference", "zoo"], sort=False):
                by = g.set_index("metric")
                vals = [_diff(by.loc[m]) for m in METRICS]
                lines.append(f"| {method} - {ref} | {zoo} | {int(by['n'].iloc[0])} | " + " | ".join(vals) + " |")
    if len(norm):
        lines += [
            "",
            "## Normalised SUC",
            "",
            "(SUC - floor) / (best response - floor) per run: 0 is the random learner, 1 the mean best response "
            "of the task and zoo; mean +- std over seeds ('-': the best response does not beat the floor).",
            "",
        ]
        summary = norm.groupby(["method", "task", "zoo"], sort=False)["normalised_SUC"].agg(
            lambda s: _norm_cell(s.to_numpy(np.float64))
        )
        lines.append(md_table(summary.unstack("zoo")))
    if len(agg):
        lines += [
            "",
            "## Aggregates",
            "",
            f"Over the runs x (task, test zoo) scores of each method: interquartile mean (IQM) and mean with "
            f"stratified bootstrap 95 % intervals ({cfg.bootstrap_reps:,} resamples, seed {cfg.bootstrap_seed}); "
            "SUC as a fraction, and normalised SUC over the pairs where it is defined.",
            "",
            "| score | method | statistic | value | 95 % interval | runs x tasks |",
            "|---|---|---|---|---|---|",
        ]
        for _, a in agg.iterrows():
            lines.append(
                f"| {a['score']} | {a['method']} | {a['statistic']} | {a['value']:.3f} | "
                f"[{a['ci95_low']:.3f}, {a['ci95_high']:.3f}] | {a['runs']} x {a['tasks']} |"
            )
    if len(poi):
        lines += ["", "Probability of improvement (ties count half), stratified bootstrap 95 % interval:", ""]
        lines += ["| score | P(method > reference) | value | 95 % interval |", "|---|---|---|---|"]
        for _, p in poi.iterrows():
            lines.append(
                f"| {p['score']} | P({p['method']} > {p['reference']}) | {p['P(method > reference)']:.3f} | "
                f"[{p['ci95_low']:.3f}, {p['ci95_high']:.3f}] |"
            )
    if claims is not None and len(claims):
        lines += _claims_text(claims)
    return "\n".join(lines) + "\n"


def _claims_text(claims: pd.DataFrame) -> list[str]:
    """Each of the paper's orderings: how many comparisons it holds in, and every one where it does not."""
    lines = [
        "",
        "## The paper's orderings",
        "",
        "SUC of the side the paper puts ahead minus the other, paired over seeds, per task and test zoo: holds "
        "where the t-based 95 % interval is above 0, reversed where it is below, undecided otherwise.",
        "",
    ]
    for claim, g in claims.groupby("claim", sort=False):
        counts = g["verdict"].value_counts()
        parts = [f"{counts.get(v, 0)} {v}" for v in ("holds", "ahead, undecided", "behind, undecided", "reversed")]
        lines.append(f"- {claim}: {len(g)} comparisons: " + "; ".join(parts) + ".")
    misses = claims[claims.verdict != "holds"]
    if len(misses):
        lines += ["", "Where an ordering does not hold:", ""]
        lines += [
            "| claim | task | zoo | better - worse | n | SUC difference | verdict |",
            "|---|---|---|---|---|---|---|",
        ]
        for _, c in misses.iterrows():
            lines.append(
                f"| {c['claim']} | {c['task']} | {c['zoo']} | {c['better']} - {c['worse']} | {int(c['n'])} | "
                f"{_diff(c)} | {c['verdict']} |"
            )
    return lines


def _diff(row: pd.Series) -> str:
    if not np.isfinite(row["diff"]):
        return "-"
    return f"{row['diff']:+.1f} +- {row['se']:.1f} [{row['ci95_low']:+.1f}, {row['ci95_high']:+.1f}]"


def _norm_cell(x: np.ndarray) -> str:
    if not np.isfinite(x).all():
        return "-"
    mean, std = mean_std(x)
    return f"{mean:.2f}" if not np.isfinite(std) else f"{mean:.2f} +- {std:.2f}"


# the paper's two figures: the methods without teammate modelling (Fig. 3, with FCP beside them) and with it (Fig. 4)
FIGURES = {
    "fig3_without_teammate_modelling": (
        "SUC without teammate modelling (Fig. 3)",
        ("sp", "pbt", "fcp", "hola_no_g", "hola"),
    ),
    "fig4_with_teammate_modelling": ("SUC with teammate modelling (Fig. 4)", ("mappo", "naht_d_no_dec", "naht_d")),
}


def _draw_suc(ax: Any, cfg: BenchmarkConfig, sub: pd.DataFrame, methods: Sequence[str]) -> None:
    """SUC of one task per test zoo (groups) and method (bars, std as error bars); best response and floor as
    lines."""
    width = 0.8 / max(len(methods), 1)
    for i, method in enumerate(methods):
        rows = sub[sub.method == method].set_index("zoo").reindex(list(cfg.zoos))
        x = np.arange(len(cfg.zoos)) - 0.4 + width * (i + 0.5)
        ax.bar(x, rows["SUC_mean"], width, yerr=rows["SUC_std"].fillna(0.0), capsize=3, label=method)
    for bound, style in (("br", "k--"), ("floor", "k:")):
        rows = sub[sub.method == bound].set_index("zoo")
        for j, zoo in enumerate(cfg.zoos):
            if zoo in rows.index:
                label = ("best response" if bound == "br" else "floor (random)") if j == 0 else None
                ax.plot([j - 0.45, j + 0.45], [rows.loc[zoo, "SUC_mean"]] * 2, style, label=label)
    ax.set_xticks(np.arange(len(cfg.zoos)), list(cfg.zoos))


def _save(fig: Any, path: Path) -> Path:
    import matplotlib.pyplot as plt

    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
    return path


def suc_figure(cfg: BenchmarkConfig, table: pd.DataFrame, task: str, path: Path) -> Path:
    """SUC per test zoo (groups) and method (bars, std as error bars); best response and floor as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(2.0 + 1.6 * len(cfg.zoos), 3.6))
    _draw_suc(ax, cfg, table[table.task == task], list(cfg.methods))
    ax.set_ylabel("SUC (%)")
    ax.set_title(f"{cfg.name}: SUC on {task} ({cfg.env_steps:,} env steps per run)")
    ax.legend(fontsize=7, loc="upper right")
    return _save(fig, path)


def family_figure(cfg: BenchmarkConfig, table: pd.DataFrame, title: str, methods: Sequence[str], path: Path) -> Path:
    """One of the paper's figures: a panel per task, the family's methods as bars per test zoo, the best
    response and the floor as lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(cfg.tasks), figsize=(1.2 + 3.2 * len(cfg.tasks), 3.6), sharey=True, squeeze=False)
    for ax, task in zip(axes[0], cfg.tasks, strict=True):
        _draw_suc(ax, cfg, table[table.task == task], methods)
        ax.set_title(task)
    axes[0][0].set_ylabel("SUC (%)")
    axes[0][-1].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{cfg.name}: {title}, mean +- std over {len(cfg.seeds)} seeds, {cfg.env_steps:,} env steps per run")
    return _save(fig, path)


def write_report(cfg: BenchmarkConfig, records: Sequence[dict[str, Any]]) -> dict[str, Path]:
    """Write every report file to ``cfg.results``; the paths by name."""
    frame = evaluations(records)
    table = table2(cfg, frame)
    pairs = paired(cfg, frame)
    norm = normalised(cfg, frame)
    agg, poi = aggregates(cfg, frame, norm)
    spent, timing = budget(cfg, records)
    claims = orderings(cfg, frame)
    out = cfg.results
    files: dict[str, Path] = {}
    for name, data in (
        ("evaluations", frame),
        ("table", table),
        ("paired", pairs),
        ("normalised", norm),
        ("aggregate", agg),
        ("improvement", poi),
        ("budget", spent),
        ("timing", timing),
        ("orderings", claims),
    ):
        files[f"{name}.csv"] = atomic_write_bytes(out / f"{name}.csv", data.to_csv(index=False).encode())
    files["report.md"] = atomic_write_text(
        out / "report.md", markdown(cfg, table, pairs, norm, agg, poi, spent, claims)
    )
    for task in cfg.tasks:
        files[f"suc_{task}.png"] = suc_figure(cfg, table, task, out / f"suc_{task}.png")
    for name, (title, family) in FIGURES.items():
        methods = [m for m in family if m in cfg.methods]
        if methods:
            files[f"{name}.png"] = family_figure(cfg, table, title, methods, out / f"{name}.png")
    return files
