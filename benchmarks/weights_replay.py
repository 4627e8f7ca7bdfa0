"""Replay a benchmark's published weights: each plays every zoo of its manifest again, on the episodes the
benchmark played (its evaluation seed and episode count), and is compared with its manifest's metrics.

Prints JSON: this host's float kernels (:func:`atdrone.hostinfo.float_kernels`), and per weight and zoo the
manifest's and the replay's SUC, COL, AST and REW, whether they are equal to the last bit, and whether the
manifest was measured on float kernels equal to this host's (where they must be). Exit 1 when a weight measured
on this host's kernels plays other metrics. A zoo of 500 episodes takes 3-5 s of one core (a paper-budget
weight: 4 zoos); the quick benchmark's 32 weights (5 zoos, 100 episodes each) took 6 minutes beside a running
grid. Its ``differs`` says per metric how many replays differ and by how much at most.

With ``--cells GLOB`` it replays a grid's cell records instead (``runs/benchmarks/<benchmark>/cells/``, their
learners restored beside them; floors are skipped): whether the records of cells run on other machines replay on
this one.

Usage: python benchmarks/weights_replay.py [--benchmark paper_budget] [--methods sp hola] [--tasks 4p2e5o]
       [--zoos zoo3] [--cells 'sp-4p2e5o-*'] [--out FILE]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent.parent


def _same(a: dict[str, float], b: dict[str, float]) -> bool:
    return set(a) == set(b) and all(a[k] == b[k] or (math.isnan(a[k]) and math.isnan(b[k])) for k in a)


def _weights(results: Path, config: dict[str, Any], methods: Any, tasks: Any) -> list[dict[str, Any]]:
    """One item per published weight: what to play and what it kept."""
    from atdrone.benchmark.weights import REPO

    items = []
    for path in sorted((results / "weights").glob("*/*.json")):
        doc = json.loads(path.read_text())
        if (methods and doc["method"] not in methods) or (tasks and doc["task"] not in tasks):
            continue
        docs = doc.get("zoo_documents")  # weights measured before the zoos were made per task
        zoos = {zoo: REPO / docs / f"{zoo}.json" if docs else zoo for zoo in doc["metrics"]}
        items.append(
            {
                "label": f"{doc['benchmark']}/{doc['method']}/{doc['task']}",
                "policy": f"weights:{doc['benchmark']}/{doc['method']}/{doc['task']}",
                "task": doc["task"],
                "seed": int(doc["seed"]),
                "episodes": int(doc.get("eval_episodes", config["eval_episodes"])),
                "metrics": doc["metrics"],
                "zoos": zoos,
                "measured_on": doc.get("measured_on"),
            }
        )
    return items


def _cells(folder: Path, pattern: str, config: dict[str, Any]) -> list[dict[str, Any]]:
    """One item per cell record matching ``pattern`` (floors aside): its learner and its metrics."""
    items = []
    for path in sorted((folder / "cells").glob(f"{pattern}.json")):
        rec = json.loads(path.read_text())
        if path.name.startswith("_") or "checkpoint" not in rec:
            continue
        if not (folder / rec["checkpoint"]).is_file():  # e.g. a best response: the grid keeps no learner of it
            print(f"{rec['name']}: no learner at {rec['checkpoint']}, skipped", file=sys.stderr)
            continue
        items.append(
            {
                "label": rec["name"],
                "policy": str(folder / rec["checkpoint"]),
                "task": rec["cell"]["task"],
                "seed": int(rec["cell"]["seed"]),
                "episodes": int(config["eval_episodes"]),
                "metrics": rec["metrics"],
                "zoos": {zoo: zoo for zoo in rec["metrics"]},
                "measured_on": rec.get("timing", {}).get("machine"),
            }
        )
    return items


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--benchmark", default="paper_budget", help="a folder of benchmarks/results/")
    parser.add_argument("--methods", nargs="*", default=None)
    parser.add_argument("--tasks", nargs="*", default=None)
    parser.add_argument("--zoos", nargs="*", default=None)
    parser.add_argument("--cells", default=None, help="replay the grid's cell records matching this glob instead")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)

    from atdrone.benchmark.weights import play_as_cell
    from atdrone.hostinfo import float_kernels

    config = json.loads((HERE / "configs" / "benchmarks" / f"{args.benchmark}.json").read_text())
    if args.cells:
        items = _cells(HERE / "runs" / "benchmarks" / args.benchmark, args.cells, config)
    else:
        items = _weights(HERE / "benchmarks" / "results" / args.benchmark, config, args.methods, args.tasks)
    if not items:
        parser.error("nothing to replay: no published weights or cell records match")
    here = float_kernels()
    rows: list[dict[str, Any]] = []
    for item in items:
        for zoo, played_zoo in item["zoos"].items():
            if args.zoos and zoo not in args.zoos:
                continue
            t0 = time.perf_counter()
            played = play_as_cell(item["policy"], item["task"], played_zoo, item["seed"], item["episodes"])
            kept = item["metrics"][zoo]
            rows.append(
                {
                    "replayed": item["label"],
                    "zoo": zoo,
                    "episodes": item["episodes"],
                    "kept": kept,
                    "played": played,
                    "bit_for_bit": _same(kept, played),
                    "abs_diff": {k: abs(kept[k] - played[k]) for k in kept if k in played},
                    "measured_here": item["measured_on"] == here,
                    "wall_s": round(time.perf_counter() - t0, 1),
                }
            )
            print(f"{item['label']} {zoo}: {'equal' if rows[-1]['bit_for_bit'] else 'differs'}", file=sys.stderr)
    failed = [r for r in rows if r["measured_here"] and not r["bit_for_bit"]]
    report = {
        "host": here,
        "replayed": len(rows),
        "bit_for_bit": sum(r["bit_for_bit"] for r in rows),
        "measured_here": sum(r["measured_here"] for r in rows),
        "failed": len(failed),
        # per metric: how many replays differ from what was kept, and by how much at most (NaN: an AST of no success)
        "differs": {
            m: {
                "rows": sum(not _same({m: r["kept"][m]}, {m: r["played"][m]}) for r in rows),
                "max_abs_diff": max((r["abs_diff"][m] for r in rows if not math.isnan(r["abs_diff"][m])), default=0.0),
            }
            for m in ("SUC", "COL", "AST", "REW")
        },
        "rows": rows,
    }
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        args.out.write_text(text + "\n")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
