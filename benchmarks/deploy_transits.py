"""How often the transit planner finds no plan from where episodes on the fleet ended.

For every episode in the given flight logs, the drones' positions on its last policy tick
are the starts; ``--draws`` spawn draws of the task (drones clear of each other, targets
inside the fence and off the obstacles, as the loop makes them) are the targets. Prints
how many of those transits :func:`~atdrone.deploy.transit.plan_transit` refused, and how
many episode ends would end the flight: the loop redraws the spawn up to
``SPAWN_DRAWS`` times, so consecutive groups of that many draws from one end, all refused.

Usage: python benchmarks/deploy_transits.py LOG_DIR [LOG_DIR ...] [--draws 20] (a multiple of SPAWN_DRAWS)
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from atdrone.config import load_task
from atdrone.deploy.sequence import SPAWN_DRAWS
from atdrone.deploy.shield import Obstacles, ShieldConfig, geofence, push_out_of_obstacles
from atdrone.deploy.transit import TransitBlocked, plan_transit, separated_spawn
from atdrone.envs.core import spawn
from atdrone.envs.geometry import Geometry


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", nargs="+", type=Path)
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--draws", type=int, default=20)
    parser.add_argument("--speed", type=float, default=0.3, help="goto_speed, m/s")
    parser.add_argument("--height", type=float, default=0.5)
    args = parser.parse_args()
    task, shield = load_task(args.task), ShieldConfig()
    geo = Geometry.from_config(task)
    obstacles = Obstacles(
        np.c_[geo.box_center, geo.box_half].reshape(-1, 4), np.c_[geo.disc_center, geo.disc_radius].reshape(-1, 3)
    )
    lo, hi = geofence((geo.width, geo.height), shield.margin)
    P = task.players.num_p
    rng = np.random.default_rng(0)
    starts = []
    for log in args.logs:
        flight = pd.read_parquet(log / "flight.parquet")
        for _, rows in flight[flight["step"] >= 0].groupby("episode"):
            last = rows[rows["step"] == rows["step"].max()].drop_duplicates("drone")
            order = sorted(last["drone"], key=lambda d: (last.set_index("drone").loc[d, "role"] == "evader", d))
            xy = last.set_index("drone").loc[order, ["x", "y"]].to_numpy(np.float64)
            starts.append(np.c_[xy, np.full(len(xy), args.height)])

    def draw() -> tuple[np.ndarray, np.ndarray]:
        pos, _ = spawn(task, rng, 1)
        return pos[0, :P], pos[0, P:]

    refused = np.zeros((len(starts), args.draws), dtype=bool)
    for s, start in enumerate(starts):
        for k in range(args.draws):
            pos_p, pos_e = separated_spawn(draw, shield.drone_radius, shield.drone_half_height)
            end = np.c_[np.r_[pos_p, pos_e], np.full(len(start), args.height)]
            end[:, :2], _ = push_out_of_obstacles(np.clip(end[:, :2], lo, hi), obstacles, shield.obstacle_clearance)
            end[:, :2] = np.clip(end[:, :2], lo, hi)
            try:
                plan_transit(
                    start,
                    end,
                    args.speed,
                    shield.drone_radius,
                    shield.drone_half_height,
                    bounds=(lo, hi),
                    obstacles=obstacles,
                    clearance=shield.obstacle_clearance,
                )
            except TransitBlocked:
                refused[s, k] = True
    groups = refused[:, : args.draws // SPAWN_DRAWS * SPAWN_DRAWS].reshape(len(starts), -1, SPAWN_DRAWS)
    print(
        json.dumps(
            {
                "episode_ends": len(starts),
                "transits": int(refused.size),
                "blocked": int(refused.sum()),
                "rate": float(refused.mean()) if refused.size else 0.0,
                "spawn_draws": SPAWN_DRAWS,
                "redraw_groups": int(groups[..., 0].size),
                "flight_ending": int(groups.all(-1).sum()),
            }
        )
    )


if __name__ == "__main__":
    main()
