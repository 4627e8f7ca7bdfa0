"""The benchmark report's figures (PNG): SUC per task, the paper's two figures, the performance profiles.

Every figure is a pure function of the report's tables; matplotlib is imported inside the
functions that draw (the Agg backend: no display needed).
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from atdrone.benchmark.config import BenchmarkConfig
from atdrone.fileio import atomic_write_bytes

# the paper's two figures: the methods without teammate modelling (Fig. 3, with FCP beside them) and with it (Fig. 4)
FIGURES = {
    "fig3_without_teammate_modelling": (
        "SUC without teammate modelling (Fig. 3)",
        ("sp", "pbt", "fcp", "hola_no_g", "hola"),
    ),
    "fig4_with_teammate_modelling": ("SUC with teammate modelling (Fig. 4)", ("mappo", "naht_d_no_dec", "naht_d")),
}


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


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
    plt = _pyplot()
    fig.tight_layout()
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buffer.getvalue())
    return path


def suc_figure(cfg: BenchmarkConfig, table: pd.DataFrame, task: str, path: Path) -> Path:
    """SUC per test zoo (groups) and method (bars, std as error bars); best response and floor as lines."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(2.0 + 1.6 * len(cfg.zoos), 3.6))
    _draw_suc(ax, cfg, table[table.task == task], list(cfg.methods))
    ax.set_ylabel("SUC (%)")
    ax.set_title(f"{cfg.name}: SUC on {task} ({cfg.env_steps:,} env steps per run)")
    ax.legend(fontsize=7, loc="upper right")
    return _save(fig, path)


def family_figure(cfg: BenchmarkConfig, table: pd.DataFrame, title: str, methods: Sequence[str], path: Path) -> Path:
    """One of the paper's figures: a panel per task, the family's methods as bars per test zoo, the best
    response and the floor as lines."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, len(cfg.tasks), figsize=(1.2 + 3.2 * len(cfg.tasks), 3.6), sharey=True, squeeze=False)
    for ax, task in zip(axes[0], cfg.tasks, strict=True):
        _draw_suc(ax, cfg, table[table.task == task], methods)
        ax.set_title(task)
    axes[0][0].set_ylabel("SUC (%)")
    axes[0][-1].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{cfg.name}: {title}, mean +- std over {len(cfg.seeds)} seeds, {cfg.env_steps:,} env steps per run")
    return _save(fig, path)


def profile_figure(cfg: BenchmarkConfig, profiles: pd.DataFrame, path: Path) -> Path:
    """rliable's performance profiles: per score (a panel), the share of (run, task, zoo) scores above each
    threshold, a line per method with its bootstrap 95 % band."""
    plt = _pyplot()
    scores = list(dict.fromkeys(profiles["score"]))
    fig, axes = plt.subplots(1, len(scores), figsize=(1.0 + 4.2 * len(scores), 3.6), squeeze=False)
    for ax, score in zip(axes[0], scores, strict=True):
        sub = profiles[profiles.score == score]
        for method, g in sub.groupby("method", sort=False):
            line = ax.plot(g["tau"], g["value"], label=method)[0]
            ax.fill_between(g["tau"], g["ci95_low"], g["ci95_high"], color=line.get_color(), alpha=0.2)
        ax.set_xlabel(f"{score} threshold tau")
        ax.set_title(score)
        ax.set_ylim(-0.02, 1.02)
    axes[0][0].set_ylabel("share of runs x (task, zoo) above tau")
    axes[0][-1].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"{cfg.name}: performance profiles, {len(cfg.seeds)} seeds, {cfg.env_steps:,} env steps per run")
    return _save(fig, path)
