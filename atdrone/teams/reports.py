"""Evaluation results as the paper lays them out: a text table, a JSON summary and a CSV of episodes.

The table has a row block per task (one line per metric) and a column per zoo, each
cell the value over all episodes and its 95 % confidence interval over episodes
(``73.0 [69.0, 76.7]``), with several seeds also the interval over the seeds' values;
a zoo with missing members shows them instead. The
JSON holds, per cell, the aggregated summary and the per-seed metrics (NaN, e.g. AST
without a success, is written as null); the CSV holds every episode record. Both
files are written atomically.
"""

from __future__ import annotations

import io
import json
import math
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from atdrone.fileio import atomic_write_text
from atdrone.teams.evaluation import METRICS, GridCell

UNITS = {"SUC": "%", "COL": "%", "AST": "steps", "REW": ""}
DECIMALS = {"SUC": 1, "COL": 1, "AST": 1, "REW": 2}
SEEDS_NOTE = "; seeds [95 % CI over the seeds' values]"


def _cell_lines(cell: GridCell) -> list[str]:
    if cell.evaluation is None:
        return [f"missing: {', '.join(cell.missing)}"] + [""] * (len(METRICS) - 1)
    value, interval, over_seeds = cell.evaluation.pooled, cell.evaluation.interval, cell.evaluation.seed_interval
    lines = []
    for m in METRICS:
        if math.isnan(value[m]):
            lines.append("n/a")
            continue
        text = f"{_number(value[m], m)} {_bounds(interval[m], m)}"
        if over_seeds is not None:
            text += f"; seeds {_bounds(over_seeds[m], m)}"
        lines.append(text)
    return lines


def _number(value: float, metric: str) -> str:
    return f"{value:.{DECIMALS[metric]}f}"


def _bounds(interval: tuple[float, float], metric: str) -> str:
    """``[low, high]``, or ``[n/a]`` when too few values give no interval (one successful episode's AST)."""
    low, high = interval
    if math.isnan(low) or math.isnan(high):
        return "[n/a]"
    return f"[{_number(low, metric)}, {_number(high, metric)}]"


def format_table(cells: Sequence[GridCell], learner: str, episodes: int, seeds: Sequence[int]) -> str:
    """The grid as text: rows tasks (a line per metric), columns zoos."""
    tasks = list(dict.fromkeys(c.task for c in cells))
    zoos = list(dict.fromkeys(c.zoo for c in cells))
    by_key = {(c.task, c.zoo): _cell_lines(c) for c in cells}
    labels = [f"{m} {UNITS[m]}".strip() for m in METRICS]
    task_w = max(len("task"), *(len(t) for t in tasks))
    metric_w = max(len("metric"), *(len(s) for s in labels))
    zoo_w = {z: max(len(z), *(len(line) for t in tasks for line in by_key.get((t, z), [""]))) for z in zoos}
    seed_text = ", ".join(map(str, seeds))
    out = [
        f"{learner}: {episodes} episodes per seed, {len(seeds)} seed{'s' if len(seeds) != 1 else ''} ({seed_text});"
        f" value over all episodes [95 % CI over episodes]{SEEDS_NOTE if len(seeds) > 1 else ''}",
        "",
        "  ".join([f"{'task':<{task_w}}", f"{'metric':<{metric_w}}", *(f"{z:<{zoo_w[z]}}" for z in zoos)]).rstrip(),
        "  ".join(["-" * task_w, "-" * metric_w, *("-" * zoo_w[z] for z in zoos)]),
    ]
    for n, task in enumerate(tasks):
        if n:
            out.append("")
        for i, label in enumerate(labels):
            row = [f"{task if i == 0 else '':<{task_w}}", f"{label:<{metric_w}}"]
            row += [f"{by_key.get((task, z), [''] * len(METRICS))[i]:<{zoo_w[z]}}" for z in zoos]
            out.append("  ".join(row).rstrip())
    return "\n".join(out)


def _finite(value: Any) -> Any:
    """JSON-safe: NaN and infinities become None, numpy scalars plain Python."""
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def report_document(cells: Sequence[GridCell], learner: str, episodes: int, seeds: Sequence[int]) -> dict[str, Any]:
    """The JSON summary: run settings, and per cell its summary and per-seed metrics (or what is missing)."""
    doc_cells: list[dict[str, Any]] = []
    for c in cells:
        if c.evaluation is None:
            doc_cells.append({"task": c.task, "zoo": c.zoo, "status": "missing", "missing": list(c.missing)})
            continue
        per_seed = c.evaluation.per_seed.reset_index().to_dict(orient="records")
        doc_cells.append(
            {"task": c.task, "zoo": c.zoo, "status": "ok", "summary": c.evaluation.summary(), "per_seed": per_seed}
        )
    doc: dict[str, Any] = {
        "learner": learner,
        "episodes_per_seed": episodes,
        "seeds": list(seeds),
        "metrics": {"SUC": "% success", "COL": "% collision", "AST": "mean steps of successes", "REW": "mean return"},
        "cells": doc_cells,
    }
    return _finite(doc)


def episode_table(cells: Sequence[GridCell]) -> pd.DataFrame:
    """Every episode record of the evaluated cells, with task, zoo and learner columns first."""
    frames = []
    for c in cells:
        if c.evaluation is not None:
            frame = c.evaluation.records.copy()
            frame.insert(0, "learner", c.evaluation.learner)
            frame.insert(0, "zoo", c.zoo)
            frame.insert(0, "task", c.task)
            frames.append(frame)
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def write_report(
    out_dir: str | os.PathLike[str],
    stem: str,
    cells: Sequence[GridCell],
    learner: str,
    episodes: int,
    seeds: Sequence[int],
) -> tuple[Path, Path]:
    """Write ``<out_dir>/<stem>.json`` (summary) and ``<stem>.csv`` (episodes) atomically; their paths."""
    out = Path(out_dir)
    doc = report_document(cells, learner, episodes, seeds)
    json_path = atomic_write_text(out / f"{stem}.json", json.dumps(doc, indent=2, allow_nan=False) + "\n")
    buffer = io.StringIO()
    episode_table(cells).to_csv(buffer, index=False)
    csv_path = atomic_write_text(out / f"{stem}.csv", buffer.getvalue())
    return json_path, csv_path
