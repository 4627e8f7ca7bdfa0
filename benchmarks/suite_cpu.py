"""Where a command's CPU goes, by kind of process: the test suite's map of Ray actors, pytest workers and daemons.

Runs the command and, until it ends, reads every process's cumulative CPU time (utime + stime from
/proc/PID/stat) each --interval seconds; a process is counted from the first sample that sees it (one
that lives less than an interval may be missed). Each process is named by what it runs: a Ray actor by
its class (Ray titles a worker ``ray::ClassName`` once it holds one), a pytest worker, a Ray daemon or the
program's own name. Prints JSON: the wall time, the CPU-seconds of every kind with its process count,
and the total. Linux only. Measure on an otherwise idle machine: every process is counted.

Usage: python benchmarks/suite_cpu.py [--interval 0.5] -- python tests/run_suite.py
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import time
from collections import defaultdict
from pathlib import Path

TICK = os.sysconf("SC_CLK_TCK")


def _sample(seen: dict[tuple[str, str], list]) -> None:
    """Update ``seen[(pid, start time)] = [cpu seconds, command line]`` from /proc."""
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
            fields = stat[stat.rindex(")") + 2 :].split()
            cpu = (int(fields[11]) + int(fields[12])) / TICK
            key = (entry.name, fields[19])
            name = seen[key][1] if key in seen else ""
            if not re.match(r"ray::(?!IDLE)", name):  # read again until its actor names it (a zombie's is empty)
                name = (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace").strip() or name
            seen[key] = [cpu, name]
        except (OSError, ValueError, IndexError):
            continue  # gone between the listing and the read


def kind(cmdline: str) -> str:
    """What a process is, from its command line."""
    if m := re.match(r"ray::(\w+)", cmdline):
        return f"ray actor {m.group(1)}" if m.group(1) != "IDLE" else "ray worker (idle)"
    if "default_worker.py" in cmdline:
        return "ray worker (starting)"
    if "pytest" in cmdline or "exec(eval(sys.stdin.readline()))" in cmdline:
        return "pytest"
    words = cmdline.split()
    for word in words[:3]:
        name = Path(word).name
        if name.endswith(".py") or name in ("gcs_server", "raylet", "mypy", "ruff"):
            return name
    return Path(words[0]).name if words else "?"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--interval", type=float, default=0.5, help="seconds between samples")
    parser.add_argument("command", nargs=argparse.REMAINDER, help="the command, after --")
    args = parser.parse_args()
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("give the command to measure after --")
    before: dict[tuple[str, str], list] = {}
    _sample(before)
    seen: dict[tuple[str, str], list] = {}
    start = time.monotonic()
    proc = subprocess.Popen(command)
    while proc.poll() is None:
        _sample(seen)
        time.sleep(args.interval)
    wall = time.monotonic() - start
    groups: dict[str, list[float]] = defaultdict(lambda: [0.0, 0])
    for key, (cpu, cmdline) in seen.items():
        if key[0] == str(os.getpid()):
            continue  # this sampler
        cpu -= before.get(key, [0.0])[0]  # a process older than the command: only what it used since
        if cpu > 0:
            g = groups[kind(cmdline)]
            g[0] += cpu
            g[1] += 1
    ordered = sorted(groups.items(), key=lambda kv: -kv[1][0])
    print(
        json.dumps(
            {
                "benchmark": "suite_cpu",
                "command": command,
                "exit_status": proc.returncode,
                "wall_s": round(wall, 1),
                "cpu_s": round(sum(g[0] for g in groups.values()), 1),
                "by_kind": {k: {"cpu_s": round(g[0], 1), "processes": g[1]} for k, g in ordered},
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
