"""The flight log's pictures: the arena with every drone's path (PNG) and a short animation (GIF)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

GIF_FRAMES = 60
ROLE_COLORS = {"learner": "#1f5fbf", "partner": "#2a9d3a", "evader": "#d62728", "backup": "#8c564b"}


def title(meta: Mapping[str, Any]) -> str:
    return f"{meta.get('name', 'flight')}: {meta.get('member', '?')} on {meta.get('task', '?')}"


def _figure(geometry: Mapping[str, Any], height_px: int, header: float) -> tuple[Any, Any, Any]:
    """An Agg figure with the arena, walls and obstacles drawn (render.py's look)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure
    from matplotlib.patches import Circle, Rectangle

    from atdrone.envs.render import FIGURE_DPI, FLOOR_COLOR, GRID_COLOR, OBSTACLE_COLOR, WALL_COLOR

    width, height, pad = float(geometry["width"]), float(geometry["height"]), 0.15
    scale = height_px / FIGURE_DPI / (height + 2 * pad)
    total = (height + 2 * pad) * scale + header
    figure = Figure(figsize=((width + 2 * pad) * scale, total), dpi=FIGURE_DPI)
    canvas = FigureCanvasAgg(figure)
    ax = figure.add_axes((0.0, 0.0, 1.0, 1.0 - header / total))
    ax.set_xlim(-pad, width + pad)
    ax.set_ylim(-pad, height + pad)
    ax.set_aspect("equal")
    ax.set_axis_off()
    ax.add_patch(Rectangle((0, 0), width, height, facecolor=FLOOR_COLOR, edgecolor="none", zorder=0))
    ax.add_patch(Rectangle((0, 0), width, height, facecolor="none", edgecolor=WALL_COLOR, linewidth=3, zorder=5))
    for cx, cy, hx, hy in geometry.get("boxes", []):
        ax.add_patch(Rectangle((cx - hx, cy - hy), 2 * hx, 2 * hy, facecolor=OBSTACLE_COLOR, zorder=2))
    for cx, cy, r in geometry.get("discs", []):
        ax.add_patch(Circle((cx, cy), r, facecolor=OBSTACLE_COLOR, zorder=2))
    ax.vlines(np.arange(0.5, width, 0.5), 0, height, color=GRID_COLOR, linewidth=0.6, zorder=0.5)
    ax.hlines(np.arange(0.5, height, 0.5), 0, width, color=GRID_COLOR, linewidth=0.6, zorder=0.5)
    return figure, canvas, ax


def _drone_colors(flight: pd.DataFrame) -> dict[str, str]:
    """A colour per drone: its role's hue, lightened for each further drone of the role."""
    from matplotlib.colors import to_rgb

    roles = flight.groupby("drone", sort=False)["role"].first()
    colors = {}
    for role, names in roles.groupby(roles, sort=False):
        base = np.array(to_rgb(ROLE_COLORS.get(str(role), "#555555")))
        for k, name in enumerate(names.index):
            mix = 0.45 * k / max(1, len(names) - 1) if len(names) > 1 else 0.0
            colors[str(name)] = "#{:02x}{:02x}{:02x}".format(*(255 * (base + (1 - base) * mix)).astype(int))
    return colors


def _paths(flight: pd.DataFrame, columns: Sequence[str]) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Drones, tick times (T,) and their ``columns`` values (T, D, len(columns)), NaN where absent."""
    grid = flight.groupby(["t", "drone"], sort=True)[list(columns)].first().unstack("drone")
    drones = [str(d) for d in grid[columns[0]].columns]
    values = np.stack([grid[c].to_numpy(np.float64) for c in columns], -1)
    return drones, grid.index.to_numpy(np.float64), values


def plot_trajectories(flight: pd.DataFrame, geometry: Mapping[str, Any], path: Path, title: str = "") -> Path:
    """The arena with every drone's path, its setpoints faint and the shield's events marked (PNG)."""
    from atdrone.envs.render import save_png

    figure, canvas, ax = _figure(geometry, 640, 0.4)
    figure.text(0.03, 0.985, title, fontsize=10, weight="bold", va="top")
    colors = _drone_colors(flight)
    if not flight.empty:
        drones, _, xy = _paths(flight, ["x", "y"])
        _, _, sp = _paths(flight, ["setpoint_x", "setpoint_y"])
        _, _, episode = _paths(flight, ["episode"])
        # break a path where its episode changes (virtual evaders jump to new spawns)
        jump = np.r_[False, (np.diff(episode[..., 0], axis=0) != 0).any(1)]
        xy[jump], sp[jump] = np.nan, np.nan
        for d, name in enumerate(drones):
            keep = np.isfinite(xy[:, d, 0])
            style = "--" if name.startswith("virtual") else "-"
            ax.plot(*xy[keep, d].T, style, color=colors[name], linewidth=1.4, zorder=3, label=name)
            ax.plot(*sp[np.isfinite(sp[:, d, 0]), d].T, color=colors[name], linewidth=0.8, alpha=0.25, zorder=2.5)
        last = flight.dropna(subset=["x", "y"]).groupby("drone", sort=False)[["x", "y"]].last()  # where each ended
        ax.scatter(last.x, last.y, s=36, c=[colors[str(n)] for n in last.index], edgecolors="white", zorder=6)
        for name, (x, y) in last.iterrows():
            ax.annotate(str(name), (x, y), xytext=(4, 4), textcoords="offset points", fontsize=7, zorder=7)
        events = flight[flight["events"].astype(str) != ""]
        fault = events["events"].str.contains("fault:")
        rules = events["events"].str.replace(r"(fault|pair|dropped|took_slot):[^,]*|backup_\w+", "", regex=True)
        shield_rows = events[rules.str.strip(",") != ""]
        if len(shield_rows):
            ax.scatter(shield_rows.x, shield_rows.y, marker="x", color="black", s=22, zorder=8, label="shield")
        if fault.any():
            ax.scatter(events.x[fault], events.y[fault], marker="^", color="#ff8c00", s=30, zorder=8, label="fault")
        ax.legend(loc="upper right", fontsize=6, framealpha=0.8)
    canvas.draw()
    frame = np.asarray(canvas.buffer_rgba())[..., :3].copy()
    figure.clear()
    return save_png(frame, path)


def animate(flight: pd.DataFrame, geometry: Mapping[str, Any], path: Path, frames: int = GIF_FRAMES) -> Path:
    """A short GIF of the flight: at most ``frames`` evenly spaced ticks, drones with 2 s trails."""
    from atdrone.envs.render import save_gif

    figure, canvas, ax = _figure(geometry, 320, 0.3)
    label = figure.text(0.03, 0.985, "", fontsize=8, family="monospace", va="top")
    images = []
    if flight.empty:
        canvas.draw()
        images.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
    else:
        colors = _drone_colors(flight)
        drones, times, xy = _paths(flight, ["x", "y"])
        _, _, info = _paths(flight, ["episode", "step"])
        picks = np.unique(np.linspace(0, len(times) - 1, min(frames, len(times))).astype(int))
        dots = ax.scatter(np.zeros(len(drones)), np.zeros(len(drones)), s=40, c=[colors[d] for d in drones], zorder=6)
        trails = [ax.plot([], [], color=colors[d], linewidth=1, alpha=0.5, zorder=4)[0] for d in drones]
        for k in picks:
            window = (times > times[k] - 2.0) & (times <= times[k])
            dots.set_offsets(np.nan_to_num(xy[k], nan=-10.0))  # unknown poses drawn off the arena
            for d, line in enumerate(trails):
                line.set_data(xy[window, d, 0], xy[window, d, 1])
            episode, step = np.nanmax(info[k], axis=0)
            label.set_text(f"t = {times[k]:6.1f} s   episode {int(episode)}   step {int(step)}")
            canvas.draw()
            images.append(np.asarray(canvas.buffer_rgba())[..., :3].copy())
    figure.clear()
    return save_gif(images, path, fps=10)
