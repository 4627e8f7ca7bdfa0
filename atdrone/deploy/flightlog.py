"""The flight log: one row per tick and drone, one per episode, and what is made of them.

:class:`FlightLog` collects rows while the loop flies; :meth:`FlightLog.write` puts a log
directory together, every file written atomically (a temp name, then a rename):

- ``flight.parquet``: per tick and drone: ``t`` (clock seconds since the flight started),
  ``episode``, ``step`` (-1 while the high-level commander flies), ``drone``, ``role``,
  ``x, y, z, yaw`` (measured, arena frame; NaN unknown), ``setpoint_x, setpoint_y,
  setpoint_z``, ``state`` (:data:`FLIGHT_STATES`), ``events`` (comma-joined shield rules,
  ``fault:KIND`` notes, a ``pair:DRONE`` note per drone the separation rule held it
  with, and the team's notes: ``dropped:RULE`` (a partner drone dropped alone),
  ``backup_takeoff``, ``took_slot:SLOT`` and ``backup_gave_up``; "" for none), ``battery``
  (V) and ``latency_STAGE`` (seconds; NaN on ticks without that stage).
- ``episodes.parquet``: ``episode, outcome, steps, captured, reward, virtual_evaders``.
- ``meta.json``: the config summary given to the log, the tick overruns, the arena
  geometry (walls and obstacles) and the flight's ``team_changes`` (each partner drone
  dropped alone and the backup that took its slot), so the directory alone is enough for
  :func:`summarize`.
- ``summary.json``: :func:`summarize` of the directory (non-finite numbers as null).
- ``trajectories.png``: the arena, each drone's path, setpoints faint, shield events marked, and
  ``flight.gif``: a short animation (:mod:`atdrone.deploy.flightplot`).

:func:`log_to_mlflow` records the directory as an MLflow run tagged ``kind=deploy``.
"""

from __future__ import annotations

import json
import math
import re
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from atdrone.deploy.flightplot import GIF_FRAMES as GIF_FRAMES  # re-exported: the animation's frame cap
from atdrone.deploy.flightplot import animate, plot_trajectories, title
from atdrone.fileio import atomic_write, atomic_write_text

FLIGHT_STATES = ("idle", "taking_off", "flying", "landing", "landed", "stopped", "lost", "virtual")
AIRBORNE = ("taking_off", "flying", "landing")
OUTCOMES = ("captured", "collision", "timeout", "shield", "aborted")
LATENCY_STAGES = ("mocap_age", "observe", "policy", "shield", "send", "tick")  # the usual order; others follow
PERCENTILES = (50, 95, 99)
PAIR = "pair:"  # an events note: the separation rule held this drone together with the named one
TEAM_NOTES = ("dropped:", "took_slot:", "backup_")  # a partner dropped alone, a backup's takeoff, its slot taken
NOTES = ("fault:", PAIR, *TEAM_NOTES)  # events that are notes, not shield rules
EXPERIMENT = "atdrone-deploy"
FILES = ("flight.parquet", "episodes.parquet", "meta.json", "summary.json", "trajectories.png", "flight.gif")

_COLUMNS = (
    "t",
    "episode",
    "step",
    "drone",
    "role",
    "x",
    "y",
    "z",
    "yaw",
    "setpoint_x",
    "setpoint_y",
    "setpoint_z",
    "state",
    "events",
    "battery",
)
_EPISODE_COLUMNS = ("episode", "outcome", "steps", "captured", "reward", "virtual_evaders")


def _geometry(meta: Mapping[str, Any]) -> dict[str, Any]:
    """The arena and obstacles to draw: ``meta["geometry"]``, else the task's, else the bare arena."""
    if "geometry" in meta:
        return dict(meta["geometry"])
    width, height = (float(v) for v in meta.get("arena", (math.nan, math.nan)))
    geo = {"width": width, "height": height, "boxes": [], "discs": []}
    try:
        from atdrone.config import load_task
        from atdrone.envs.geometry import Geometry

        g = Geometry.from_config(load_task(str(meta["task"])))
    except (KeyError, ValueError, OSError):  # no task, or a task file no longer there: walls only
        return geo
    if math.isnan(width):
        geo.update(width=g.width, height=g.height)
    geo["boxes"] = np.c_[g.box_center, g.box_half].tolist()  # cx, cy, half width, half height
    geo["discs"] = np.c_[g.disc_center, g.disc_radius].tolist()  # cx, cy, radius
    return geo


def _jsonable(value: Any) -> Any:
    """Plain JSON data: numpy scalars and arrays unwrapped, non-finite floats as None."""
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, str | int | float | bool) or value is None:
        return value
    return str(value)


def _dumps(data: Any) -> str:
    return json.dumps(_jsonable(data), indent=2, allow_nan=False) + "\n"


class FlightLog:
    """Rows of one flight, collected from the loop's thread (see the module docstring).

    meta: the config summary: ``name, task, member, backend, evaders, dt, arena [w, h],
    drones {name: role}`` and anything else worth keeping; obstacles come from the task
    (or pass ``geometry`` as in meta.json).
    """

    def __init__(self, meta: Mapping[str, Any]) -> None:
        self.meta = dict(meta)
        self.geometry = _geometry(self.meta)
        self.overruns = 0
        self._rows: list[tuple[Any, ...]] = []
        self._latency: list[Mapping[str, float]] = []
        self._episodes: list[tuple[Any, ...]] = []
        self._lock = threading.Lock()

    def tick(
        self,
        t: float,
        episode: int,
        step: int,
        drone: str,
        role: str,
        pos: np.ndarray,
        yaw: float,
        setpoint: np.ndarray,
        state: str,
        events: Sequence[str],
        battery: float,
        latency: Mapping[str, float],
    ) -> None:
        """One row: drone ``drone`` at tick time ``t``; ``latency`` maps stage -> seconds."""
        if state not in FLIGHT_STATES:
            raise ValueError(f"unknown flight state {state!r} (known: {', '.join(FLIGHT_STATES)})")
        x, y, z = (float(v) for v in np.asarray(pos, dtype=np.float64).reshape(3))
        sx, sy, sz = (float(v) for v in np.asarray(setpoint, dtype=np.float64).reshape(3))
        row = (float(t), int(episode), int(step), drone, role, x, y, z, float(yaw), sx, sy, sz, state)
        with self._lock:
            self._rows.append((*row, ",".join(events), float(battery)))
            self._latency.append(dict(latency))

    def episode(
        self, episode: int, outcome: str, steps: int, captured: int, reward: float, virtual_evaders: bool
    ) -> None:
        """One finished episode; ``outcome`` one of :data:`OUTCOMES`."""
        if outcome not in OUTCOMES:
            raise ValueError(f"unknown episode outcome {outcome!r} (known: {', '.join(OUTCOMES)})")
        with self._lock:
            self._episodes.append((int(episode), outcome, int(steps), int(captured), float(reward), virtual_evaders))

    def overrun(self, count: int = 1) -> None:
        """Count late ticks (or set :attr:`overruns` from the loop's ticker)."""
        with self._lock:
            self.overruns += count

    def frame(self) -> pd.DataFrame:
        """The tick rows so far (see the module docstring for the columns)."""
        with self._lock:
            rows, latency = list(self._rows), list(self._latency)
        frame = pd.DataFrame(rows, columns=list(_COLUMNS))
        frame = frame.astype({"episode": np.int64, "step": np.int64})
        lat = pd.DataFrame(latency, index=frame.index) if latency else pd.DataFrame(index=frame.index)
        stages = [s for s in LATENCY_STAGES if s in lat] + sorted(s for s in lat if s not in LATENCY_STAGES)
        lat = lat[stages].astype(np.float64).add_prefix("latency_")
        return pd.concat([frame, lat], axis=1)

    def episodes(self) -> pd.DataFrame:
        """The finished episodes so far."""
        with self._lock:
            rows = list(self._episodes)
        frame = pd.DataFrame(rows, columns=list(_EPISODE_COLUMNS))
        return frame.astype({"episode": np.int64, "steps": np.int64, "captured": np.int64, "reward": np.float64})

    def write_rows(self, directory: Path) -> Path:
        """Write the rows so far (flight.parquet, episodes.parquet, meta.json, summary.json), each atomically:
        called after every episode, so a flight that dies leaves every finished episode on disk."""
        directory = Path(directory)
        directory.mkdir(parents=True, exist_ok=True)
        flight, episodes = self.frame(), self.episodes()
        atomic_write(directory / "flight.parquet", lambda f: flight.to_parquet(f, index=False))
        atomic_write(directory / "episodes.parquet", lambda f: episodes.to_parquet(f, index=False))
        meta = {**self.meta, "overruns": self.overruns, "geometry": self.geometry}
        atomic_write_text(directory / "meta.json", _dumps(meta))
        atomic_write_text(directory / "summary.json", _dumps(summarize(directory)))
        return directory

    def write(self, directory: Path) -> Path:
        """Write the log directory (every file atomically, the plots too); return it."""
        directory = self.write_rows(directory)
        flight = self.frame()
        meta = {**self.meta, "overruns": self.overruns, "geometry": self.geometry}
        plot_trajectories(flight, self.geometry, directory / "trajectories.png", title=title(meta))
        animate(flight, self.geometry, directory / "flight.gif")
        return directory


# ------------------------------------------------------------------ the summary
def _read(directory: Path) -> tuple[pd.DataFrame, pd.DataFrame, dict[str, Any]]:
    directory = Path(directory)
    meta = json.loads((directory / "meta.json").read_text())
    return pd.read_parquet(directory / "flight.parquet"), pd.read_parquet(directory / "episodes.parquet"), meta


def _physical(flight: pd.DataFrame, meta: Mapping[str, Any]) -> pd.DataFrame:
    """Rows of the real (or simulated-real) drones: those of meta's drones, else not virtual."""
    drones = meta.get("drones")
    return flight[flight["drone"].isin(list(drones))] if drones else flight[flight["state"] != "virtual"]


def episode_metrics(episodes: pd.DataFrame) -> dict[str, float]:
    """SUC, COL, AST, REW of the evaluation protocol (:func:`atdrone.teams.evaluation.metrics`), AST_std."""
    if episodes.empty:
        return dict.fromkeys(("SUC", "COL", "AST", "REW", "AST_std"), math.nan)
    from atdrone.teams.evaluation import metrics

    records = pd.DataFrame(
        {
            "success": episodes["outcome"] == "captured",
            "collided": episodes["outcome"] == "collision",
            "length": episodes["steps"],
            "return": episodes["reward"],
        }
    )
    out = metrics(records)
    ok = records["length"][records["success"]]
    out["AST_std"] = float(ok.std(ddof=1)) if len(ok) > 1 else math.nan
    return out


def separation(flight: pd.DataFrame) -> dict[str, Any]:
    """The smallest 3-D distance between two drones airborne at the same tick, where and between whom."""
    air = flight[flight["state"].isin(AIRBORNE)]
    none = {"min_separation": math.nan, "min_separation_t": math.nan, "min_separation_pair": []}
    if air["drone"].nunique() < 2:
        return none
    grid = air.groupby(["t", "drone"])[["x", "y", "z"]].first().unstack("drone")
    drones = list(grid["x"].columns)
    pos = np.stack([grid[c].to_numpy(np.float64) for c in ("x", "y", "z")], -1)  # (T, D, 3)
    dist = np.linalg.norm(pos[:, :, None] - pos[:, None], axis=-1)
    dist[:, np.arange(len(drones)), np.arange(len(drones))] = np.inf
    dist = np.where(np.isfinite(dist), dist, np.inf)
    k = int(np.argmin(dist))
    ti, i, j = np.unravel_index(k, dist.shape)
    if not np.isfinite(dist[ti, i, j]):
        return none
    pair = sorted([drones[i], drones[j]])
    return {
        "min_separation": float(dist[ti, i, j]),
        "min_separation_t": float(grid.index[ti]),
        "min_separation_pair": pair,
    }


HOLDS = ("separation", "policy_late", "nan_setpoint")  # shield rules that hold a drone in place


def ground_speed(flight: pd.DataFrame) -> float:
    """The median horizontal speed (m/s) of the pursuer drones between consecutive ticks of the policy legs
    while they track (rows with step >= 0, airborne, measured on both ticks, held on neither: a hold is the
    shield's, not the policy's; the trained speed is 0.30 m/s)."""
    legs = flight[(flight["step"] >= 0) & flight["role"].isin(("learner", "partner")) & flight["state"].isin(AIRBORNE)]
    speeds = []
    for _, rows in legs.sort_values("t").groupby(["drone", "episode"]):
        dt = np.diff(rows["t"].to_numpy(np.float64))
        dxy = np.hypot(np.diff(rows["x"].to_numpy(np.float64)), np.diff(rows["y"].to_numpy(np.float64)))
        held = rows["events"].astype(str).str.contains("|".join(HOLDS)).to_numpy()
        ok = (dt > 0) & np.isfinite(dxy) & ~held[1:] & ~held[:-1]
        speeds.append(dxy[ok] / dt[ok])
    values = np.concatenate(speeds) if speeds else np.zeros(0)
    return float(np.median(values)) if len(values) else math.nan


def latency_percentiles(flight: pd.DataFrame) -> dict[str, dict[str, float]]:
    """p50/p95/p99/max and count of each latency stage over ticks (one value per tick, finite ones)."""
    columns = [c for c in flight.columns if c.startswith("latency_")]
    per_tick = flight.groupby("t")[columns].first()
    out = {}
    for column in columns:
        values = per_tick[column].to_numpy(np.float64)
        values = values[np.isfinite(values)]
        if len(values):
            stats = {f"p{q}": float(v) for q, v in zip(PERCENTILES, np.percentile(values, PERCENTILES), strict=True)}
            out[column.removeprefix("latency_")] = {**stats, "max": float(values.max()), "n": len(values)}
    return out


def summarize(directory: Path) -> dict[str, Any]:
    """What a log directory says, from its files alone (see :func:`format_summary`).

    ticks: distinct tick times; SUC/COL/AST/REW per the evaluation protocol (SUC: % of
    episodes captured, COL: % ending in a collision, AST: mean steps of the captured
    ones, AST_std their sample std); interventions: rows (tick x drone) on which each
    shield rule acted; faults: injected faults by kind; latency: per stage over ticks;
    min_separation: the smallest distance between airborne physical drones;
    battery_min: per physical drone (V); team_changes: each partner drone dropped alone (its slot, why, when)
    and the backup that took its slot (when, its memory reset) or why none did.
    """
    flight, episodes, meta = _read(directory)
    physical = _physical(flight, meta)
    events = flight["events"].astype(str).str.split(",").explode()
    events = events[events != ""]
    faults = events[events.str.startswith("fault:")]
    rules = events[~events.str.startswith(NOTES)]
    t = flight["t"].to_numpy(np.float64)
    battery = physical.groupby("drone", sort=True)["battery"].min()
    summary: dict[str, Any] = {
        **{k: meta[k] for k in ("name", "task", "member", "backend", "evaders") if k in meta},
        "ticks": int(flight["t"].nunique()),
        "flight_time": float(t.max() - t.min()) if len(t) else 0.0,
        "episodes": len(episodes),
        "outcomes": {str(k): int(v) for k, v in episodes["outcome"].value_counts().sort_index().items()},
        **episode_metrics(episodes),
        "interventions": {str(k): int(v) for k, v in rules.value_counts().sort_index().items()},
        "faults": {str(k).removeprefix("fault:"): int(v) for k, v in faults.value_counts().sort_index().items()},
        "latency": latency_percentiles(flight),
        "overruns": int(meta.get("overruns", 0)),
        **separation(_physical(flight, meta)),
        "ground_speed_median": ground_speed(flight),
        "ended_early": str(meta.get("ended_early", "")),
        "endings": {str(k): str(v) for k, v in meta.get("endings", {}).items()},
        "episodes_flown": int(meta.get("episodes_flown", len(episodes))),
        "mocap_callback_errors": int(meta.get("mocap_callback_errors", 0)),
        "battery_min": {str(k): float(v) for k, v in battery.items()},
        "team_changes": list(meta.get("team_changes", [])),
    }
    summary["interventions_total"] = int(sum(summary["interventions"].values()))
    return summary


def _number(value: Any, fmt: str = ".1f", unit: str = "") -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    return f"{value:{fmt}}{unit}"


def format_summary(summary: Mapping[str, Any]) -> str:
    """The summary as text (what ``atdrone deploy report LOG`` prints)."""
    who = f"member {summary.get('member', '?')} on {summary.get('task', '?')} ({summary.get('backend', '?')} backend)"
    outcomes = ", ".join(f"{k} {v}" for k, v in summary.get("outcomes", {}).items()) or "none"
    lines = [
        f"flight {summary.get('name', '')}: {who}",
        f"  {summary['episodes']} episode(s), {summary['ticks']} ticks over {_number(summary['flight_time'])} s; "
        f"outcomes: {outcomes}",
        f"  SUC {_number(summary['SUC'], unit=' %')}  COL {_number(summary['COL'], unit=' %')}  "
        f"AST {_number(summary['AST'], unit=' steps')}  REW {_number(summary['REW'], '.2f')}",
        "  shield interventions: "
        + (", ".join(f"{k} {v}" for k, v in summary["interventions"].items()) or "none")
        + "; faults injected: "
        + (", ".join(f"{k} {v}" for k, v in summary.get("faults", {}).items()) or "none"),
        f"  tick overruns: {summary['overruns']}; min separation "
        + (
            f"{_number(summary['min_separation'], '.3f', ' m')} ({' - '.join(summary['min_separation_pair'])} "
            f"at t = {_number(summary['min_separation_t'], '.1f')} s)"
            if summary.get("min_separation_pair")
            else "- (fewer than two drones airborne)"
        ),
        f"  pursuers' median ground speed in policy legs: {_number(summary.get('ground_speed_median'), '.3f', ' m/s')}"
        + (f"; ENDED EARLY: {summary['ended_early']}" if summary.get("ended_early") else ""),
        "  drones: " + (", ".join(f"{k} {v}" for k, v in summary.get("endings", {}).items()) or "-"),
        "  battery min: "
        + (", ".join(f"{k} {_number(v, '.2f', ' V')}" for k, v in summary["battery_min"].items()) or "-"),
    ]
    lines += [f"  team change: {team_change(c)}" for c in summary.get("team_changes", [])]
    latency = summary.get("latency", {})
    if latency:
        lines.append(f"  {'latency (ms)':<14}" + "".join(f"{f'p{q}':>9}" for q in PERCENTILES) + f"{'max':>9}")
        for stage, s in latency.items():
            cells = "".join(f"{_number(s[f'p{q}'] * 1000, '.2f'):>9}" for q in PERCENTILES)
            lines.append(f"  {stage:<14}{cells}{_number(s['max'] * 1000, '.2f'):>9}")
    return "\n".join(lines)


# ------------------------------------------------------------------ MLflow
def _in(episode: int) -> str:
    return f"in episode {int(episode) + 1}" if int(episode) >= 0 else "before the first episode"


def team_change(change: Mapping[str, Any]) -> str:
    """One team change as text: the partner drone dropped, and what came of its slot."""
    text = f"{change['drone']} (slot {change['slot']}) dropped at t = {_number(change['t'])} s {_in(change['episode'])}"
    text += f": {change['why']}"
    backup = change.get("backup")
    if not backup:
        return text + "; no backup, the slot stayed empty"
    if change.get("took_slot_t") is not None:
        reset = ", its memory reset" if change.get("memory_reset") else ""
        took = f"{_number(change['took_slot_t'])} s {_in(change['took_slot_episode'])}"
        return text + f"; backup {backup} took the slot at t = {took}{reset}"
    return text + f"; backup {backup} did not take the slot ({change.get('backup_end') or 'the flight ended first'})"


def _metric_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_\-./ ]", "_", text)


def log_to_mlflow(directory: Path, tracking_uri: str | None, run_name: str, experiment: str = EXPERIMENT) -> str:
    """Record a flight log as an MLflow run (params, metrics, the files, tag ``kind=deploy``); its id."""
    from atdrone.tracking import Tracker

    directory = Path(directory)
    summary = summarize(directory)
    meta = json.loads((directory / "meta.json").read_text())
    params = {k: v for k, v in meta.items() if k not in ("geometry", "overruns")}
    metrics: dict[str, float] = {
        f"deploy/{k}": summary[k]
        for k in ("SUC", "COL", "AST", "REW", "episodes", "ticks", "overruns", "min_separation", "flight_time")
    }
    metrics["deploy/interventions"] = summary["interventions_total"]
    metrics.update({f"deploy/interventions/{k}": v for k, v in summary["interventions"].items()})
    for stage, stats in summary["latency"].items():
        metrics.update({f"deploy/latency/{stage}_p{q}": stats[f"p{q}"] for q in PERCENTILES})
    metrics.update({f"deploy/battery_min/{k}": v for k, v in summary["battery_min"].items()})
    tracker = Tracker(tracking_uri)
    tags = {"kind": "deploy", "atdrone.task": str(meta.get("task", "")), "atdrone.member": str(meta.get("member", ""))}
    with tracker.run(experiment, run_name, tags=tags) as run_id:
        tracker.log_params(params)
        tracker.log_metrics({_metric_name(k): v for k, v in metrics.items()}, step=0)
        episodes = pd.read_parquet(directory / "episodes.parquet")
        for row in episodes.itertuples():  # per-episode series, one step per episode
            tracker.log_metrics({"deploy/episode_steps": row.steps, "deploy/episode_reward": row.reward}, row.episode)
        for path in sorted(p for p in directory.iterdir() if p.is_file() and not p.name.startswith(".")):
            tracker.log_artifact(path)
    return run_id
