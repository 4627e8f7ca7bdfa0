"""Keep a benchmark grid's final learners beside its cell records, and put them back in a new checkout.

    python benchmarks/grid_learners.py save    [--cells DIR] [--folder DIR] [--learners DIR]
    python benchmarks/grid_learners.py restore [--cells DIR] [--folder DIR] [--learners DIR]

A finished method cell's record names its final learner by a path in the benchmark's folder
(``runs/benchmarks/paper_budget/`` by default) and by its sha256. That folder is a run folder, never committed: a
grid resumed on another machine or in a fresh clone from its committed records (copied into the folder's
``cells/``) would skip the finished cells and then find none of their learners when it publishes weights or when
the open-teaming report plays them. ``save`` copies each method cell's learner to ``<learners>/<cell>.pt``
(about 0.4 MB each; best responses and floors are left out: the reports use only their metrics); ``restore``
copies each back to where its record names it. Both check every file's sha256 against the record and refuse a
mismatch; both skip what is already in place, so running either again changes nothing; both name the cells whose
learner is in neither place (exit 1 after copying the others).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from pathlib import Path
from typing import Any

from atdrone.fileio import atomic_write_bytes

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "paper_budget"


def method_records(cells: Path) -> list[dict[str, Any]]:
    """The finished method cells' records (those naming a learner) in ``cells``."""
    records = [json.loads(p.read_text()) for p in sorted(cells.glob("*.json")) if not p.name.startswith("_")]
    return [r for r in records if r["cell"]["kind"] == "method" and "checkpoint" in r]


def _digest(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _copy(source: Path, target: Path, sha256: str, what: str) -> bool | None:
    """Copy ``source`` to ``target`` unless the target already holds it (False); None when ``source`` is missing;
    refuse a file whose digest is not ``sha256``."""
    if target.is_file() and _digest(target) == sha256:
        return False
    if not source.is_file():
        return None
    if (found := _digest(source)) != sha256:
        raise ValueError(f"{what}: {source} has sha256 {found[:12]}..., its record says {sha256[:12]}...")
    atomic_write_bytes(target, source.read_bytes())
    return True


def sync(action: str, cells: Path, folder: Path, learners: Path) -> tuple[list[str], list[str]]:
    """``save``: copy every method cell's learner from ``folder`` to ``learners/<cell>.pt``; ``restore``: copy each
    back to where its record names it in ``folder``. The cells copied, and those whose learner is in neither
    place (a cell to run again)."""
    done, missing = [], []
    for r in method_records(cells):
        run_file, kept = folder / r["checkpoint"], learners / f"{r['name']}.pt"
        source, target = (run_file, kept) if action == "save" else (kept, run_file)
        target.parent.mkdir(parents=True, exist_ok=True)
        copied = _copy(source, target, r["sha256"], r["name"])
        if copied:
            done.append(r["name"])
        elif copied is None:
            missing.append(r["name"])
    return done, missing


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=["save", "restore"])
    parser.add_argument("--cells", type=Path, default=RESULTS / "cells", help="the cell records (committed)")
    parser.add_argument("--folder", type=Path, default=ROOT / "runs" / "benchmarks" / "paper_budget",
                        help="the benchmark's folder (its out_dir/name), where the records' paths start")  # fmt: skip
    parser.add_argument("--learners", type=Path, default=RESULTS / "learners", help="where the learners are kept")
    args = parser.parse_args(argv)
    try:
        done, missing = sync(args.action, args.cells, args.folder, args.learners)
    except (OSError, ValueError) as err:
        print(f"grid_learners: error: {err}", file=sys.stderr)
        return 1
    print(f"{args.action}: {len(done)} learner(s){': ' + ', '.join(done) if done else ''}")
    if missing:
        print(f"grid_learners: no learner for {', '.join(missing)} (run those cells again)", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
