"""Pictures of the pursuit simulator: single frames and PNG/GIF files.

Matplotlib is imported only inside the functions that draw (on its Agg canvas, no
pyplot), so importing :mod:`atdrone.envs` stays light. A frame shows one environment
of a :class:`BatchedPursuit`: the arena and its walls, box and disc obstacles,
pursuers (blue; zoo partners green when a team plays) and evaders (red) with heading
arrows, each pursuer's capture radius (solid ring) and perception radius (faint ring),
captured evaders greyed and crossed, collisions marked (an orange ring around each pursuer that hit a
teammate or an obstacle, a line between a colliding pair), a title (a long one on two lines, never under 7 pt),
the step counter and, optionally, the trails the drones left. Recording whole episodes (policies, teams) is
:func:`atdrone.teams.replay.record_episode`.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from atdrone.envs.core import BatchedPursuit, PursuitState
from atdrone.envs.rules import judge
from atdrone.fileio import atomic_write

PURSUER_COLOR = "#1f5fbf"
PARTNER_COLOR = "#2a9d3a"
EVADER_COLOR = "#d62728"
CAPTURED_COLOR = "#8c8c8c"
OBSTACLE_COLOR = "#5a5a5a"
WALL_COLOR = "#222222"
FLOOR_COLOR = "#fbfbf7"
ARROW_LENGTH = 0.22  # metres
DRONE_RADIUS = 0.07  # metres, the drawn body only (the simulator's drones are points)
FIGURE_DPI = 80
GRID_COLOR = "#e6e6e0"
COLLISION_COLOR = "#ff7f0e"


class FrameRenderer:
    """Draws frames of one environment of a core; reuse it to draw many frames fast.

    The figure and the static scene (arena, walls, obstacles) are built once; each
    :meth:`draw` replaces only the drones, rings, trails and labels.
    """

    def __init__(
        self, core: BatchedPursuit, env_index: int = 0, partner_slots: Sequence[int] = (), member: str | None = None
    ) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        from matplotlib.patches import Circle, Rectangle

        if not 0 <= env_index < core.num_envs:
            raise IndexError(f"env_index {env_index} out of range for {core.num_envs} environments")
        self.core = core
        self.env_index = env_index
        partners = {int(i) for i in partner_slots}
        self.pursuer_colors = [PARTNER_COLOR if i in partners else PURSUER_COLOR for i in range(core.num_p)]
        geo = core.geometry
        pad = 0.15
        w, h = geo.width + 2 * pad, geo.height + 2 * pad
        scale = 6.4 / h  # inches per metre: about 512 px tall at FIGURE_DPI
        header = 0.9  # inches above the arena: a title of up to two lines, the status line, the legend
        total = h * scale + header
        self.figure = Figure(figsize=(w * scale, total), dpi=FIGURE_DPI)
        self.canvas = FigureCanvasAgg(self.figure)
        ax = self.figure.add_axes((0.0, 0.0, 1.0, h * scale / total))
        ax.set_xlim(-pad, geo.width + pad)
        ax.set_ylim(-pad, geo.height + pad)
        ax.set_aspect("equal")
        ax.set_axis_off()
        floor = ax.add_patch(
            Rectangle((0, 0), geo.width, geo.height, facecolor=FLOOR_COLOR, edgecolor="none", zorder=0)
        )
        ax.add_patch(
            Rectangle((0, 0), geo.width, geo.height, facecolor="none", edgecolor=WALL_COLOR, linewidth=3, zorder=5)
        )
        for (cx, cy), (hx, hy) in zip(geo.box_center, geo.box_half, strict=True):
            ax.add_patch(Rectangle((cx - hx, cy - hy), 2 * hx, 2 * hy, facecolor=OBSTACLE_COLOR, zorder=2))
        for (cx, cy), r in zip(geo.disc_center, geo.disc_radius, strict=True):
            ax.add_patch(Circle((cx, cy), r, facecolor=OBSTACLE_COLOR, zorder=2))
        # a faint 0.5 m grid to read distances by
        ax.vlines(np.arange(0.5, geo.width, 0.5), 0, geo.height, color=GRID_COLOR, linewidth=0.6, zorder=0.5)
        ax.hlines(np.arange(0.5, geo.height, 0.5), 0, geo.width, color=GRID_COLOR, linewidth=0.6, zorder=0.5)
        self.floor = floor  # dynamic artists are clipped to the arena
        self.ax = ax
        self.legend = self._add_legend(h * scale / total, bool(partners), member)
        self.title = self.figure.text(
            0.03, 1.0 - 0.05 / total, "", fontsize=10, weight="bold", va="top", linespacing=1.1
        )
        self.status = self.figure.text(0.03, 1.0 - 0.3 / total, "", fontsize=8, va="top", family="monospace")
        self._title_source: str | None = None
        self._dynamic: list[Any] = []

    def _add_legend(self, arena_top: float, team: bool, member: str | None) -> Any:
        """One row just above the arena: whose drones are which colour (the member's, the partners'), evaders."""
        from matplotlib.lines import Line2D

        def dot(color: str, label: str, marker: str = "o") -> Line2D:
            return Line2D([], [], linestyle="none", marker=marker, markersize=6, color=color, label=label)

        def ring(color: str, label: str) -> Line2D:
            return Line2D(
                [],
                [],
                linestyle="none",
                marker="o",
                markersize=8,
                markerfacecolor="none",
                markeredgewidth=2,
                color=color,
                label=label,
            )

        flown = member or "pursuers"
        handles = [dot(PURSUER_COLOR, f"{flown} (learners)" if team else flown)]
        if team:
            handles.append(dot(PARTNER_COLOR, "zoo partners"))
        handles += [dot(EVADER_COLOR, "evader"), dot("black", "caught", "x"), ring(COLLISION_COLOR, "collision")]
        return self.figure.legend(
            handles=handles,
            loc="lower left",
            bbox_to_anchor=(0.01, arena_top),
            ncol=len(handles),
            fontsize=7.5,
            frameon=False,
            handletextpad=0.2,
            columnspacing=0.9,
            borderaxespad=0.1,
        )

    def _set_title(self, title: str) -> None:
        """Show ``title`` on one line at 8.5-10 pt if it fits the frame's width, else on two lines at 7-10 pt;
        the status line goes just below it."""
        if title == self._title_source:
            return
        self._title_source = title
        renderer = self.canvas.get_renderer()
        width = self.figure.bbox.width * 0.97
        layouts = [(title, size) for size in (10.0, 9.5, 9.0, 8.5)]
        layouts += [(two_lines(title), size) for size in (10.0, 9.5, 9.0, 8.5, 8.0, 7.5, 7.0)]
        for text, size in layouts:
            self.title.set_text(text)
            self.title.set_fontsize(size)
            if self.title.get_window_extent(renderer=renderer).x1 <= width:
                break
        below = self.title.get_window_extent(renderer=renderer).y0 - 0.06 * self.figure.dpi
        self.status.set_y(below / self.figure.bbox.height)

    def draw(
        self, state: PursuitState | None = None, title: str | None = None, trails: np.ndarray | None = None
    ) -> np.ndarray:
        """The (H, W, 3) uint8 RGB image of ``state`` (default: the core's current state).

        ``state`` is a batch like ``core.state``; env ``env_index`` of it is drawn.
        ``trails``: (T, N, 2) past positions of every drone of that environment.
        """
        from matplotlib.colors import to_rgba
        from matplotlib.patches import Circle

        core, ax, k = self.core, self.ax, self.env_index
        s = core.state if state is None else state
        cfg = core.cfg
        P = core.num_p
        pos = np.asarray(s.pos[k], dtype=np.float64)
        heading = np.asarray(s.heading[k], dtype=np.float64)
        captured = np.asarray(s.captured[k], dtype=bool)
        for artist in self._dynamic:
            artist.remove()
        dyn: list[Any] = []

        if trails is not None and len(trails) > 1:
            for n in range(pos.shape[0]):
                color = self.pursuer_colors[n] if n < P else (CAPTURED_COLOR if captured[n - P] else EVADER_COLOR)
                (line,) = ax.plot(trails[:, n, 0], trails[:, n, 1], color=color, alpha=0.35, linewidth=1, zorder=1)
                dyn.append(line)

        for i in range(P):
            xy, color = pos[i], self.pursuer_colors[i]
            perception = Circle(
                xy,
                cfg.players.reception_range,
                facecolor=to_rgba(color, 0.03),
                edgecolor=to_rgba(color, 0.35),
                linewidth=0.8,
                linestyle=(0, (2, 3)),
                zorder=1,
            )
            dyn.append(ax.add_patch(perception))
            perception.set_clip_path(self.floor)
            dyn.append(
                ax.add_patch(
                    Circle(
                        xy,
                        cfg.task.capture_range,
                        facecolor="none",
                        edgecolor=color,
                        linewidth=1.0,
                        alpha=0.8,
                        zorder=3,
                    )
                )
            )
            dyn.append(ax.add_patch(Circle(xy, DRONE_RADIUS, facecolor=color, edgecolor="white", zorder=6)))
            label = ax.text(xy[0], xy[1], str(i), color="white", fontsize=7, weight="bold", ha="center", va="center")
            dyn.append(label)
            label.set_zorder(7)

        for j in range(core.num_e):
            xy = pos[P + j]
            if captured[j]:
                dyn.append(ax.add_patch(Circle(xy, DRONE_RADIUS, facecolor=CAPTURED_COLOR, alpha=0.7, zorder=4)))
                # the cross stays visible above the pursuer that made the capture
                (cross,) = ax.plot(*xy, marker="x", color="black", markersize=7, markeredgewidth=1.5, zorder=9)
                dyn.append(cross)
            else:
                dyn.append(ax.add_patch(Circle(xy, DRONE_RADIUS, facecolor=EVADER_COLOR, edgecolor="white", zorder=6)))

        dyn += self._collisions(pos, captured)

        live = np.r_[np.ones(P, dtype=bool), ~captured]
        u, v = np.cos(heading) * ARROW_LENGTH, np.sin(heading) * ARROW_LENGTH
        colors = self.pursuer_colors + [EVADER_COLOR] * core.num_e
        dyn.append(
            ax.quiver(
                pos[live, 0],
                pos[live, 1],
                u[live],
                v[live],
                color=[c for c, keep in zip(colors, live, strict=True) if keep],
                angles="xy",
                scale_units="xy",
                scale=1.0,
                width=0.008,
                headwidth=3.5,
                headlength=4,
                zorder=5.5,  # under the bodies: the arrow sticks out of the disc
            )
        )
        self._dynamic = dyn

        t = int(s.t[k])
        self._set_title(title if title is not None else cfg.name)
        self.status.set_text(
            f"step {t} / {cfg.task.task_horizon} ({t / cfg.task.fps:.1f} s)    caught {int(captured.sum())}/"
            f"{core.num_e}    return {float(s.ep_return[k]):+.1f}    grid 0.5 m"
        )
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def _collisions(self, pos: np.ndarray, captured: np.ndarray) -> list[Any]:
        """Artists marking the collisions of the drawn positions, judged by the simulator's own rule."""
        from matplotlib.patches import Circle

        core, ax = self.core, self.ax
        found = judge(pos[None], captured[None], core.cfg, core.geometry)
        artists: list[Any] = []
        for i, j in core.pairs[found.hit_pairs[0]]:
            (line,) = ax.plot(*pos[[i, j]].T, color=COLLISION_COLOR, linewidth=2.5, zorder=5.7)
            artists.append(line)
        for i in np.flatnonzero(found.collided[0]):
            ring = Circle(
                pos[i], 1.8 * DRONE_RADIUS, facecolor="none", edgecolor=COLLISION_COLOR, linewidth=3, zorder=8
            )
            artists.append(ax.add_patch(ring))
        return artists

    def close(self) -> None:
        self.figure.clear()


def two_lines(text: str) -> str:
    """``text`` broken at the space that best balances two lines (unchanged without a space)."""
    words = text.split(" ")
    if len(words) < 2:
        return text
    cut = min(range(1, len(words)), key=lambda i: abs(len(" ".join(words[:i])) - len(" ".join(words[i:]))))
    return " ".join(words[:cut]) + "\n" + " ".join(words[cut:])


def render_frame(
    core: BatchedPursuit, env_index: int = 0, state: PursuitState | None = None, title: str | None = None
) -> np.ndarray:
    """One (H, W, 3) uint8 RGB image of environment ``env_index`` (current state by default)."""
    renderer = FrameRenderer(core, env_index)
    try:
        return renderer.draw(state, title)
    finally:
        renderer.close()


def save_png(frame: np.ndarray, path: str | os.PathLike[str]) -> Path:
    """Write one RGB frame as a PNG, atomically."""
    from PIL import Image

    image = Image.fromarray(np.asarray(frame, dtype=np.uint8))
    return atomic_write(path, lambda f: image.save(f, format="PNG"))


def save_gif(frames: Sequence[np.ndarray], path: str | os.PathLike[str], fps: float = 10) -> Path:
    """Write RGB frames as a looping GIF at ``fps``, atomically (one shared palette)."""
    from PIL import Image

    if len(frames) == 0:
        raise ValueError("save_gif needs at least one frame")
    images = [Image.fromarray(np.asarray(f, dtype=np.uint8)) for f in frames]
    # one palette for every frame, drawn from a few frames spread over the episode
    samples = [np.asarray(frames[i], dtype=np.uint8) for i in np.linspace(0, len(frames) - 1, 4).astype(int)]
    palette = Image.fromarray(np.concatenate(samples, 0)).quantize(colors=96, dither=Image.Dither.NONE)
    first, *rest = (im.quantize(palette=palette, dither=Image.Dither.NONE) for im in images)
    duration = max(20, round(1000 / fps))
    return atomic_write(
        path,
        lambda f: first.save(
            f, format="GIF", save_all=True, append_images=rest, duration=duration, loop=0, optimize=True
        ),
    )
