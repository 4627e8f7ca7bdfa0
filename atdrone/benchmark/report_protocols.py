"""The benchmark report's team-change table: each method's final learners played on the protocols of team events.

From the cell records' ``protocols`` (a benchmark config's ``protocols`` key): per method x
task x protocol, over the seeds, the mean and std (ddof 1) of SUC, of SUC after the first
event (SUC_post) and of the recovery time (REC, steps from the event to the next capture).
These protocols have no bounds, so they are in no normalised score or aggregate.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np
import pandas as pd

from atdrone.benchmark.stats import mean_std

COLUMNS = ("SUC", "SUC_post", "REC", "EVT")


def protocol_table(records: Sequence[dict[str, Any]]) -> pd.DataFrame:
    """One row per (method, task, protocol): n seeds and each of :data:`COLUMNS`' mean and std."""
    rows = []
    for rec in records:
        cell = rec["cell"]
        for name, values in rec.get("protocols", {}).items():
            row = {"method": cell["method"], "task": cell["task"], "protocol": name, "seed": cell["seed"]}
            rows.append(row | {k: values.get(k, np.nan) for k in COLUMNS})
    if not rows:
        return pd.DataFrame()
    frame = pd.DataFrame(rows)
    out = []
    for (method, task, name), g in frame.groupby(["method", "task", "protocol"], sort=False):
        summary: dict[str, Any] = {"method": method, "task": task, "protocol": name, "n": len(g)}
        for k in COLUMNS:
            summary[f"{k}_mean"], summary[f"{k}_std"] = mean_std(g[k].dropna())
        out.append(summary)
    return pd.DataFrame(out)


def protocols_text(table: pd.DataFrame, episodes: int) -> list[str]:
    """The report's section (none without protocols)."""
    if table.empty:
        return []
    lines = [
        "",
        "## Team changes (protocols of team events)",
        "",
        f"Each method's final learners played on the protocols ({episodes} episodes per seed): SUC over all the "
        "episodes, SUC_post over the episodes that lived to the first event, REC the mean steps from the event "
        "to the next capture; mean ± std over seeds (ddof 1). No bounds: not in the normalised scores.",
        "",
        "| method | task | protocol | n | SUC | SUC_post | REC (steps) |",
        "|---|---|---|---|---|---|---|",
    ]
    for _, r in table.iterrows():
        cells = [f"{r[f'{k}_mean']:.1f} ± {r[f'{k}_std']:.1f}" for k in ("SUC", "SUC_post", "REC")]
        lines.append(f"| {r['method']} | {r['task']} | {r['protocol']} | {r['n']} | {' | '.join(cells)} |")
    return lines
