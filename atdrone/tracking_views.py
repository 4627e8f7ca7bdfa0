"""What MLflow is given to show a population, worked out without MLflow: per-member values as one series per
name, the run description's population table, the parent run's main numbers, and the experiment page's view
(columns and charts) that the links atdrone prints open (:mod:`atdrone.tracking` logs and sets them)."""

from __future__ import annotations

import base64
import json
import zlib
from collections.abc import Iterable, Mapping, Sequence
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


# ---------------------------------------------------------------------------------------------- the shared view
# MLflow 3's experiment page takes its columns and charts from the browser's localStorage, or from a "shared view":
# the experiment tag ``mlflow.sharedViewState.<id>`` opened with ``#/experiments/<n>/runs?viewStateShareKey=<id>``
# (the redirect from ``#/experiments/<n>`` keeps only a few parameters and drops that one). The tag holds an
# envelope ``{name, createdAt, updatedAt, state}`` whose ``state`` is the page's UI state as JSON text, plain or
# ``deflate;`` + base64 of its zlib bytes; MLflow takes only its known keys (``selectedColumns``,
# ``compareRunCharts``, ``compareRunSections``, ``isAccordionReordered``, ``hideEmptyCharts``, ...).
VIEW_ID = "atdrone"
VIEW_TAG = f"mlflow.sharedViewState.{VIEW_ID}"
VIEW_NAME = "atdrone: key metrics"
VIEW_TAG_LIMIT = 20_000  # MLflow's longest experiment tag value
MODEL_METRICS = "Model metrics"  # MLflow's chart section for the metric names without a "/"
_COMPRESSED = "deflate;"
_KEY_SUFFIXES = ("_SUC_best", "_SUC_mean", "_SUC_champion")
_KEY_LEAVES = ("SUC", "COL", "AST", "REW")
_MAX_COLUMNS = 8


def key_metric_columns(keys: Iterable[str]) -> list[str]:
    """The metric names a runs table shows as columns, SUC first: a population's ``<zoo>_SUC_best``, ``_mean``
    and ``_champion``, a run's or an evaluation's ``.../SUC`` (then COL, AST, REW); never a curve (``gen/...``)
    nor an interval bound."""

    def rank(key: str) -> tuple[int, int, str] | None:
        if key.startswith("gen/"):
            return None
        for i, suffix in enumerate(_KEY_SUFFIXES):
            if key.endswith(suffix) and "/" not in key:
                return (0, i, key)
        leaf = key.rpartition("/")[2]
        if leaf in _KEY_LEAVES:
            return (1, _KEY_LEAVES.index(leaf), key)
        return None

    ranked = sorted(r for r in map(rank, set(keys)) if r is not None)
    return [key for *_, key in ranked[:_MAX_COLUMNS]]


def _duplicate(key: str) -> bool:
    """``eval/<zoo>/best_SUC`` and ``eval/<zoo>/selected_SUC``: the numbers ``<zoo>_SUC_best`` and
    ``<zoo>_SUC_champion`` already chart."""
    parts = key.split("/")
    return len(parts) == 3 and parts[0] == "eval" and parts[2] in ("best_SUC", "selected_SUC")


def _section(key: str) -> str:
    head, _, _ = key.rpartition("/")
    return head or MODEL_METRICS


def runs_view_state(top: Iterable[str], nested: Iterable[str] = ()) -> dict[str, Any]:
    """The experiment page's UI state for metric names ``top`` (logged by top-level runs) and ``nested`` (only by
    nested runs): the key numbers as columns and bar charts first, one section per name prefix with a chart per
    name, and the nested runs' names as deleted charts.

    The table shows top-level runs with their children folded, so a chart of a nested-only name is empty and its
    section (``budget``, ``pop``, ``train``) a blank one; named here as deleted, MLflow never adds them back. A name
    missing from the state (logged after it was written) gets a chart of its own when the page loads.
    """
    top_keys = sorted(set(top))
    hidden = sorted(set(nested) - set(top_keys)) + [k for k in top_keys if _duplicate(k)]
    shown = [k for k in top_keys if not _duplicate(k)]
    columns = key_metric_columns(shown)
    summary = [k for k in columns if "/" not in k]  # a population's numbers, logged once at its last step
    selected = ["attributes.`Models`", *(f"metrics.`{k}`" for k in columns)]
    if not shown:  # no runs yet: MLflow draws its own charts until the view is written again
        return {"selectedColumns": selected, "hideEmptyCharts": True}
    sections = sorted({_section(k) for k in shown}, key=lambda name: (name != MODEL_METRICS, name))

    def chart(key: str, deleted: bool = False) -> dict[str, Any]:
        # a summary number as a bar per run (not "generated": MLflow would redraw it as a one-point line); the
        # rest "generated" bars, which MLflow redraws as lines when they have steps (a run's eval/SUC curve)
        return {
            "uuid": f"atdrone-chart-{key}",
            "type": "BAR",
            "runsCountToCompare": 10,
            "metricSectionId": f"atdrone-section-{'' if deleted else _section(key)}",
            "deleted": deleted,
            "isGenerated": key not in summary,
            "metricKey": key,
            "displayName": key.rpartition("/")[2],
        }

    return {
        "selectedColumns": selected,
        "hideEmptyCharts": True,
        "isAccordionReordered": True,  # keep this order of sections
        "compareRunSections": [
            {
                "uuid": f"atdrone-section-{name}",
                "name": name,
                "display": True,
                "isReordered": False,
                "deleted": False,
                "isGenerated": True,
            }
            for name in sections
        ],
        "compareRunCharts": [
            *(chart(k) for k in sorted(shown, key=lambda k: (k not in summary, k))),
            *(chart(k, deleted=True) for k in hidden),
        ],
    }


def view_tag_value(state: Mapping[str, Any], created_ms: int, updated_ms: int | None = None) -> str:
    """The value of :data:`VIEW_TAG`: MLflow's envelope around ``state`` compressed (zlib, base64, ``deflate;``).

    ValueError when even that is over MLflow's tag limit.
    """
    packed = _COMPRESSED + base64.b64encode(zlib.compress(json.dumps(state).encode(), 9)).decode()
    envelope = {
        "name": VIEW_NAME,
        "createdAt": int(created_ms),
        "updatedAt": int(created_ms if updated_ms is None else updated_ms),
        "state": packed,
    }
    value = json.dumps(envelope)
    if len(value) > VIEW_TAG_LIMIT:
        raise ValueError(f"the view is {len(value)} characters, over MLflow's {VIEW_TAG_LIMIT}")
    return value


def read_view(value: str) -> tuple[int, dict[str, Any]]:
    """The creation time (ms) and the state of a :data:`VIEW_TAG` value (plain or compressed, as MLflow reads it)."""
    envelope = json.loads(value)
    state = str(envelope["state"])
    if state.startswith(_COMPRESSED):
        state = zlib.decompress(base64.b64decode(state.removeprefix(_COMPRESSED))).decode()
    return int(envelope["createdAt"]), dict(json.loads(state))
