"""Open-teaming report: learners on Zoo 3 and its team-event protocols, every split of the team, other team sizes.

Usage, on the final learners of a benchmark grid (each training seed's own learner, from the cell records):

    python benchmarks/protocol_report.py --cells benchmarks/results/paper_budget/cells \
        --runs runs/benchmarks/paper_budget --methods sp hola mappo naht_d --tasks 4p2e1o 4p2e5o

``--learner LABEL=POLICY`` adds a learner by any name ``atdrone evaluate`` takes (``{task}`` in it is the task),
reported as one seed. Each learner is played (its evaluation seed: the benchmark's, 10,000 + its training seed, so
every method meets the same episodes) with Zoo 3 alone and with zoo3+swap, zoo3+drop and zoo3+drop+join
(``--episodes`` each): SUC, SUC after the event and the recovery time REC (steps from the event to the next
capture); in every seat assignment of the task with Zoo 3 (``--split-episodes`` per assignment); and in teams of 3,
4, 5 and 6 pursuers (2 evaders, 1 obstacle) with Zoo 1 (``--episodes`` each, the learner as a cross-task player).
Per method and task: mean ± std (ddof 1) over the training seeds; the SUC a protocol costs (Zoo 3 alone minus the
protocol), paired by seed, with a 95 % t-interval of seeds - 1 degrees of freedom; and per task and protocol, which
method loses least, against each other method with the paired interval of the difference. Resumable: one JSON per
(learner, task, seed) in ``<out>/cells/``, so processes given different ``--seeds`` (or methods, tasks) can play
side by side into one ``--out``. Each cell names the build (python, numpy, torch) that played it, and the report
warns when its cells come from more than one. Writes ``<out>/report.md`` and ``report.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
from pathlib import Path
from typing import Any

import numpy as np

from atdrone.benchmark.stats import over_seeds
from atdrone.benchmark.stats import t_interval as paired_t
from atdrone.fileio import atomic_write_text

PROTOCOLS = ("zoo3+swap", "zoo3+drop", "zoo3+drop+join")
SIZES = tuple(f"configs/tasks/{n}p2e1o.json" for n in (3, 4, 5, 6))  # 4: the paper's size, for comparison
WANTED = ("SUC", "COL", "EVT", "SUC_pre", "SUC_post", "COL_post", "REC", "REC_none")
EVAL_SEED = 10_000  # the benchmark's: a learner of training seed s plays the episodes of seed EVAL_SEED + s


def play(policy_name: str, task: str, seed: int, episodes: int, split_episodes: int) -> dict[str, Any]:
    """Every number of one learner on one task."""
    from atdrone.resolve import resolve
    from atdrone.teams.evaluation import evaluate
    from atdrone.teams.splits import evaluate_splits

    learner = resolve(policy_name).policy()
    seeds = [EVAL_SEED + seed]
    out: dict[str, Any] = {"policy": policy_name, "task": task, "seed": seed, "episodes": episodes, "build": build()}
    out["protocols"] = {}
    for name in ("zoo3", *PROTOCOLS):
        result = evaluate(learner, task, "zoo3", episodes, seeds, protocol=None if name == "zoo3" else name)
        out["protocols"][name] = {k: v for k, v in result.mean.items() if k in WANTED}
    split = evaluate_splits(learner, task, "zoo3", split_episodes, seeds)
    out["splits"] = {
        str(k): {"seat_sets": int(row["seat_sets"]), "episodes": int(row["episodes"]), "SUC": float(row["SUC"])}
        for k, row in split.per_k().iterrows()
    }
    out["sizes"] = {}
    for size in SIZES:
        result = evaluate(learner, size, "zoo1", episodes, seeds, cross_task=True)
        out["sizes"][Path(size).stem] = {k: result.mean[k] for k in ("SUC", "COL")}
    return out


def build() -> str:
    """The build that plays the episodes: another one plays them slightly differently (docs/evaluation.md)."""
    import torch

    return f"python {platform.python_version()}, numpy {np.__version__}, torch {torch.__version__}"


def builds_line(cells: list[dict[str, Any]]) -> str:
    """One sentence naming the build(s) the cells were played with; more than one is a warning."""
    found = sorted({str(c.get("build", "not recorded")) for c in cells})
    if len(found) == 1:
        return f"Every cell was played with {found[0]}."
    return (
        f"**The cells come from {len(found)} builds** ({'; '.join(found)}): their numbers differ slightly "
        "from build to build, so compare learners played on one."
    )


def grid_learners(cells: Path, runs: Path, methods: list[str], tasks: list[str]) -> list[tuple[str, str, int, str]]:
    """(method, task, training seed, checkpoint) of every finished grid cell of these methods and tasks."""
    found = []
    for path in sorted(cells.glob("*.json")):
        record = json.loads(path.read_text())
        cell = record.get("cell", {})
        if cell.get("kind") == "method" and cell["method"] in methods and cell["task"] in tasks:
            found.append((cell["method"], cell["task"], int(cell["seed"]), str(runs / record["checkpoint"])))
    return found


def t_interval(diffs: list[float]) -> tuple[float, float, float] | None:
    """Mean of paired differences and its 95 % t-interval (n - 1 degrees of freedom); None under 2 values."""
    found = paired_t(diffs)
    return None if found["n"] < 2 else (found["diff"], *found["ci95"])


def _ci(found: tuple[float, float, float] | None) -> str:
    return "-" if found is None else f"{found[0]:+.1f} [{found[1]:+.1f}, {found[2]:+.1f}]"


def _mean_ci(values: list[float]) -> str:
    """``mean [low, high]``: the 95 % t-interval of the mean over seeds; ``over_seeds`` under two values."""
    found = t_interval(values)
    return over_seeds(values) if found is None else f"{found[0]:.1f} [{found[1]:.1f}, {found[2]:.1f}]"


def summarise(cells: list[dict[str, Any]]) -> dict[str, Any]:
    """Per (learner, task): seeds, protocol SUC/REC over seeds, the SUC each protocol costs (paired), splits,
    sizes; per (task, protocol): the method that loses least and its paired comparisons."""
    groups: dict[tuple[str, str], dict[int, dict[str, Any]]] = {}
    for c in cells:
        groups.setdefault((c["learner"], c["task"]), {})[c["seed"]] = c
    out: dict[str, Any] = {"learners": {}, "least_loss": {}, "builds": builds_line(cells)}
    loss: dict[tuple[str, str, str], dict[int, float]] = {}
    for (label, task), by_seed in sorted(groups.items()):
        seeds = sorted(by_seed)
        row: dict[str, Any] = {"seeds": seeds, "protocols": {}, "loss": {}, "splits": {}, "sizes": {}}
        for name in ("zoo3", *PROTOCOLS):
            row["protocols"][name] = {
                m: [by_seed[s]["protocols"][name].get(m, np.nan) for s in seeds] for m in ("SUC", "SUC_post", "REC")
            }
        for name in PROTOCOLS:
            lost = {s: by_seed[s]["protocols"]["zoo3"]["SUC"] - by_seed[s]["protocols"][name]["SUC"] for s in seeds}
            loss[(task, name, label)] = lost
            row["loss"][name] = {"per_seed": list(lost.values()), "t95": t_interval(list(lost.values()))}
        for k in by_seed[seeds[0]]["splits"]:
            row["splits"][k] = [by_seed[s]["splits"][k]["SUC"] for s in seeds]
        for size in by_seed[seeds[0]]["sizes"]:
            row["sizes"][size] = [by_seed[s]["sizes"][size]["SUC"] for s in seeds]
        out["learners"][f"{label}|{task}"] = row
    for task in sorted({t for t, _, _ in loss}):
        for name in PROTOCOLS:
            methods = {lab: v for (t, p, lab), v in loss.items() if t == task and p == name}
            if len(methods) < 2:
                continue
            best = min(methods, key=lambda lab: float(np.mean(list(methods[lab].values()))))
            versus = {}
            for other, lost in methods.items():
                if other == best:
                    continue
                common = sorted(set(lost) & set(methods[best]))
                found = t_interval([methods[best][s] - lost[s] for s in common])
                verdict = "undecided" if found is None or found[2] >= 0 else "less"
                versus[other] = {"diff_t95": found, "n": len(common), "verdict": verdict}
            out["least_loss"][f"{task}|{name}"] = {"method": best, "versus": versus}
    return out


def markdown(summary: dict[str, Any], episodes: int, split_episodes: int) -> str:
    rows = summary["learners"]
    played_with = summary.get("builds", "")
    lines = [
        "# Open teaming",
        "",
        f"Each learner with Zoo 3 alone and with its team-event protocols ({episodes} episodes each, evaluation "
        "seed 10,000 + the training seed); mean ± std (ddof 1) over the training seeds. SUC after: over the "
        "episodes that reached their first event. REC: steps from the event to the next capture. Re-run: "
        "`python benchmarks/protocol_report.py` (see its docstring). " + played_with,
        "",
        "| learner | task | seeds | "
        + " | ".join(f"SUC {p}" for p in ("zoo3", *PROTOCOLS))
        + " | "
        + " | ".join(f"REC {p}" for p in PROTOCOLS)
        + " |",
        "|" + " --- |" * (3 + 1 + 2 * len(PROTOCOLS)),
    ]
    for key, r in rows.items():
        label, task = key.split("|")
        suc = [over_seeds(r["protocols"][p]["SUC"]) for p in ("zoo3", *PROTOCOLS)]
        rec = [over_seeds(r["protocols"][p]["REC"]) for p in PROTOCOLS]
        lines.append(f"| {label} | {task} | {len(r['seeds'])} | " + " | ".join(suc + rec) + " |")
    lines += [
        "",
        "## Means with their intervals",
        "",
        "The same learners: mean over the training seeds [95 % t-interval, seeds - 1 degrees of freedom]. SUC after "
        "the event and REC per protocol.",
        "",
        "| learner | task | "
        + " | ".join(f"SUC after {p}" for p in PROTOCOLS)
        + " | "
        + " | ".join(f"REC {p}" for p in PROTOCOLS)
        + " |",
        "|" + " --- |" * (2 + 2 * len(PROTOCOLS)),
    ]
    for key, r in rows.items():
        label, task = key.split("|")
        cells = [_mean_ci(r["protocols"][p][m]) for m in ("SUC_post", "REC") for p in PROTOCOLS]
        lines.append(f"| {label} | {task} | " + " | ".join(cells) + " |")
    lines += [
        "",
        "## What a team change costs",
        "",
        "SUC with Zoo 3 alone minus SUC with the protocol, paired by training seed: mean [95 % t-interval].",
        "",
        "| learner | task | " + " | ".join(PROTOCOLS) + " |",
        "|" + " --- |" * (2 + len(PROTOCOLS)),
    ]
    for key, r in rows.items():
        label, task = key.split("|")
        losses = [r["loss"][p] for p in PROTOCOLS]
        cost = [_ci(lost["t95"]) if lost["t95"] else over_seeds(lost["per_seed"]) for lost in losses]
        lines.append(f"| {label} | {task} | " + " | ".join(cost) + " |")
    if summary["least_loss"]:
        lines += [
            "",
            "Which method loses least, per task and protocol; against each other method the difference of their "
            "losses (least - other, paired by seed) with its 95 % t-interval: *less* when the interval is below 0.",
            "",
            "| task | protocol | loses least | against the others |",
            "| --- | --- | --- | --- |",
        ]
        for key, found in summary["least_loss"].items():
            task, name = key.split("|")
            versus = "; ".join(
                f"{o}: {_ci(tuple(v['diff_t95']) if v['diff_t95'] else None)} {v['verdict']}"
                for o, v in found["versus"].items()
            )
            lines.append(f"| {task} | {name} | {found['method']} | {versus} |")
    lines += [
        "",
        f"## Every split of the team (Zoo 3, {split_episodes} episodes per seat assignment)",
        "",
        "| learner | task | SUC with k learners: k = 1, 2, 3 |",
        "| --- | --- | --- |",
    ]
    for key, r in rows.items():
        label, task = key.split("|")
        lines.append(f"| {label} | {task} | " + ", ".join(over_seeds(v) for v in r["splits"].values()) + " |")
    sizes = next(iter(rows.values()))["sizes"] if rows else {}
    lines += ["", "## Other team sizes (Zoo 1)", "", "| learner | task | " + " | ".join(sizes) + " |"]
    lines.append("|" + " --- |" * (2 + len(sizes)))
    for key, r in rows.items():
        label, task = key.split("|")
        lines.append(f"| {label} | {task} | " + " | ".join(over_seeds(v) for v in r["sizes"].values()) + " |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cells", type=Path, default=None, help="a benchmark's cell records (a results cells/ folder)")
    parser.add_argument("--runs", type=Path, default=Path("runs/benchmarks/paper_budget"), help="the grid's folder")
    parser.add_argument("--methods", nargs="*", default=["sp", "hola", "mappo", "naht_d"])
    parser.add_argument("--tasks", nargs="+", default=["4p2e1o", "4p2e5o"])
    parser.add_argument("--seeds", nargs="*", type=int, default=None, help="only these training seeds (default: all)")
    parser.add_argument("--learner", action="append", default=[], help="LABEL=POLICY, played on every task")
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--split-episodes", type=int, default=100)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/protocols"))
    args = parser.parse_args(argv)
    learners: list[tuple[str, str, int, str]] = []
    if args.cells is not None:
        learners += grid_learners(args.cells, args.runs, args.methods, args.tasks)
        if args.seeds is not None:  # one process per seed, side by side: each writes its own cells
            learners = [learner for learner in learners if learner[2] in args.seeds]
    for item in args.learner:
        label, _, name = item.partition("=")
        learners += [(label, task, 0, name.format(task=task)) for task in args.tasks]
    folder = args.out / "cells"
    folder.mkdir(parents=True, exist_ok=True)
    for label, task, seed, name in learners:
        path = folder / f"{label}-{task}-s{seed}.json"
        if path.exists():
            continue
        cell = {"learner": label, **play(name, task, seed, args.episodes, args.split_episodes)}
        atomic_write_text(path, json.dumps(cell, indent=1, default=float))
        print(f"{label} {task} s{seed}: SUC {cell['protocols']['zoo3']['SUC']:.1f} with zoo3", flush=True)
    cells = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))]
    summary = summarise(cells)
    atomic_write_text(args.out / "report.json", json.dumps(summary, indent=1, default=float))
    atomic_write_text(args.out / "report.md", markdown(summary, args.episodes, args.split_episodes))
    print((args.out / "report.md").read_text())


if __name__ == "__main__":
    main()
