"""The benchmark beside the paper: Table 2 value by value, and each ordering the paper states.

- :func:`side_by_side`: for every method x task x zoo x metric of the paper's Table 2
  (:mod:`atdrone.benchmark.paper`: COL, AST, REW; the paper gives no SUC there) the paper's
  mean +- std, ours (mean +- std over seeds and the t-based 95 % interval of the mean, n - 1
  degrees of freedom from the seeds with a value), and ours minus the paper's.
- :func:`orderings`: each ordering the paper's text states (:data:`CLAIMS`), per task and
  test zoo, as SUC of the side put ahead minus the other, paired over the seeds both ran, with
  a verdict (holds, reversed, or undecided with its direction), beside the paper's own Table 2
  differences where the table has both sides. The paper's figures (SUC, Figs. 3 and 4) are
  images whose numbers its LaTeX source does not give.

The zoos are the project's (``configs/zoos``, per task), built after the paper's description,
not the paper's partners: a difference from the paper mixes the method with the partners.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import pandas as pd

from atdrone.benchmark.config import BenchmarkConfig
from atdrone.benchmark.paper import PAPER_METHODS, PAPER_METRICS, TABLE2
from atdrone.benchmark.stats import mean_std, paired_difference, t_interval

# The paper's orderings (Sec. 5, Figs. 3-4): (claim, better, worse, tasks, zoos); None: every task or test zoo.
# "br" is the best response of each (task, zoo); the easy tasks are 4p2e3o and 4p2e1o, the hard 4p2e5o and 4p3e5o.
EASY, HARD = ("4p2e3o", "4p2e1o"), ("4p2e5o", "4p3e5o")
CLAIMS: tuple[tuple[str, str, tuple[str, ...] | None, tuple[str, ...] | None, tuple[str, ...] | None], ...] = (
    ("HOLA-Drone V2 ahead of SP and w/o g on Zoo 3 in the hard tasks", "hola", ("sp", "hola_no_g"), HARD, ("zoo3",)),
    ("the best response is the upper bound", "br", None, None, None),
    ("NAHT-D ahead of MAPPO on the easy tasks", "naht_d", ("mappo",), EASY, None),
    ("NAHT-D w/o Dec ahead of MAPPO on the easy tasks", "naht_d_no_dec", ("mappo",), EASY, None),
    ("NAHT-D w/o Dec ahead of NAHT-D on the hard tasks", "naht_d_no_dec", ("naht_d",), HARD, None),
)
# the (method, task) runs the claims compare, where a preset gives more seeds
ORDERING_RUNS: tuple[tuple[tuple[str, ...], tuple[str, ...]], ...] = (
    (("hola", "sp", "hola_no_g"), HARD),
    (("naht_d", "naht_d_no_dec", "mappo"), EASY),
    (("naht_d_no_dec", "naht_d"), HARD),
)


def _verdict(diff: float, low: float, high: float) -> str:
    if not np.isfinite(low):
        return "-"
    if low > 0:
        return "holds"
    if high < 0:
        return "reversed"
    return "ahead, undecided" if diff > 0 else "behind, undecided"


def _paper_difference(better: str, worse: str, task: str, zoo: str) -> str:
    """The paper's Table 2 difference better - worse (REW, COL, AST) for a (task, zoo), where it has both."""
    cell = TABLE2.get(task, {}).get(zoo, {})
    if better not in cell or worse not in cell:
        return "Table 2 lacks one side (SUC: a figure without numbers)"
    return ", ".join(f"{m} {cell[better][m][0] - cell[worse][m][0]:+.1f}" for m in ("REW", "COL", "AST"))


def orderings(cfg: BenchmarkConfig, frame: pd.DataFrame) -> pd.DataFrame:
    """The paper's orderings (:data:`CLAIMS`) checked where the config has both sides: SUC of the better
    side minus the worse over the seeds both ran (paired, t-based 95 % interval), a verdict: holds (the
    interval above 0), reversed (below 0), or ahead / behind but undecided; and the paper's Table 2
    differences of the same pair."""
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
                        {"claim": claim, "task": task, "zoo": zoo, "better": better, "worse": other, "n": d["n"]}
                        | {"diff": d["diff"], "se": d["se"], "ci95_low": low, "ci95_high": high}
                        | {"verdict": _verdict(d["diff"], low, high)}
                        | {"paper": _paper_difference(better, other, task, zoo)}
                    )
    return pd.DataFrame(rows)


def side_by_side(cfg: BenchmarkConfig, frame: pd.DataFrame) -> pd.DataFrame:
    """One row per method x task x zoo x metric of the paper's Table 2 that this benchmark measured."""
    rows = []
    for task in [t for t in cfg.tasks if t in TABLE2]:
        for zoo in [z for z in cfg.zoos if z in TABLE2[task]]:
            for method in [m for m in PAPER_METHODS if m in cfg.methods]:
                g = frame[(frame.method == method) & (frame.task == task) & (frame.zoo == zoo)]
                if g.empty:
                    continue
                for metric in PAPER_METRICS:
                    paper_mean, paper_std = TABLE2[task][zoo][method][metric]
                    values = g[metric].to_numpy(np.float64)
                    mean, std = mean_std(values)
                    ci = t_interval(values)
                    low, high = ci["ci95"]
                    rows.append(
                        {"task": task, "zoo": zoo, "method": method, "metric": metric}
                        | {"paper_mean": paper_mean, "paper_std": paper_std, "n": ci["n"], "mean": mean, "std": std}
                        | {"ci95_low": low, "ci95_high": high, "diff": mean - paper_mean}
                        | {"paper_in_interval": bool(low <= paper_mean <= high) if np.isfinite(low) else None}
                    )
    return pd.DataFrame(rows)


def _ours(row: Any) -> str:
    if not np.isfinite(row["mean"]):
        return "-"
    interval = f" [{row['ci95_low']:.1f}, {row['ci95_high']:.1f}]" if np.isfinite(row["ci95_low"]) else ""
    return f"{row['mean']:.1f}{interval} (n {int(row['n'])})"


def side_by_side_text(side: pd.DataFrame) -> list[str]:
    """The side-by-side table's Markdown section."""
    if side.empty:
        return []
    lines = [
        "",
        "## Beside the paper (Table 2)",
        "",
        "Per method, task and test zoo: the paper's mean +- std; ours, the mean over seeds with its t-based 95 % "
        "interval (n - 1 degrees of freedom, n the seeds with a value: AST needs a success); ours - paper. The "
        "zoos are the project's, built after the paper's description, not the paper's partners. The paper gives "
        "no SUC in Table 2.",
        "",
        "| task | zoo | method | " + " | ".join(f"{m} paper | {m} ours | {m} diff" for m in PAPER_METRICS) + " |",
        "|---" * (3 + 3 * len(PAPER_METRICS)) + "|",
    ]
    for (task, zoo, method), g in side.groupby(["task", "zoo", "method"], sort=False):
        by = g.set_index("metric")
        cells = []
        for m in PAPER_METRICS:
            r = by.loc[m]
            diff = f"{r['diff']:+.1f}" if np.isfinite(r["diff"]) else "-"
            cells += [f"{r['paper_mean']:.1f} +- {r['paper_std']:.1f}", _ours(r), diff]
        lines.append(f"| {task} | {zoo} | {method} | " + " | ".join(cells) + " |")
    inside = side["paper_in_interval"].dropna()
    lines += ["", f"The paper's mean lies inside our interval in {int(inside.sum())} of {len(inside)} comparisons."]
    return lines


def diff_text(row: Any) -> str:
    if not np.isfinite(row["diff"]):
        return "-"
    if not np.isfinite(row["se"]):
        return f"{row['diff']:+.1f}"
    return f"{row['diff']:+.1f} +- {row['se']:.1f} [{row['ci95_low']:+.1f}, {row['ci95_high']:+.1f}]"


def orderings_text(claims: pd.DataFrame) -> list[str]:
    """Each of the paper's orderings: a summary line per claim and a row per comparison."""
    if claims.empty:
        return []
    lines = [
        "",
        "## The paper's orderings",
        "",
        "SUC of the side the paper puts ahead minus the other, paired over seeds, per task and test zoo (mean "
        "+- standard error [t-based 95 % interval, n - 1 degrees of freedom]): holds where the interval is "
        "above 0, reversed where it is below, undecided otherwise. The paper's column: its Table 2 differences "
        "of the same pair (its SUC is in figures without numbers).",
        "",
    ]
    for claim, g in claims.groupby("claim", sort=False):
        counts = g["verdict"].value_counts()
        parts = [f"{counts.get(v, 0)} {v}" for v in ("holds", "ahead, undecided", "behind, undecided", "reversed")]
        lines.append(f"- {claim}: {len(g)} comparisons: " + "; ".join(parts) + ".")
    lines += [
        "",
        "| claim | task | zoo | better - worse | n | SUC difference | verdict | the paper's Table 2 |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for _, c in claims.iterrows():
        lines.append(
            f"| {c['claim']} | {c['task']} | {c['zoo']} | {c['better']} - {c['worse']} | {int(c['n'])} | "
            f"{diff_text(c)} | {c['verdict']} | {c['paper']} |"
        )
    return lines
