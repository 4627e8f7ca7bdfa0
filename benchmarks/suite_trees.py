"""A test selection in two (or more) checkouts, round after round: wall and machine CPU of each.

Each round runs ``python -m pytest -q -p no:cacheprovider ARGS`` in every tree in turn (the tree's own
code first on ``PYTHONPATH``, its ``.venv`` or ``--python``), so a change is measured against its
parent on the same machine in the same minutes. Machine CPU is the whole machine's (/proc/stat), Ray's
actor processes included: measure on an otherwise idle machine. Prints one JSON line per run, then
the whole record.

    git worktree add --detach /tmp/before <commit>
    python benchmarks/suite_trees.py --tree before=/tmp/before --tree now=. --rounds 2 -- \
        -n 2 tests/test_service.py tests/test_service_runs.py tests/test_teammate_service.py
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def machine_cpu_s() -> float:
    """CPU-seconds the machine has spent (user, nice and system) since boot."""
    with open("/proc/stat") as f:
        fields = [int(x) for x in f.readline().split()[1:4]]
    return sum(fields) / os.sysconf("SC_CLK_TCK")


def main(argv: list[str]) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", action="append", required=True, help="LABEL=PATH, one per checkout")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--python", default="", help="the interpreter (default: each tree's .venv/bin/python)")
    parser.add_argument("pytest", nargs=argparse.REMAINDER, help="pytest's arguments, after --")
    args = parser.parse_args(argv)
    trees = dict(t.split("=", 1) for t in args.tree)
    extra = [a for a in args.pytest if a != "--"]
    runs = []
    for r in range(args.rounds):
        for label, path in trees.items():
            tree = Path(path).resolve()
            python = args.python or str(tree / ".venv" / "bin" / "python")
            env = {**os.environ, "PYTHONPATH": str(tree)}
            env.pop("PYTHONDONTWRITEBYTECODE", None)
            t0, c0 = time.monotonic(), machine_cpu_s()
            done = subprocess.run(
                [python, "-m", "pytest", "-q", "-p", "no:cacheprovider", *extra],
                cwd=tree,
                env=env,
                capture_output=True,
                text=True,
            )
            lines = done.stdout.strip().splitlines()
            row = {
                "round": r,
                "tree": label,
                "wall_s": round(time.monotonic() - t0, 1),
                "machine_cpu_s": round(machine_cpu_s() - c0, 1),
                "exit_status": done.returncode,
                "result": lines[-1] if lines else "",
            }
            print(json.dumps(row), flush=True)
            runs.append(row)
    print(json.dumps({"benchmark": "suite_trees", "trees": trees, "pytest": extra, "runs": runs}, indent=2))


if __name__ == "__main__":
    main(sys.argv[1:])
