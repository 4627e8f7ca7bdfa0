"""Pictures of a population: the preference hypergraph and the cross-play heatmap."""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import pandas as pd

from atdrone.fileio import atomic_write_bytes


def _figure(width: float, height: float) -> tuple[Any, Any, Any]:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    return plt, *plt.subplots(figsize=(width, height), dpi=100)


def _save(plt: Any, fig: Any, path: Path) -> None:
    buf = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def draw_hypergraph(
    weights: dict[str, float], preference: dict[str, list[str]], eta: dict[str, float], path: Path
) -> None:
    """Members on a circle (size: eta); each member's preferred team drawn as arrows to its co-members.

    weights: team ("a|b|c|d") -> weight; preference: member -> its preferred team.
    """
    plt, fig, ax = _figure(5.5, 5.5)
    nodes = sorted(set(eta) | {m for team in weights for m in team.split("|")})
    pos = {
        n: (math.cos(2 * math.pi * i / len(nodes)), math.sin(2 * math.pi * i / len(nodes))) for i, n in enumerate(nodes)
    }
    for key in weights:
        distinct = sorted(set(key.split("|")))
        xs = [pos[m][0] for m in distinct] + [pos[distinct[0]][0]]
        ys = [pos[m][1] for m in distinct] + [pos[distinct[0]][1]]
        ax.plot(xs, ys, color="0.85", lw=0.8, zorder=1)
    for node, team in preference.items():
        for other in set(team) - {node}:
            (x0, y0), (x1, y1) = pos[node], pos[other]
            ax.annotate("", (x1, y1), (x0, y0), arrowprops={"arrowstyle": "->", "color": "tab:blue", "alpha": 0.6})
    for n in nodes:
        e = eta.get(n, 0.0)
        ax.scatter(*pos[n], s=300 + 1500 * e, color="tab:orange", zorder=3, edgecolor="k")
        ax.text(pos[n][0], pos[n][1] - 0.18, f"{n}\neta {e:.2f}", ha="center", va="top", fontsize=7)
    ax.set_xlim(-1.5, 1.5)
    ax.set_ylim(-1.6, 1.4)
    ax.set_axis_off()
    ax.set_title("preference hypergraph (arrows: each member's best team)", fontsize=9)
    _save(plt, fig, path)


def crossplay_heatmap(table: pd.DataFrame, path: Path, title: str = "cross-play SUC") -> None:
    """A member x member heatmap of a cross-play matrix (NaN cells left blank)."""
    plt, fig, ax = _figure(1.5 + 0.55 * len(table.columns), 1.2 + 0.5 * len(table.index))
    im = ax.imshow(table.to_numpy(dtype=float), cmap="viridis", vmin=0, vmax=100)
    ax.set_xticks(range(len(table.columns)), [str(c) for c in table.columns], rotation=60, ha="right", fontsize=7)
    ax.set_yticks(range(len(table.index)), [str(i) for i in table.index], fontsize=7)
    for (i, j), v in pd.DataFrame(table.to_numpy(dtype=float)).stack().items():
        ax.text(j, i, f"{v:.0f}", ha="center", va="center", fontsize=7, color="w" if v < 60 else "k")
    fig.colorbar(im, ax=ax, shrink=0.8)
    ax.set_title(title, fontsize=9)
    _save(plt, fig, path)
