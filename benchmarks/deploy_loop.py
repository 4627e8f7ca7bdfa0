"""The deploy loop with 6 drones on the sim backend in real time: does it hold 10 Hz?

Flies configs/deploy/sim_4p2e1o.json (4 pursuers, 2 evader drones, real cflib over the
simulated radio to the firmware-like simulated fleet, simulated motion capture at 100 Hz
posted to the bridge's sender, extpose at 50 Hz) at clock rate 1 for ``--episodes``
episodes of at most ``--steps`` steps, then prints JSON: ticks, overruns, the achieved
tick rate, per-stage latency percentiles (ms) from the flight log, and the pursuers'
median ground speed on the policy legs (trained: 0.30 m/s). The reference in the same run
is the tick period (100 ms): ``p99_over_period`` is the tick latency's 99th percentile as
a share of it. Targets: 10 Hz held, tick p99 < 20 ms, ground speed within 10 % of 0.30.

Usage: python benchmarks/deploy_loop.py [--steps 300] [--episodes 3] [--out-dir reports/deploy_bench]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from atdrone.deploy.config import load_deploy
from atdrone.deploy.job import effective_task, run_deploy

ROOT = Path(__file__).resolve().parent.parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300, help="episode steps at 10 Hz (default 300: 30 s)")
    parser.add_argument("--episodes", type=int, default=3, help="episodes flown (default 3)")
    parser.add_argument("--out-dir", default=None, help="where the flight log goes (default: a temp dir)")
    args = parser.parse_args()
    out = Path(args.out_dir or tempfile.mkdtemp(prefix="deploy_bench_"))
    doc = json.loads((ROOT / "configs" / "deploy" / "sim_4p2e1o.json").read_text())
    doc.update(
        horizon=args.steps,
        episodes=args.episodes,
        out_dir=str(out),
        sim={"clock_rate": 1.0, "mocap_rate": 100.0, "mocap_noise": 0.002, "mocap_latency": 0.01},
    )
    cfg = load_deploy(doc)
    result = run_deploy(cfg, arm=True, tracking_uri=f"sqlite:///{out / 'mlflow.db'}", say=lambda _: None)
    assert result.log_dir is not None and result.summary is not None
    frame = pd.read_parquet(result.log_dir / "flight.parquet")
    episode = frame[frame.step >= 0].drop_duplicates("t")
    gaps = episode.groupby("episode").t.diff().dropna().to_numpy()  # tick to tick within each episode
    stages = [c.removeprefix("latency_") for c in episode.columns if c.startswith("latency_")]
    latency = {
        s: {f"p{q}": float(np.nanpercentile(episode[f"latency_{s}"], q) * 1000) for q in (50, 95, 99)}
        for s in stages
        if episode[f"latency_{s}"].notna().any()
    }
    period = effective_task(cfg).dt
    tick_p99 = latency.get("tick", {}).get("p99", float("nan"))
    report = {
        "drones": len(cfg.drones),
        "ticks": len(episode),
        "overruns": int(result.summary.get("overruns", 0)),
        "rate_hz": float(1.0 / gaps.mean()) if len(gaps) else float("nan"),
        "max_tick_gap_s": float(gaps.max()) if len(gaps) else float("nan"),
        "latency_ms": latency,
        "tick_p99_ms": tick_p99,
        "p99_over_period": tick_p99 / (period * 1000),
        "ground_speed_median": result.summary["ground_speed_median"],
        "ended_early": result.ended_early,
        "load_average": list(os.getloadavg()),
        "targets": {"rate_hz": 10.0, "tick_p99_ms": 20.0, "ground_speed_median": 0.30},
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
