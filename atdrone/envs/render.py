"""Pictures of the pursuit simulator: single frames, PNG/GIF files and recorded episodes.

Matplotlib is imported only inside the functions that draw (on its Agg canvas, no
pyplot), so importing :mod:`atdrone.envs` stays light. A frame shows one environment
of a :class:`BatchedPursuit`: the arena and its walls, box and disc obstacles,
pursuers (blue; zoo partners green when a team plays) and evaders (red) with heading
arrows, each pursuer's capture radius (solid ring) and perception radius (faint ring),
captured evaders greyed and crossed, the step counter and, optionally, the trails the
drones left.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from atdrone.config import TaskConfig
from atdrone.envs.core import DIST_SCALE, DONE_REASONS, ENTITY_FEATURES, RUNNING, BatchedPursuit, PursuitState
from atdrone.envs.single import Stepper
from atdrone.fileio import atomic_write

if TYPE_CHECKING:  # atdrone.policies and atdrone.teams build on atdrone.envs
    from atdrone.policies.base import Policy as DronePolicy
    from atdrone.policies.zoo import Zoo
    from atdrone.teams.match import Match

Policy = Callable[[np.ndarray, BatchedPursuit], np.ndarray]  # obs (B, n, obs_dim), core -> actions (B, n)

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


class FrameRenderer:
    """Draws frames of one environment of a core; reuse it to draw many frames fast.

    The figure and the static scene (arena, walls, obstacles) are built once; each
    :meth:`draw` replaces only the drones, rings, trails and labels.
    """

    def __init__(self, core: BatchedPursuit, env_index: int = 0, partner_slots: Sequence[int] = ()) -> None:
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
        header = 0.5  # inches of text above the arena
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
        self.title = self.figure.text(0.03, 1.0 - 0.15 / total, "", fontsize=10, weight="bold", va="center")
        self.status = self.figure.text(0.03, 1.0 - 0.36 / total, "", fontsize=8, va="center", family="monospace")
        self._dynamic: list[Any] = []

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
        self.title.set_text(title if title is not None else cfg.name)
        self.status.set_text(
            f"t = {t} / {cfg.task.task_horizon}    captured {int(captured.sum())}/{core.num_e}"
            f"    return {float(s.ep_return[k]):+.1f}"
        )
        self.canvas.draw()
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def close(self) -> None:
        self.figure.clear()


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


_TURNS = np.linspace(-1.0, 1.0, 17)  # candidate actions of chase_nearest's safety filter


def chase_nearest(obs: np.ndarray, core: BatchedPursuit, clearance: float = 0.35) -> np.ndarray:
    """The default demo policy: steer each pursuer at its nearest visible evader.

    Read from the observation alone (layout of :mod:`atdrone.envs.core`): the wanted
    turn is clip(bearing / 45 degrees, -1, 1) towards the nearest unmasked evader
    block, straight ahead when none is visible. A safety filter then picks, among 17
    turns in [-1, 1], the one that best turns the nose away from every obstacle, wall
    or teammate nearer than ``clearance`` metres (ties: closest to the wanted turn),
    so demo episodes do not end at the first wall. obs (B, P, obs_dim) -> actions (B, P),
    for every pursuer or any P of them.
    """
    B, P, _ = obs.shape  # P: the drones steered, every pursuer or some of them
    E = core.num_e
    blocks = obs.reshape(B, P, -1, ENTITY_FEATURES)
    mask, dist = blocks[..., 0] > 0.5, blocks[..., 1] * DIST_SCALE
    bearing = np.arctan2(blocks[..., 2], blocks[..., 3])

    ev_dist = np.where(mask[..., :E], dist[..., :E], np.inf)
    nearest = ev_dist.argmin(-1)[..., None]
    seen = np.isfinite(np.take_along_axis(ev_dist, nearest, -1)[..., 0])
    aim = np.take_along_axis(bearing[..., :E], nearest, -1)[..., 0]
    want = np.where(seen, np.clip(aim / (np.pi / 4), -1.0, 1.0), 0.0)

    # The obstacle block (slot E) and the teammate blocks: after turning by a, an entity at
    # bearing b sits at b - a * pi/4; a near one should end up abeam or behind (cos <= 0).
    near = mask[..., E:] & (dist[..., E:] < clearance)  # (B, P, M)
    after = bearing[..., E:, None] - _TURNS * (np.pi / 4)  # (B, P, M, K)
    unsafe = (near[..., None] * np.maximum(np.cos(after), 0.0)).sum(-2)  # (B, P, K)
    cost = unsafe * 10.0 + np.abs(_TURNS - want[..., None])
    return _TURNS[cost.argmin(-1)] if near.any() else want


def record_episode(
    task: TaskConfig | str,
    seed: int | None = 0,
    policy: Policy | DronePolicy | None = None,
    max_steps: int | None = None,
    frame_every: int = 1,
    trails: bool = True,
    title: str | None = None,
    partners: Zoo | Sequence[DronePolicy] | None = None,
) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Run one episode of ``BatchedPursuit(task, num_envs=1, seed)`` and draw it.

    ``policy``: a :class:`~atdrone.policies.Policy` or a function ``(obs, core) ->
    actions`` over the drones it steers; default :func:`chase_nearest`. Without
    ``partners`` it steers every pursuer (obs (1, num_p, obs_dim), actions (1, num_p)).
    With ``partners`` (a zoo or partner policies) a :class:`~atdrone.teams.match.Match` on
    the core gives it the task's num_ctrl learner slots (obs (1, num_ctrl, obs_dim),
    actions (1, num_ctrl)) and the partners drawn for the episode fill the others;
    they are drawn green. The episode runs until it ends (captured, collision,
    timeout) or for ``max_steps`` steps (outcome "running"). Every ``frame_every``-th
    step is drawn, plus the first and the last (the pre-reset final state).
    Returns the frames and a summary: task, seed, steps, outcome, return, captured,
    num_e, and with partners the team (learner_slots, partner_slots, partners).
    """
    if frame_every < 1:
        raise ValueError(f"frame_every must be >= 1, got {frame_every}")
    core = BatchedPursuit(task, num_envs=1, seed=seed)
    match: Match | None = None
    stepper: Stepper = core
    if partners is not None:
        from atdrone.teams.match import Match

        stepper = match = Match(core, partners, seed=seed)
    act = _actor(policy, core, match)
    obs = stepper.reset(seed=seed)
    name = title if title is not None else f"{core.cfg.name}  seed {seed}"
    team: dict[str, list[Any]] = {}
    if match is not None:
        team = {k: v[0].tolist() for k, v in match.team().items() if k != "partner_members"}
        if title is None:
            name += f"  partners: {', '.join(team['partners'])}"
    renderer = FrameRenderer(core, 0, partner_slots=team.get("partner_slots", ()))
    history = [core.state.pos[0].copy()]
    frames = [renderer.draw(title=name)]
    reason, step, final = RUNNING, 0, core.state
    limit = core.cfg.task.task_horizon if max_steps is None else max_steps
    try:
        while step < limit:
            obs, _, done, info = stepper.step(np.asarray(act(obs), dtype=np.float64).reshape(1, -1))
            step += 1
            if done[0]:
                assert core.final_state is not None
                final, reason = core.final_state, int(info["done_reason"][0])
            else:
                final = core.state
            history.append(final.pos[0].copy())
            if done[0] or step % frame_every == 0 or step == limit:
                trail = np.asarray(history) if trails else None
                frames.append(renderer.draw(final, title=name, trails=trail))
            if done[0]:
                break
    finally:
        renderer.close()
    summary: dict[str, Any] = {
        "task": core.cfg.name,
        "seed": seed,
        "steps": int(final.t[0]),
        "outcome": DONE_REASONS[reason],
        "return": float(final.ep_return[0]),
        "captured": int(final.captured[0].sum()),
        "num_e": core.num_e,
    }
    if team:
        summary["team"] = team
    return frames, summary


def _actor(
    policy: Policy | DronePolicy | None, core: BatchedPursuit, match: Match | None
) -> Callable[[np.ndarray], np.ndarray]:
    """``obs -> actions`` of the drones ``policy`` steers: every pursuer, or the match's learners."""
    from atdrone.policies.base import DroneBatch
    from atdrone.policies.base import Policy as PolicyProtocol

    if policy is None:
        return lambda obs: chase_nearest(obs, core)
    if isinstance(policy, PolicyProtocol):
        drones = policy
        drones.reset(np.ones(1, dtype=bool))
        if match is not None:
            learners = match
            return lambda obs: drones.act(learners.learner_batch())
        return lambda obs: drones.act(DroneBatch.all_slots(core, obs))
    steer = policy
    return lambda obs: steer(obs, core)
