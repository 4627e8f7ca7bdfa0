"""Add the episode summaries to finished cell records that lack them, by playing each cell's evaluation again.

    python benchmarks/grid_episodes.py [--config paper_budget] [--cells DIR] [--limit N] [PATTERN...]

A cell's record keeps, per zoo, :func:`~atdrone.benchmark.episodes.episode_summary` of its evaluation (who was in
the collisions, captures, episode lengths, the return split into the reward's terms); records written before the
summaries were kept have only the metrics. This script plays each such cell's evaluation again: the same learner
(the checkpoint its record names, checked against its sha256), the same zoos in the same order, episodes and seed.
Evaluation of a trained learner is deterministic, so the replay's SUC, COL, AST and REW must equal the record's to
the last bit: a record whose replay differs is left as it is and named (exit 1). A record that matches gets its
``episodes``, written atomically in the job's own format. A floor replays its random learner (its turns drawn from
the drones' keys, as the job draws them). Records that already have them, and cells whose learner is not in the
folder, are skipped (the latter named). It prints a line per record and costs what the cells' evaluations cost
(about 40 s of one core per method cell on a 2-core host), so run it at a low priority beside other work.
"""

from __future__ import annotations

import argparse
import fnmatch
import hashlib
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from atdrone.fileio import atomic_write_bytes

ROOT = Path(__file__).resolve().parent.parent


def _same(a: float, b: float) -> bool:
    return (math.isnan(a) and math.isnan(b)) or a == b


def replay(cfg: Any, record: dict[str, Any]) -> dict[str, dict[str, float]] | str:
    """The record's episode summaries from its evaluation played again, or why not (a line)."""
    from atdrone.benchmark.cells import EVAL_SEED, RandomPolicy, cell_zoos
    from atdrone.benchmark.episodes import episode_summary
    from atdrone.config import load_task
    from atdrone.policies.neural import load_policy
    from atdrone.teams.evaluation import METRICS, evaluate

    cell = record["cell"]
    if cell["kind"] == "floor":
        policy: Any = RandomPolicy(EVAL_SEED + cell["seed"])
    else:
        checkpoint = cfg.folder / record["checkpoint"]
        if not checkpoint.is_file():
            return f"skipped: no learner at {checkpoint}"
        if hashlib.sha256(checkpoint.read_bytes()).hexdigest() != record["sha256"]:
            return f"skipped: {checkpoint} is not the learner its record names (sha256)"
        policy = load_policy(checkpoint)
    zoos = cell_zoos(cfg, cell["kind"], cell["zoo"])
    task = load_task(cell["task"])
    out = {}
    for zoo in zoos:
        result = evaluate(policy, task, zoo, episodes=cfg.eval_episodes, seeds=[EVAL_SEED + cell["seed"]])
        kept = record["metrics"][zoo]
        if not all(_same(float(result.mean[m]), float(kept[m])) for m in METRICS):
            return f"differs: {zoo} replayed {result.mean}, recorded {kept}"
        out[zoo] = episode_summary(result.records, task)
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="paper_budget", help="the benchmark (a configs/benchmarks name or a path)")
    ap.add_argument("--cells", type=Path, help="the cell records (default: the benchmark folder's cells/)")
    ap.add_argument("--limit", type=int, default=0, help="at most this many records (0: all)")
    ap.add_argument("patterns", nargs="*", help="only the cells whose names match one of these (fnmatch), in order")
    args = ap.parse_args(argv)
    import torch

    from atdrone.benchmark.config import parse_benchmark

    torch.set_num_threads(1)
    cfg = parse_benchmark(args.config)
    cells = args.cells or cfg.folder / "cells"
    paths = [p for p in sorted(cells.glob("*.json")) if not p.name.startswith("_")]
    if args.patterns:
        paths = list(dict.fromkeys(p for pattern in args.patterns for p in paths if fnmatch.fnmatch(p.stem, pattern)))
    todo = [p for p in paths if "episodes" not in json.loads(p.read_text())]
    if args.limit:
        todo = todo[: args.limit]
    print(f"{len(todo)} of {len(paths)} records in {cells} lack episode summaries", flush=True)
    failed = []
    for i, path in enumerate(todo, 1):
        t0 = time.perf_counter()
        record = json.loads(path.read_text())
        got = replay(cfg, record)
        if isinstance(got, str):
            print(f"[{i}/{len(todo)}] {path.stem}: {got}", flush=True)
            failed += [path.stem] if got.startswith("differs") else []
            continue
        record["episodes"] = got
        atomic_write_bytes(path, json.dumps(record, indent=2, sort_keys=True).encode())
        print(f"[{i}/{len(todo)}] {path.stem}: {len(got)} zoo(s) in {time.perf_counter() - t0:.0f} s", flush=True)
    if failed:
        print(f"replays that differ from their records (left as they were): {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
