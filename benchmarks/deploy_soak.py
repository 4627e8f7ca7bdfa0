"""Soak: armed three-episode flights of the shipped sim config, run as a user runs them, on a busy host.

Each flight is ``atdrone deploy configs/deploy/sim_4p2e1o.json --arm --episodes 3`` in its
own process (the config unchanged: its clock rate, the radio model with lost and retried
packets, every threshold), with ``--busy`` processes spinning on the CPU beside it the
whole time. Per flight it reads the log the job wrote: episodes flown, how each drone
ended (the job's word) and what the simulated firmware saw (``fleet.json``: every impact
with the floor and what cut the motors). A drone counts as **cut in the air** when it met
the floor faster than 0.5 m/s with its motors off (it fell), and as a **hard landing**
when it met it that fast with its motors on (a landing meets it at 0.1-0.2 m/s). Writes
JSON: flights, flights that flew every episode, drones cut in the air (goal: 0), hard
landings, exits non-zero, per flight the details; the load average before and after, the
command, the date.

Usage: python benchmarks/deploy_soak.py [--flights 20] [--busy 2] [--out benchmarks/results/deploy_soak.json]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
CONFIG = ROOT / "configs" / "deploy" / "sim_4p2e1o.json"
IMPACT = 0.5  # m/s: faster than a landing ever meets the floor


def config_path(work: Path) -> Path:
    """The shipped config; a copy naming the same member where its checkpoint moved to the task's folder."""
    doc = json.loads(CONFIG.read_text())
    member = Path(doc["member"].get("checkpoint", ""))
    if member.suffix and not (ROOT / member).is_file():
        moved = member.parent / "4p2e1o" / member.name
        if (ROOT / moved).is_file():
            doc["member"]["checkpoint"] = str(moved)
            path = work / CONFIG.name
            path.write_text(json.dumps(doc, indent=2))
            return path
    return CONFIG


def from_log(log: Path) -> dict[str, Any]:
    """What one flight's log directory says (meta.json, fleet.json)."""
    meta = json.loads((log / "meta.json").read_text())
    fleet = json.loads((log / "fleet.json").read_text()) if (log / "fleet.json").is_file() else {}
    impacts = {n: [(s, on) for _, s, on in v["impacts"]] for n, v in fleet.items()}
    return {
        "log_dir": log.name,
        "episodes_flown": int(meta.get("episodes_flown", 0)),
        "ended_early": str(meta.get("ended_early", "")),
        "endings": meta.get("endings", {}),
        "max_impact": {n: max((s for s, _ in v), default=0.0) for n, v in impacts.items()},
        "cut_in_the_air": sorted(n for n, v in impacts.items() if any(s >= IMPACT and not on for s, on in v)),
        "hard_landing": sorted(n for n, v in impacts.items() if any(s >= IMPACT and on for s, on in v)),
        "stopped_by": {n: sorted({w for _, w in v["history"]}) for n, v in fleet.items() if v["history"]},
        "overruns": int(meta.get("overruns", 0)),
    }


def fly_once(config: Path, out: Path, episodes: int, timeout: float) -> dict[str, Any]:
    """One armed flight through the CLI; what its log says."""
    before = set(out.iterdir()) if out.exists() else set()
    cmd = [sys.executable, "-m", "atdrone.cli", "deploy", str(config), "--arm", "--episodes", str(episodes)]
    cmd += ["--out-dir", str(out), "--tracking-uri", f"sqlite:///{out / 'mlflow.db'}"]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    wall = time.perf_counter() - t0
    logs = [p for p in set(out.iterdir()) - before if (p / "meta.json").is_file()]
    row: dict[str, Any] = {"exit": proc.returncode, "wall_s": round(wall, 1), "stderr_tail": proc.stderr[-400:]}
    if len(logs) != 1:
        row["error"] = f"expected one new log directory, found {len(logs)}"
        return row
    row.update(from_log(logs[0]))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--flights", type=int, default=20)
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--busy", type=int, default=2, help="busy-looping processes beside the flights")
    parser.add_argument("--timeout", type=float, default=600.0, help="wall seconds one flight may take")
    parser.add_argument("--out", default=str(ROOT / "benchmarks" / "results" / "deploy_soak.json"))
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="deploy_soak_"))
    config = config_path(work)
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.busy)]
    load_before = os.getloadavg()
    rows = []
    try:
        for k in range(args.flights):
            row = fly_once(config, work / "flights", args.episodes, args.timeout)
            rows.append(row)
            print(json.dumps({"flight": k, **{x: row.get(x) for x in ("exit", "episodes_flown", "cut_in_the_air")}}))
    finally:
        for p in busy:
            p.kill()
            p.wait()
    result = {
        "command": f"python benchmarks/deploy_soak.py --flights {args.flights} --episodes {args.episodes} "
        f"--busy {args.busy}",
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "config": str(CONFIG.relative_to(ROOT)),
        "host": {"cpus": os.cpu_count(), "python": platform.python_version(), "machine": platform.machine()},
        "load_average_before": [round(v, 2) for v in load_before],
        "load_average_after": [round(v, 2) for v in os.getloadavg()],
        "flights": len(rows),
        "flew_every_episode": sum(r.get("episodes_flown", 0) == args.episodes for r in rows),
        "drones_cut_in_the_air": sum(len(r.get("cut_in_the_air", [])) for r in rows),
        "hard_landings": sum(len(r.get("hard_landing", [])) for r in rows),
        "drones_not_landed": sum(sum(e != "landed" for e in r.get("endings", {}).values()) for r in rows),
        "exit_nonzero": sum(r["exit"] != 0 for r in rows),
        "wall_s_median": sorted(r["wall_s"] for r in rows)[len(rows) // 2] if rows else None,
        "per_flight": rows,
    }
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    summary = {k: result[k] for k in ("flights", "flew_every_episode", "drones_cut_in_the_air", "exit_nonzero")}
    print(json.dumps(summary))


if __name__ == "__main__":
    main()
