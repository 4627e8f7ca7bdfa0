"""What MLflow is given to show a population, worked out without MLflow: per-member values as one series per
name, the run description's population table, the parent run's main numbers (:mod:`atdrone.tracking` logs them)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any


def member_series(
    metrics: Mapping[str, float], members: Sequence[str]
) -> tuple[dict[str, float], dict[str, list[float]]]:
    """Split per-member metrics (``pop/rho/hola-g0-1``, ``pop/drawn/hola-g3-0/hola-g0-1``) into one series per
    name over ``members`` (``pop/rho`` at step i is member i's value, NaN where a member has none) and the rest.

    MLflow draws one chart per metric key: a population's per-member values as keys of their own are a wall of
    single-point charts; as one series they are one chart with the population along its x axis.
    """
    order = {m: i for i, m in enumerate(members)}
    series: dict[str, list[float]] = {}
    rest: dict[str, float] = {}
    for key, value in metrics.items():
        head, _, member = key.rpartition("/")
        if head and member in order:
            values = series.setdefault(head, [float("nan")] * len(members))
            values[order[member]] = float(value)
        else:
            rest[key] = value
    return rest, series


def population_markdown(rows: Sequence[Mapping[str, Any]], title: str) -> str:
    """A run description: ``title``, then the population table (one row per member) as Markdown."""
    if not rows:
        return title
    columns = list(dict.fromkeys(k for row in rows for k in row))

    def cell(value: Any) -> str:
        if isinstance(value, float):
            return "-" if value != value else f"{value:.2f}"
        return str(value)

    lines = [title, "", "| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    lines += ["| " + " | ".join(cell(row.get(c)) for c in columns) + " |" for row in rows]
    return "\n".join(lines)


def population_columns(
    rows: Sequence[Mapping[str, Any]], select_zoo: str, final_zoo: str, best: str
) -> dict[str, float]:
    """The parent run's main numbers, as metrics the runs table shows as columns: the best and mean SUC on the
    selection zoo and the chosen member's (the champion's) SUC on the test zoo."""
    out: dict[str, float] = {}
    chosen = [float(r[f"{select_zoo}_SUC"]) for r in rows if _finite(r.get(f"{select_zoo}_SUC"))] if select_zoo else []
    if chosen:
        out[f"{select_zoo}_SUC_best"] = max(chosen)
        out[f"{select_zoo}_SUC_mean"] = sum(chosen) / len(chosen)
    mine = [r for r in rows if r.get("member") == best and _finite(r.get(f"{final_zoo}_SUC"))] if final_zoo else []
    if mine:
        out[f"{final_zoo}_SUC_champion"] = float(mine[0][f"{final_zoo}_SUC"])
    return out


def _finite(value: Any) -> bool:
    return (
        isinstance(value, int | float) and not isinstance(value, bool) and value == value and abs(value) != float("inf")
    )
