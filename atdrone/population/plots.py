"""Pictures of a population: the preference hypergraph and the cross-play heatmap.

Each picture has a builder that returns the matplotlib Figure (what the tests read:
labels, colour bars, arrows) and a writer that saves it as a PNG atomically.
"""

from __future__ import annotations

import io
import math
import textwrap
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from atdrone.fileio import atomic_write_bytes


def _pyplot() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    return plt


def save_figure(fig: Any, path: Path) -> Path:
    """Write ``fig`` as a PNG (temp name, then rename) and close it."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", bbox_inches="tight")
    _pyplot().close(fig)
    atomic_write_bytes(path, buf.getvalue())
    return path


# ------------------------------------------------------------------ cross-play
def crossplay_figure(table: pd.DataFrame, title: str = "cross-play SUC", metric: str = "SUC") -> Any:
    """A member x partner heatmap of a cross-play matrix (rows: the member, columns: its partner; NaN blank).

    Axis labels, a colour bar labelled with the metric, cell values while legible, and a
    title wrapped to the figure's width. The colour scale spans the values present
    (:func:`colour_range`), so a matrix of 2-7 % is not all one dark colour. Cells are
    0.5 in a side, smaller past 18 members so the heatmap stays within 9 in; tick labels
    keep 9 pt up to 30 members (6 pt at 50).
    """
    plt = _pyplot()
    n_rows, n_cols = table.shape
    cell = min(0.5, 9.0 / max(n_rows, n_cols, 1))  # inches a side: the heatmap stays within 9 in
    tick = float(np.clip(0.42 * cell * 72, 6.0, 9.0))  # pt: a tick label fits its row or column
    names = [str(x) for x in (*table.index, *table.columns)]
    label = 0.55 * tick / 72 * max(map(len, names), default=1)  # inches of the longest tick label
    width, height = max(n_cols, 4) * cell + label + 2.2, max(n_rows, 4) * cell + 0.85 * label + 1.4
    fig, ax = plt.subplots(figsize=(width, height), dpi=100, layout="constrained")
    values = table.to_numpy(dtype=float)
    percent = metric in ("SUC", "COL")
    low, high = colour_range(values)
    im = ax.imshow(values, cmap="viridis", vmin=low, vmax=high, aspect="auto")
    ax.set_xticks(range(n_cols), [str(c) for c in table.columns], rotation=55, ha="right", fontsize=tick)
    ax.set_yticks(range(n_rows), [str(i) for i in table.index], fontsize=tick)
    ax.set_xlabel("partner", fontsize=10)
    ax.set_ylabel("member", fontsize=10)
    _annotate(ax, im, values, fontsize=min(tick - 1, 0.33 * cell * 72))
    bar = fig.colorbar(im, ax=ax, shrink=0.85)
    bar.set_label(f"{metric} (%)" if percent else metric, fontsize=10)
    ax.set_title(_wrap(title, width, points=10), fontsize=10)
    return fig


def colour_range(values: np.ndarray) -> tuple[float, float]:
    """The colour scale's ends: the smallest and largest finite value (widened to 1 unit when they are equal)."""
    finite = values[np.isfinite(values)]
    if not finite.size:
        return 0.0, 1.0
    low, high = float(finite.min()), float(finite.max())
    return (low - 0.5, high + 0.5) if high - low < 1e-9 else (low, high)


def _annotate(ax: Any, image: Any, values: np.ndarray, fontsize: float) -> None:
    """Each finite cell's value, white on the colour map's dark part, black on its light part; none below 5.5 pt."""
    if fontsize < 5.5:
        return
    for (i, j), v in np.ndenumerate(values):
        if np.isfinite(v):
            colour = "w" if image.norm(v) < 0.6 else "k"  # viridis turns light at about 60 %
            ax.text(j, i, f"{v:.0f}", ha="center", va="center", fontsize=fontsize, color=colour)


def crossplay_heatmap(table: pd.DataFrame, path: Path, title: str = "cross-play SUC", metric: str = "SUC") -> Path:
    """Save :func:`crossplay_figure` as a PNG."""
    return save_figure(crossplay_figure(table, title, metric), path)


def _wrap(title: str, width_in: float, points: float = 9.0) -> str:
    """The title broken into lines that fit ``width_in`` inches at ``points`` pt (about 0.55 em per character)."""
    chars = max(20, int(width_in * 72 / (0.55 * points)))
    return "\n".join(textwrap.wrap(title, chars)) or title


# ------------------------------------------------------------------ hypergraph
def hypergraph_figure(
    weights: dict[str, float],
    preference: dict[str, list[str]],
    eta: dict[str, float],
    rho: dict[str, float] | None = None,
    generation: int | None = None,
) -> Any:
    """Members on a circle coloured by eta, with an arrow from each member to every co-member of its preferred team.

    weights: team ("a|b|c") -> weight (drawn as light grey hyperedges); preference:
    member -> its preferred team. Arrows (networkx) stop at the node borders; a colour bar
    is the key for eta (preference centrality); members without eta are white. With
    ``rho`` each label also gives the member's share of the partner draws; with
    ``generation`` the title names it.
    """
    import networkx as nx

    plt = _pyplot()
    nodes = sorted(set(eta) | {m for team in weights for m in team.split("|")} | set(preference))
    size = 6.0 + 0.12 * len(nodes)
    fig, ax = plt.subplots(figsize=(size + 1.2, size), dpi=100, layout="constrained")
    pos = {
        n: (math.cos(2 * math.pi * i / len(nodes)), math.sin(2 * math.pi * i / len(nodes))) for i, n in enumerate(nodes)
    }
    for key in weights:  # every hyperedge of G'_t, as a light closed polygon
        members = sorted(set(key.split("|")))
        ring = [*members, members[0]]
        ax.plot([pos[m][0] for m in ring], [pos[m][1] for m in ring], color="0.88", lw=0.8, zorder=0)
    graph = nx.DiGraph()
    graph.add_nodes_from(nodes)
    graph.add_edges_from((n, m) for n, team in preference.items() for m in set(team) - {n})
    node_size = 900
    cmap = plt.get_cmap("plasma")
    colours = [cmap(eta[n]) if n in eta else (1.0, 1.0, 1.0, 1.0) for n in nodes]
    nx.draw_networkx_nodes(graph, pos, ax=ax, node_size=node_size, node_color=colours, edgecolors="k")
    nx.draw_networkx_edges(
        graph,
        pos,
        ax=ax,
        node_size=node_size,
        arrows=True,
        arrowstyle="-|>",
        arrowsize=14,
        width=1.2,
        edge_color="tab:blue",
        connectionstyle="arc3,rad=0.08",
    )
    for n in nodes:
        x, y = pos[n]
        label = f"{n}\neta {eta[n]:.2f}" if n in eta else f"{n}\n(no eta yet)"
        if rho is not None and n in rho:
            label += f"\nrho {rho[n]:.2f}"
        ax.text(1.28 * x, 1.28 * y, label, ha="center", va="center", fontsize=7)
    mappable = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0.0, 1.0))
    bar = fig.colorbar(mappable, ax=ax, shrink=0.7)
    bar.set_label("eta (preference centrality: in-degree / degree)", fontsize=8)
    ax.set_xlim(-1.6, 1.6)
    ax.set_ylim(-1.6, 1.6)
    ax.set_aspect("equal")
    ax.set_axis_off()
    when = f"generation {generation}: " if generation is not None else ""
    ax.set_title(f"{when}preference hypergraph: an arrow from each member to its preferred team's members", fontsize=9)
    return fig


def draw_hypergraph(
    weights: dict[str, float],
    preference: dict[str, list[str]],
    eta: dict[str, float],
    path: Path,
    rho: dict[str, float] | None = None,
    generation: int | None = None,
) -> Path:
    """Save :func:`hypergraph_figure` as a PNG."""
    return save_figure(hypergraph_figure(weights, preference, eta, rho, generation), path)
