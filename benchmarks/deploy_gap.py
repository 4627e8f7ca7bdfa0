"""Armed episodes on the simulated fleet, in resumable chunks: link losses, ground speed, the gap to the simulator.

Flies configs/deploy/gap_4p2e1o.json (4 pursuers, 2 evader drones, real cflib over the
simulated radio to the firmware-like simulated fleet) ``--episodes`` episodes in chunks
of ``--chunk``, each chunk one armed deploy job with its own seed. A chunk's result is
written atomically to ``WORK/chunk_NNN.json`` when it ends; a rerun skips the chunks
already there, so a killed run resumes where it stopped. Then prints (and writes to
``--out``) JSON: episodes flown, chunks that ended early and why (a lost link among
them), link-loss events in the logs, the pursuers' median ground speed on the policy
legs, min separation, and the gap of SUC/COL/AST to the training simulator's
evaluation of the same team on the same task and horizon (500 episodes), and the
simulator's SUC/COL/AST at the fleet's capture reach (docs/deploy.md, "Capturing an evader drone").

Usage: nice -n 10 python benchmarks/deploy_gap.py [--episodes 50] [--chunk 5] [--clock-rate 1]
       [--horizon 500] [--work-dir reports/deploy_gap] [--out benchmarks/results/deploy_gap_4p2e1o.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import platform
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from atdrone.deploy.config import DeployConfig, load_deploy
from atdrone.deploy.flightlog import episode_metrics, ground_speed
from atdrone.deploy.job import build_team, effective_task, run_deploy, simulation_gap
from atdrone.deploy.loop import Team
from atdrone.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent


def _chunk(args: argparse.Namespace, k: int, work: Path) -> dict[str, Any]:
    doc = json.loads((ROOT / "configs" / "deploy" / "gap_4p2e1o.json").read_text())
    doc.update(
        name=f"gap_chunk_{k:03d}",
        episodes=args.chunk,
        horizon=args.horizon,
        seed=args.seed + k,
        out_dir=str(work / "logs"),
        sim={**doc.get("sim", {}), "clock_rate": args.clock_rate},
    )
    cfg = load_deploy(doc)
    started = time.time()
    result = run_deploy(
        cfg, arm=True, tracking_uri=f"sqlite:///{work / 'mlflow.db'}", say=lambda m: print(f"  [{k}] {m}", flush=True)
    )
    frame = pd.read_parquet(result.log_dir / "flight.parquet") if result.log_dir else pd.DataFrame()
    return {
        "chunk": k,
        "seed": cfg.seed,
        "clock_rate": args.clock_rate,
        "log_dir": str(result.log_dir),
        "episodes_flown": result.episodes_flown,
        "ended_early": result.ended_early,
        "link_lost_rows": int(frame["events"].str.contains("link_lost").sum()) if len(frame) else 0,
        "wall_s": time.time() - started,
    }


def _by_capture_range(cfg: DeployConfig, team: Team) -> dict[str, dict[str, float]]:
    """The simulator's SUC/COL/AST for the same team and horizon at the task's capture range and at the
    fleet's capture reach (0.30 m) and its farthest hold-capture (0.60 m; docs/deploy.md): how much of the
    gap the capture rule alone explains."""
    from atdrone.policies.zoo import load_zoo
    from atdrone.teams.evaluation import metrics, run_episodes

    task = effective_task(cfg)
    out = {}
    for reach in (task.task.capture_range, 0.30, 0.60):
        t = dataclasses.replace(task, task=dataclasses.replace(task.task, capture_range=reach))
        records = run_episodes(team.learner, t, load_zoo(cfg.partners.zoo).policies(), 500, seed=cfg.seed)
        out[f"{reach:.2f}"] = {k: float(v) for k, v in metrics(records).items() if k in ("SUC", "COL", "AST")}
    return out


def _report(args: argparse.Namespace, chunks: list[dict[str, Any]], final: bool) -> dict[str, Any]:
    """The report over the chunks so far (the gap to the simulator only when ``final``), written to --out."""
    episodes = pd.concat([pd.read_parquet(Path(c["log_dir"]) / "episodes.parquet") for c in chunks], ignore_index=True)
    episodes = episodes[episodes["outcome"] != "shield"]  # an episode the shield ended is an early end, below
    speeds = [ground_speed(pd.read_parquet(Path(c["log_dir"]) / "flight.parquet")) for c in chunks]
    fleet = {**episode_metrics(episodes), "episodes": len(episodes)}
    cfg = load_deploy(ROOT / "configs" / "deploy" / "gap_4p2e1o.json", horizon=args.horizon)
    team, member = build_team(cfg)
    rates: dict[float, list[int]] = {}
    for c in chunks:  # a resumed run may fly its later chunks at another rate (a loaded host)
        rates.setdefault(float(c.get("clock_rate", args.clock_rate)), []).append(int(c["chunk"]))
    report = {
        "config": f"configs/deploy/gap_4p2e1o.json, clock rate {'/'.join(map(str, rates))}, horizon {args.horizon}, "
        f"{len(chunks)} chunks of {args.chunk}, seeds {args.seed}..{args.seed + len(chunks) - 1}",
        "clock_rate_chunks": {str(r): ks for r, ks in rates.items()},
        "complete": int(sum(c["episodes_flown"] for c in chunks)) >= args.episodes,
        "member": member,
        "episodes_flown": int(sum(c["episodes_flown"] for c in chunks)),
        "episodes_compared": len(episodes),
        "fleet": fleet,
        "outcomes": {str(k): int(v) for k, v in episodes["outcome"].value_counts().sort_index().items()},
        "chunks_ended_early": {str(c["chunk"]): c["ended_early"] for c in chunks if c["ended_early"]},
        "link_loss_chunks": sum("link_lost" in c["ended_early"] for c in chunks),
        "link_lost_rows": int(sum(c["link_lost_rows"] for c in chunks)),
        "ground_speed_median_per_chunk": speeds,
        "ground_speed_median": float(np.median([s for s in speeds if math.isfinite(s)] or [math.nan])),
        "gap": simulation_gap(cfg, effective_task(cfg), team, fleet) if final and len(episodes) else None,
        "simulator_by_capture_range": _by_capture_range(cfg, team) if final else None,
        "wall_s": float(sum(c["wall_s"] for c in chunks)),
        "load_average": list(os.getloadavg()),
        "python": platform.python_version(),
    }
    if args.out:
        atomic_write_text(Path(args.out), json.dumps(report, indent=2) + "\n")
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--chunk", type=int, default=5)
    parser.add_argument("--clock-rate", type=float, default=1.0)
    parser.add_argument("--horizon", type=int, default=500, help="steps per episode, the simulator's too")
    parser.add_argument("--seed", type=int, default=100)
    parser.add_argument("--work-dir", default="reports/deploy_gap")
    parser.add_argument("--out", default="benchmarks/results/deploy_gap_4p2e1o.json")
    parser.add_argument("--report-only", action="store_true", help="aggregate the chunks already flown; fly none")
    args = parser.parse_args()
    work = Path(args.work_dir)
    work.mkdir(parents=True, exist_ok=True)
    chunks: list[dict[str, Any]] = []
    k = 0
    # chunks until ``episodes`` episodes have been flown to their own end (a chunk that ends early counts only
    # its finished episodes, and its reason is reported), at most twice the chunks needed
    while sum(c["episodes_flown"] for c in chunks) < args.episodes and k < 2 * math.ceil(args.episodes / args.chunk):
        path = work / f"chunk_{k:03d}.json"
        if not path.is_file() and args.report_only:
            break
        if not path.is_file():
            print(f"[deploy_gap] chunk {k}: {args.chunk} episodes", flush=True)
            atomic_write_text(path, json.dumps(_chunk(args, k, work), indent=2) + "\n")
        chunks.append(json.loads(path.read_text()))
        k += 1
        if not args.report_only:
            _report(args, chunks, final=False)  # the report so far, after every chunk
    print(json.dumps(_report(args, chunks, final=True), indent=2))


if __name__ == "__main__":
    main()
