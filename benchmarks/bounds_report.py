"""The bounds of the normalised scores, from a benchmark grid's cell records, with self-play beside them.

    python benchmarks/bounds_report.py [--cells benchmarks/results/paper_budget/cells] [--out DIR]

Per (task, test zoo) whose floor and best responses are all done (every seed of the grid's config): the floor (a
random learner with the zoo's partners: SUC over its episodes), the best response (trained with the zoo's partners
at the grid's budget: SUC per seed, mean ± std, ddof 1), the one-sided Welch test that the best response is above
the floor (:mod:`atdrone.benchmark.bounds`) and whether the bound is usable, with the zoo version it was measured
with. Beside it, self-play's SUC with the same zoo (the grid's ``sp`` cells of that task, where done) and the best
response minus self-play paired by seed, with a 95 % t-interval of seeds - 1 degrees of freedom: a best response
that is not above self-play is no upper bound of what a learner reaches, whatever the floor test says.

Reads only the records (nothing is trained or played; a second). Writes ``<out>/bounds.json`` (the stored
bounds, :func:`atdrone.benchmark.bounds.write_bounds`), ``<out>/bounds.md`` and ``<out>/bounds_table.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from atdrone.benchmark.bounds import Bound, bounds_from_records, write_bounds
from atdrone.benchmark.stats import over_seeds, t_interval
from atdrone.fileio import atomic_write_text

ROOT = Path(__file__).resolve().parent.parent
CELLS = ROOT / "benchmarks" / "results" / "paper_budget" / "cells"


def load(cells: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """The grid's config and its finished cell records."""
    config = json.loads((cells / "_config.json").read_text())["config"]
    records = [json.loads(p.read_text()) for p in sorted(cells.glob("*.json")) if not p.name.startswith("_")]
    return config, records


def complete(config: dict[str, Any], records: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The br and floor records of the (task, zoo)s whose floor and every seed's best response are done."""
    seeds = set(config["seeds"])
    by_key: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in records:
        if r["cell"]["kind"] in ("br", "floor"):
            by_key.setdefault((r["cell"]["task"], r["cell"]["zoo"]), []).append(r)
    kept = []
    for rows in by_key.values():
        br_seeds = {r["cell"]["seed"] for r in rows if r["cell"]["kind"] == "br"}
        if br_seeds >= seeds and any(r["cell"]["kind"] == "floor" for r in rows):
            kept += rows
    return kept


def table(config: dict[str, Any], records: list[dict[str, Any]], bounds: list[Bound]) -> list[dict[str, Any]]:
    """One row per bound (:func:`bounds`): the bound, and self-play beside it."""
    done = complete(config, records)
    sp_records = [r for r in records if r["cell"]["kind"] == "method" and r["cell"]["method"] == "sp"]
    sp = {(r["cell"]["task"], r["cell"]["seed"]): r["metrics"] for r in sp_records}
    samples = {
        (r["cell"]["kind"], r["cell"]["task"], r["cell"].get("zoo", "")): r["budget"].get("learner_samples", 0)
        for r in [*done, *sp_records]
    }
    rows = []
    for b in bounds:
        br = {
            r["cell"]["seed"]: float(r["metrics"][b.zoo]["SUC"])
            for r in done
            if r["cell"]["kind"] == "br" and (r["cell"]["task"], r["cell"]["zoo"]) == (b.task, b.zoo)
        }
        sp_suc = {s: float(sp[(b.task, s)][b.zoo]["SUC"]) for s in br if (b.task, s) in sp}
        diff = t_interval([br[s] - sp_suc[s] for s in sorted(sp_suc)]) if len(sp_suc) >= 2 else None
        rows.append(
            {
                "task": b.task,
                "zoo": b.zoo,
                "zoo_version": b.zoo_version,
                "floor_suc": b.floor_suc,
                "floor_episodes": b.floor_episodes,
                "br_suc": [br[s] for s in sorted(br)],
                "p_value": b.p_value,
                "usable": b.usable,
                "sp_suc": [sp_suc[s] for s in sorted(sp_suc)],
                "br_minus_sp": diff,
                "br_learner_samples": samples.get(("br", b.task, b.zoo), 0),
                "sp_learner_samples": samples.get(("method", b.task, ""), 0),
            }
        )
    return rows


def bounds(config: dict[str, Any], records: list[dict[str, Any]]) -> list[Bound]:
    """The bounds of the complete (task, zoo)s."""
    return bounds_from_records(complete(config, records), int(config["eval_episodes"]))


def markdown(config: dict[str, Any], rows: list[dict[str, Any]], cells: Path) -> str:
    """The bounds table and what it means."""
    budget = int(config.get("env_steps", 0))
    lines = [
        "# Bounds of the normalised scores",
        "",
        f"From the cell records in `{cells.relative_to(ROOT) if cells.is_relative_to(ROOT) else cells}` "
        f"(budget {budget:,} env steps per run, {config['eval_episodes']} evaluation episodes per zoo, "
        f"seeds {', '.join(str(s) for s in config['seeds'])}). Made by `python benchmarks/bounds_report.py`.",
        "",
        "floor: a random learner with the zoo's partners. BR: a best response trained with the zoo's partners at the "
        "same budget (SUC per seed, mean ± std, ddof 1). p: one-sided Welch test of BR above the floor; a bound "
        "is usable (scores are normalised against it) at p < 0.05. SP: self-play with the same zoo, same seeds; "
        "BR - SP paired by seed, 95 % t-interval with seeds - 1 degrees of freedom.",
        "",
        "| task | zoo | floor SUC | BR SUC | p | usable | SP SUC | BR - SP [95 % CI] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        d = r["br_minus_sp"]
        vs = f"{d['diff']:+.1f} [{d['ci95'][0]:+.1f}, {d['ci95'][1]:+.1f}]" if d else "-"
        lines.append(
            f"| {r['task']} | {r['zoo']} | {r['floor_suc']:.1f} | {over_seeds(r['br_suc'])} | {r['p_value']:.2g} | "
            f"{'yes' if r['usable'] else 'no'} | {over_seeds(r['sp_suc'])} | {vs} |"
        )
    below = [r for r in rows if r["br_minus_sp"] and r["br_minus_sp"]["ci95"][1] < 0]
    if below:
        names = ", ".join(f"{r['task']} {r['zoo']}" for r in below)
        counts = "; ".join(
            f"{r['task']} {r['zoo']}: {r['br_learner_samples']:,} against {r['sp_learner_samples']:,}" for r in below
        )
        lines += [
            "",
            f"**The best response is below self-play** ({names}: the whole interval under 0). A best response "
            "learns from the drones it controls alone, self-play's learner from every pursuer, so at the same env "
            f"steps it collects fewer learner samples ({counts}). At this budget it is not an upper bound of what "
            "a learner reaches there: a normalised score above 1 means beating this best response, not the best "
            "possible teammate.",
        ]
    versions = "; ".join(sorted({r["zoo_version"] for r in rows}))
    lines += ["", f"Zoo versions: {versions}.", ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--cells", type=Path, default=CELLS, help="a benchmark grid's cell records")
    parser.add_argument("--out", type=Path, default=None, help="where to write (default: the cells' parent)")
    args = parser.parse_args()
    cells = args.cells.resolve()
    out = (args.out or cells.parent).resolve()
    config, records = load(cells)
    measured = bounds(config, records)
    rows = table(config, records, measured)
    write_bounds(measured, out / "bounds.json")
    atomic_write_text(out / "bounds_table.json", json.dumps(rows, indent=1) + "\n")
    atomic_write_text(out / "bounds.md", markdown(config, rows, cells))
    print(f"{len(rows)} bounds: {out / 'bounds.md'}")


if __name__ == "__main__":
    main()
