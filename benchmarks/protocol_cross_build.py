"""One open-teaming learner played on two builds: how far apart are its numbers?

Usage, with two cells of ``benchmarks/protocol_report.py`` for the same learner, task and seed played on two builds
(python, numpy, torch):

    python benchmarks/protocol_cross_build.py CELL_A CELL_B > benchmarks/results/protocols/cross_build.json

Prints JSON: both builds; every metric of both cells side by side (protocols, splits, sizes) with its difference
B - A; for SUC, the mean and largest absolute difference; and the SUC each protocol costs (Zoo 3 alone minus the
protocol) on each build, the number the report compares between methods.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import Any


def leaves(node: Any, prefix: str = "") -> dict[str, float]:
    """Every number of a cell's protocols, splits and sizes, by its path."""
    if isinstance(node, dict):
        found: dict[str, float] = {}
        for key, value in node.items():
            found.update(leaves(value, f"{prefix}/{key}" if prefix else str(key)))
        return found
    return {prefix: float(node)} if isinstance(node, (int, float)) else {}


def compare(a: dict[str, Any], b: dict[str, Any]) -> dict[str, Any]:
    """The two cells side by side; they must be one learner on one task and seed."""
    for key in ("policy", "task", "seed", "episodes"):
        if a.get(key) != b.get(key):
            raise SystemExit(f"the cells differ in {key}: {a.get(key)!r} and {b.get(key)!r}")
    left = leaves({k: a[k] for k in ("protocols", "splits", "sizes")})
    right = leaves({k: b[k] for k in ("protocols", "splits", "sizes")})
    rows = {
        path: {"A": round(left[path], 3), "B": round(right[path], 3), "B-A": round(right[path] - left[path], 3)}
        for path in left
        if path in right
    }
    suc = [row["B-A"] for path, row in rows.items() if path.endswith("/SUC")]

    def costs(cell: dict[str, Any]) -> dict[str, float]:
        zoo3 = cell["protocols"]["zoo3"]["SUC"]
        return {name: round(zoo3 - found["SUC"], 3) for name, found in cell["protocols"].items() if name != "zoo3"}

    return {
        "learner": {key: a[key] for key in ("policy", "task", "seed", "episodes")},
        "builds": {"A": a.get("build", "not recorded"), "B": b.get("build", "not recorded")},
        "SUC_difference": {
            "numbers": len(suc),
            "mean": round(sum(suc) / len(suc), 3),
            "max_abs": round(max(abs(d) for d in suc), 3),
            "unchanged": sum(d == 0 for d in suc),
        },
        "protocol_cost": {"A": costs(a), "B": costs(b)},
        "metrics": rows,
    }


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 2:
        raise SystemExit("usage: protocol_cross_build.py CELL_A CELL_B")
    a, b = (json.loads(Path(p).read_text()) for p in args)
    print(json.dumps(compare(a, b), indent=1))


if __name__ == "__main__":
    main()
