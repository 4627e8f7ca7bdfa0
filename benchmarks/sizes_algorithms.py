"""HOLA-Drone V2 and NAHT-D trained at drawn team sizes on the population service: what each rollout and episode
played, and how the final learner flies in teams of 3 to 6.

    python benchmarks/sizes_algorithms.py [--algorithms hola naht_d] [--episodes 200] [--out-dir DIR]
        [--tracking-uri URI] [--report-only]

Each algorithm's quick experiment (``configs/experiments/<algorithm>_quick.json``: 4p2e1o, 4 generations of 12
updates on 2 rollout workers) with protocol ``sizes3-6`` runs on a local Ray, tracked in MLflow (``--out-dir``
holds the runs and ``mlflow.db``; a finished run is not run again). The report counts, from each learner's
MLflow run, the team sizes of its updates (``train/team_size``, each update's mean pursuers per sample) and the
partners of its training episodes (``training.json``'s drawn teams); for HOLA-Drone V2 it checks every drawn
team against the profiles the coordinator sampled that generation (``hypergraph.json``): a team of another size
holds one profile's members alone. NAHT-D's decoder loss per update comes from the same runs. The final learner
plays ``--episodes`` episodes with Zoo 1 (rule-based drones, which fly in any team size) in teams of 3 to 6,
evaluation seed 0. One seed at the quick budget: this shows the training path end to end, it is no comparison
of methods. Writes report.md and report.json in benchmarks/results/sizes_algorithms/.
"""

from __future__ import annotations

import argparse
import json
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
from events_training import write_json  # shared
from sizes_training import SIZES, size_task

from atdrone.config import CONFIG_DIR

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "benchmarks" / "results" / "sizes_algorithms"
TASK = "4p2e1o"


def experiment(algorithm: str, out_dir: Path) -> Any:
    from atdrone.service.experiment import load_experiment

    doc = json.loads((CONFIG_DIR / "experiments" / f"{algorithm}_quick.json").read_text())
    doc.update(name=f"{algorithm}_quick_sizes", protocol="sizes3-6", out_dir=str(out_dir), gif=False)
    return load_experiment(doc)


def fits_a_profile(team: list[str], profiles: list[list[str]]) -> bool:
    """Whether a drawn team is one profile's members alone: a subset of it (fewer slots), the profile itself, or
    the profile plus extra slots of its own members (more slots)."""
    for profile in profiles:
        have, want = Counter(team), Counter(profile)
        if len(team) <= len(profile) and not have - want:
            return True
        if len(team) > len(profile) and not want - have and set(team) <= set(profile):
            return True
    return False


def learner_runs(uri: str, name: str) -> list[dict[str, Any]]:
    """Each learner's MLflow run: its member, generation, update team sizes (an update played at the task's size
    alone logs none), decoder losses and drawn teams."""
    import mlflow

    client = mlflow.MlflowClient(uri)
    exp = client.get_experiment_by_name(name)
    if exp is None:
        raise SystemExit(f"no MLflow experiment {name!r} in {uri}")
    out = []
    for run in client.search_runs([exp.experiment_id]):
        member = run.data.tags.get("atdrone.member")
        if not member:
            continue
        history = {
            key: {m.step: m.value for m in client.get_metric_history(run.info.run_id, key)}
            for key in ("train/policy_loss", "train/team_size", "train/decoder_loss")
        }
        steps = sorted(history["train/policy_loss"])
        pursuers = int(TASK.split("p", 1)[0])
        with tempfile.TemporaryDirectory() as tmp:
            training = json.loads(Path(client.download_artifacts(run.info.run_id, "training.json", tmp)).read_text())
        out.append(
            {
                "member": member,
                "generation": int(run.data.tags["atdrone.generation"]),
                "team_size": [history["train/team_size"].get(i, pursuers) for i in steps],
                "decoder_loss": [history["train/decoder_loss"][i] for i in steps if i in history["train/decoder_loss"]],
                "drawn": training["drawn"],
            }
        )
    return sorted(out, key=lambda r: (r["generation"], r["member"]))


def summarise(algorithm: str, run_dir: Path, runs: list[dict[str, Any]]) -> dict[str, Any]:
    """What the learners' training played: updates by mean team size, episodes by partner count, profile fits."""
    sizes = [s for r in runs for s in r["team_size"]]
    partners: Counter[int] = Counter()
    fits = [0, 0]  # episodes whose team fits a profile of its generation, episodes checked
    for r in runs:
        profiles = None
        if algorithm.startswith("hola"):
            graph = run_dir / "generations" / f"{r['generation']:03d}" / "hypergraph.json"
            if graph.is_file():
                profiles = [p.split("|") for p in json.loads(graph.read_text())["profiles"]]
        for team, n in r["drawn"].items():
            members = team.split("|")
            partners[len(members)] += n
            if profiles is not None:
                fits[0] += n * fits_a_profile(members, profiles)
                fits[1] += n
    losses = [x for r in runs for x in r["decoder_loss"]]
    return {
        "learners": len(runs),
        "updates": len(sizes),
        "team_size": {"mean": float(np.mean(sizes)), "min": float(min(sizes)), "max": float(max(sizes))},
        "updates_by_team_size": dict(sorted(Counter(f"{s:.1f}" for s in sizes).items())),
        "episodes_by_partners": {str(k): v for k, v in sorted(partners.items())},
        "profile_fits": {"episodes": fits[1], "fit": fits[0]} if fits[1] else None,
        "decoder_loss": {"min": min(losses), "max": max(losses), "updates": len(losses)} if losses else None,
    }


def evaluate_sizes(checkpoint: Path, episodes: int) -> dict[str, dict[str, float]]:
    from atdrone.policies.zoo import load_checkpoint
    from atdrone.teams.evaluation import evaluate

    policy = load_checkpoint(checkpoint)
    out = {}
    for p in SIZES:
        played = size_task(TASK, p)
        result = evaluate(
            policy,
            str(CONFIG_DIR / "tasks" / f"{played}.json"),
            "zoo1",
            episodes=episodes,
            seeds=[0],
            cross_task=p != 4,
        )
        out[played] = {k: float(result.mean[k]) for k in ("SUC", "COL", "AST")}
        print(f"[sizes] {checkpoint.stem} {played}: SUC {out[played]['SUC']:.1f}", flush=True)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algorithms", nargs="+", default=["hola", "naht_d"])
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--out-dir", type=Path, default=ROOT / "runs_partners" / "sizes_algorithms")
    parser.add_argument("--tracking-uri", help="MLflow tracking URI (default: mlflow.db in --out-dir)")
    parser.add_argument("--report-only", action="store_true", help="rebuild the report from report.json")
    args = parser.parse_args()
    if not args.report_only:
        from atdrone.benchmark.cells import final_member, sha256_file, training_wall
        from atdrone.service.driver import run_experiment

        uri = args.tracking_uri or f"sqlite:///{(args.out_dir / 'mlflow.db').resolve()}"
        path = OUT / "report.json"
        before = json.loads(path.read_text())["algorithms"] if path.is_file() else {}
        doc: dict[str, Any] = {"task": TASK, "episodes": args.episodes, "algorithms": {}}
        for algorithm in args.algorithms:
            cfg = experiment(algorithm, args.out_dir)
            run_experiment(cfg, resume=True, tracking_uri=uri)
            run_dir = args.out_dir / cfg.name
            member = final_member(run_dir, algorithm)
            checkpoint = run_dir / "members" / f"{member}.pt"
            old = before.get(algorithm, {})
            same = old.get("sha256") == sha256_file(checkpoint) and doc["episodes"] == old.get("episodes")
            doc["algorithms"][algorithm] = {
                "run": cfg.name,
                "final_member": member,
                "sha256": sha256_file(checkpoint),
                "episodes": args.episodes,
                "training": summarise(algorithm, run_dir, learner_runs(uri, cfg.name)),
                "train_wall_s": round(training_wall(run_dir, "registry.db"), 1),
                "zoo1": old["zoo1"] if same else evaluate_sizes(checkpoint, args.episodes),  # evaluated once
            }
        write_json(OUT / "report.json", doc)
    doc = json.loads((OUT / "report.json").read_text())
    (OUT / "report.md").write_text(report(doc))
    print((OUT / "report.md").read_text())


def report(doc: dict[str, Any]) -> str:
    md = [
        "# HOLA-Drone V2 and NAHT-D trained at drawn team sizes",
        "",
        f"Each algorithm's quick experiment on {doc['task']} (`configs/experiments/<algorithm>_quick.json`, one "
        "seed) with protocol `sizes3-6`, on the population service. Training: what the learners' updates and "
        "episodes played, from their MLflow runs. Zoo 1: the final learner with Zoo 1's rule-based drones in teams "
        f"of 3 to 6, {doc['episodes']} episodes each (evaluation seed 0). One seed at the quick budget: the "
        "training path end to end, not a comparison. Re-run: `python benchmarks/sizes_algorithms.py`.",
        "",
    ]
    for algorithm, a in doc["algorithms"].items():
        t = a["training"]
        md += [
            f"## {algorithm}",
            "",
            f"- {t['learners']} learners, {t['updates']} updates; mean pursuers per sample "
            f"{t['team_size']['mean']:.2f} (updates from {t['team_size']['min']:.1f} to {t['team_size']['max']:.1f})",
            "- training episodes by number of partners: "
            + ", ".join(f"{v} with {k}" for k, v in t["episodes_by_partners"].items()),
            f"- training wall time {a['train_wall_s'] / 60:.1f} min (2 rollout workers, beside other work)",
        ]
        if t["profile_fits"]:
            f = t["profile_fits"]
            md.append(f"- episodes whose team is one sampled profile's members alone: {f['fit']} of {f['episodes']}")
        if t["decoder_loss"]:
            d = t["decoder_loss"]
            md.append(f"- decoder loss: finite at all {d['updates']} updates, from {d['min']:.3f} to {d['max']:.3f}")
        md += [
            "",
            f"Final learner `{a['final_member']}` with Zoo 1:",
            "",
            "| team | SUC | COL | AST |",
            "|---|---|---|---|",
        ]
        md += [f"| {p} | {m['SUC']:.1f} | {m['COL']:.1f} | {m['AST']:.1f} |" for p, m in a["zoo1"].items()]
        md.append("")
    return "\n".join(md)


if __name__ == "__main__":
    main()
