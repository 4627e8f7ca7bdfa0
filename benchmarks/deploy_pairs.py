"""Why episodes on the fleet end as they do: per episode, how close pursuers came to evader drones, and which
pairs the shield's separation rule held.

Reads flight logs (directories with flight.parquet and episodes.parquet) and prints JSON:
per episode the outcome, the smallest horizontal pursuer-evader distance on the policy
legs, each captured evader drone's distance to its nearest pursuer when the capture was
judged (the tick before it began to land), and the ticks on which a drone was held by
``separation``, by the kind of pair (pursuer-pursuer, pursuer-evader, evader-evader). The
partner of a held drone is the nearest other airborne drone also held that tick (the rule
holds both of a pair).

Usage: python benchmarks/deploy_pairs.py LOG_DIR [LOG_DIR ...]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

PURSUERS = ("learner", "partner")


def capture_distances(tick: pd.DataFrame, grid: pd.DataFrame, roles: pd.Series) -> list[float]:
    """Per evader drone captured in an episode: its distance to the nearest pursuer on the tick before it
    began landing (the tick its capture was judged)."""
    out = []
    for drone in [d for d in grid["x"].columns if roles[d] not in PURSUERS]:
        rows = tick[tick["drone"] == drone].sort_values("t")
        landing = rows["t"][rows["state"] == "landing"]
        if landing.empty:
            continue
        before = grid.index[grid.index < landing.iloc[0]]
        if before.empty:
            continue
        t = before[-1]
        p = np.array([[grid["x"][d][t], grid["y"][d][t]] for d in grid["x"].columns if roles[d] in PURSUERS])
        e = np.array([grid["x"][drone][t], grid["y"][drone][t]])
        out.append(float(np.nanmin(np.hypot(*(p - e).T))))
    return out


def episode_pairs(flight: pd.DataFrame, episodes: pd.DataFrame) -> list[dict[str, Any]]:
    """One row per episode of one flight log (see the module docstring)."""
    legs = flight[(flight["step"] >= 0) & flight["state"].isin(("taking_off", "flying", "landing"))]
    rows = []
    for ep in episodes.itertuples():
        tick = legs[legs["episode"] == ep.episode]
        grid = tick.groupby(["t", "drone"])[["x", "y"]].first().unstack("drone")
        roles = tick.groupby("drone")["role"].first()
        held = tick.assign(h=tick["events"].astype(str).str.contains("separation")).pivot_table(
            index="t", columns="drone", values="h", aggfunc="any"
        )
        drones = list(grid["x"].columns)
        xy = np.stack([grid["x"][drones].to_numpy(float), grid["y"][drones].to_numpy(float)], -1)  # (T, D, 2)
        dist = np.linalg.norm(xy[:, :, None] - xy[:, None], axis=-1)
        pursuer = np.array([roles[d] in PURSUERS for d in drones])
        pe = dist[:, pursuer][:, :, ~pursuer]
        pe_min = float(np.nanmin(pe)) if np.isfinite(pe).any() else math.nan
        h = held.reindex(index=grid.index, columns=drones).fillna(False).to_numpy(bool)
        kinds = {"pursuer-pursuer": 0, "pursuer-evader": 0, "evader-evader": 0}
        for t, k in zip(*np.nonzero(h), strict=True):
            others = np.flatnonzero(h[t] & (np.arange(len(drones)) != k))
            if not len(others):
                continue
            j = others[np.nanargmin(dist[t, k, others])] if np.isfinite(dist[t, k, others]).any() else others[0]
            a, b = bool(pursuer[k]), bool(pursuer[j])
            kinds["pursuer-pursuer" if a and b else "evader-evader" if not (a or b) else "pursuer-evader"] += 1
        rows.append(
            {
                "episode": int(ep.episode),
                "outcome": str(ep.outcome),
                "steps": int(ep.steps),
                "captured": int(ep.captured),
                "min_pursuer_evader_m": pe_min,
                "held_drone_ticks": kinds,
                "policy_ticks": len(grid),
                "capture_distances_m": capture_distances(tick, grid, roles),
            }
        )
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", nargs="+", type=Path)
    args = parser.parse_args()
    out = []
    for log in args.logs:
        flight = pd.read_parquet(log / "flight.parquet")
        episodes = pd.read_parquet(log / "episodes.parquet")
        out.append({"log": str(log), "episodes": episode_pairs(flight, episodes)})
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
