"""The weights a benchmark keeps: per (method, task) the final learner of the seed that scored best on the
selection (validation) zoo, copied into the results folder with a manifest.

``<results>/weights/<method>/<task>.pt`` is the checkpoint (the project's format: JSON
header + tensors, digest-checked when loaded) and ``<task>.json`` its manifest: method,
task, seed, algorithm, member, the budget it was trained with, the sha256 of the file
(and of its tensors alone, ``weights_sha256``, which the header carries),
its metrics on every zoo with the float kernels that measured them (``measured_on``: the host writing it, which
plays them again where its cell was evaluated elsewhere) and what it was chosen on; as a model card also the PPO
setting, the zoo version of its task, 95 % intervals over the evaluation episodes (SUC and COL,
Wilson's) and the commands that reproduce it, written out as ``<task>.md``. A smoke
test's weights say so (``smoke_test``). Only the selection zoo's scores
choose (SUC, then REW, then the lower seed), never a test zoo's. The manifest is
written after the file, so a manifest names a complete file. ``weights:METHOD/TASK``
(or ``weights:BENCHMARK/METHOD/TASK``) names it wherever a policy is named
(:mod:`atdrone.resolve`).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from atdrone.benchmark.config import BenchmarkConfig
from atdrone.fileio import atomic_write_bytes
from atdrone.models.checkpoint import read_header
from atdrone.resolve import weights_checkpoint, weights_manifest
from atdrone.rundir import RunError

REPO = Path(__file__).resolve().parents[2]  # a manifest's ``zoo_documents`` are relative to it


def choose(cfg: BenchmarkConfig, records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The record of the run the selection zoo prefers among ``records`` (one method and task)."""
    zoo = cfg.select_zoo

    def key(rec: dict[str, Any]) -> tuple[float, float, int]:
        scores = rec["metrics"].get(zoo, {}) if zoo else {}
        return (scores.get("SUC", float("-inf")), scores.get("REW", float("-inf")), -int(rec["cell"]["seed"]))

    return max(records, key=key)


def keep_weights(
    cfg: BenchmarkConfig, records: Sequence[dict[str, Any]], say: Callable[[str], None] | None = None
) -> list[dict[str, Any]]:
    """Copy the chosen final learner of every (method, task) into the results folder; the manifests.

    A card's metrics are those its weight plays on the host that writes it: a chosen cell evaluated on other float
    kernels (or on kernels its record does not name) is played again here on every zoo of its record, as its cell
    played it (:func:`play_as_cell`), and its record's metrics, those of the report, are kept as ``cell_metrics``.
    ``say`` hears a line per weight played again."""
    from atdrone.hostinfo import float_kernels

    here = float_kernels()
    manifests = []
    for method in cfg.methods:
        for task in cfg.tasks:
            runs = [r for r in records if r["cell"]["kind"] == "method" and r["cell"]["method"] == method]
            runs = [r for r in runs if r["cell"]["task"] == task]
            if not runs:
                continue
            best = choose(cfg, runs)
            data = (cfg.folder / best["checkpoint"]).read_bytes()
            digest = hashlib.sha256(data).hexdigest()
            if digest != best["sha256"]:
                raise RunError(f"{best['checkpoint']} changed since its cell was evaluated (sha256 {digest})")
            atomic_write_bytes(weights_checkpoint(cfg.results, method, task), data)
            zoo = cfg.select_zoo
            manifest = {
                "benchmark": cfg.name,
                "method": method,
                "task": task,
                "seed": best["cell"]["seed"],
                "algorithm": best["algorithm"],
                "member": best["member"],
                "file": f"{task}.pt",
                "sha256": digest,
                "weights_sha256": read_header(cfg.folder / best["checkpoint"])["sha256"],
                "selected_on": {"zoo": zoo, **({k: best["metrics"][zoo][k] for k in ("SUC", "REW")} if zoo else {})},
                "budget": {**best["budget"], "env_steps_planned": cfg.env_steps},
                "metrics": best["metrics"],
                "measured_on": best.get("timing", {}).get("machine"),  # None: a record that does not name it
            }
            if manifest["measured_on"] != here:  # the card's metrics as this host plays them, bit for bit
                if say is not None:
                    say(f"weights {method}/{task}: seed {best['cell']['seed']} measured elsewhere, played again here")
                seed, path = int(best["cell"]["seed"]), cfg.folder / best["checkpoint"]
                played = {z: play_as_cell(path, task, z, seed, cfg.eval_episodes) for z in best["metrics"]}
                cell = {"cell_metrics": best["metrics"], "cell_measured_on": manifest["measured_on"]}
                manifest.update(metrics=played, measured_on=here, **cell)
            manifest.update(card(cfg, method, best, manifest["metrics"]))
            text = json.dumps(manifest, indent=2, sort_keys=True)
            atomic_write_bytes(weights_manifest(cfg.results, method, task), text.encode())
            card_path = weights_manifest(cfg.results, method, task).with_suffix(".md")
            atomic_write_bytes(card_path, card_text(manifest).encode())
            manifests.append(manifest)
    return manifests


def card(
    cfg: BenchmarkConfig, method: str, best: dict[str, Any], metrics: Mapping[str, Mapping[str, float]]
) -> dict[str, Any]:
    """The model card's fields beyond the manifest: setting, partners, intervals of ``metrics``, how to
    reproduce."""
    from atdrone.benchmark.cells import EVAL_SEED
    from atdrone.teams.evaluation import wilson_interval

    n = cfg.eval_episodes
    seed, task = int(best["cell"]["seed"]), str(best["cell"]["task"])
    intervals = {
        zoo: {m: list(wilson_interval(round(values[m] * n / 100.0), n)) for m in ("SUC", "COL") if m in values}
        for zoo, values in metrics.items()
    }
    zoos = ",".join(metrics)
    return {
        "smoke_test": bool(getattr(cfg, "smoke_test", False)),
        "ppo": cfg.experiment.get("ppo", {}),
        "zoo_version": best.get("zoo_version", ""),
        "eval_episodes": n,
        "eval_seed": EVAL_SEED + seed,
        "metrics_ci95": intervals,
        "reproduce": {
            "train": f"atdrone benchmark {cfg.name}  (cell {best['name']})",
            "evaluate": f"atdrone evaluate --policy weights:{cfg.name}/{method}/{task} --task {task} --zoo ZOO "
            f"--episodes {n} --seeds {EVAL_SEED + seed}   (ZOO one of {zoos})",
        },
    }


def card_text(m: dict[str, Any]) -> str:
    """The model card as Markdown."""
    lines = [
        f"# {m['method']} on {m['task']} ({m['benchmark']} benchmark)",
        "",
        "**A smoke test: these weights rank nothing.**" if m.get("smoke_test") else "",
        f"Load it as `weights:{m['method']}/{m['task']}` (or `weights:{m['benchmark']}/{m['method']}/{m['task']}`).",
        "",
        f"- member {m['member']} of seed {m['seed']} ({m['algorithm']}), chosen on the {m['selected_on'].get('zoo')} "
        "zoo among the benchmark's seeds (never on a test zoo)",
        f"- budget: {m['budget'].get('env_steps', 0):,} env steps "
        f"(planned {m['budget'].get('env_steps_planned', 0):,})",
        f"- PPO: {json.dumps(m.get('ppo', {}), sort_keys=True)}",
        f"- partners: zoo version {m.get('zoo_version') or 'unrecorded'}; file sha256 {m['sha256']}",
        f"- measured on: {_machine_text(m.get('measured_on'))}",
        *([_cell_text(m)] if "cell_metrics" in m else []),
        "",
        f"Evaluated with {m['eval_episodes']} episodes per zoo (evaluation seed {m['eval_seed']}); "
        "intervals over the episodes:",
        "",
        "| zoo | SUC % [95 % CI] | COL % [95 % CI] | AST | REW |",
        "|---|---|---|---|---|",
    ]
    for zoo, v in m["metrics"].items():
        ci = m["metrics_ci95"].get(zoo, {})

        def cell(metric: str, v: dict[str, float] = v, ci: dict[str, list[float]] = ci) -> str:
            low, high = ci.get(metric, [float("nan")] * 2)
            return f"{v[metric]:.1f} [{low:.1f}, {high:.1f}]"

        lines.append(f"| {zoo} | {cell('SUC')} | {cell('COL')} | {v['AST']:.1f} | {v['REW']:.2f} |")
    lines += ["", "Reproduce:", "", f"    {m['reproduce']['train']}", f"    {m['reproduce']['evaluate']}", ""]
    return "\n".join(lines)


def _machine_text(machine: dict[str, str] | None) -> str:
    if not machine:
        return "a host its record does not name (elsewhere, the metrics replay within their intervals)"
    return "; ".join(f"{k} {v}" for k, v in machine.items()) + " (they replay bit for bit on a host with these)"


def _cell_text(m: dict[str, Any]) -> str:
    """The line that says where the report's numbers of this seed came from (the card's were played again)."""
    diffs = [abs(m["cell_metrics"][z][k] - v) for z, vs in m["metrics"].items() for k, v in vs.items() if k != "AST"]
    most = max(diffs, default=0.0)
    differ = f"differ from them by at most {most:.3g}" if most else "equal them to the last bit"
    return (
        f"- the report's numbers for this seed were measured on {_machine_text(m.get('cell_measured_on'))}; "
        f"played again here, SUC, COL and REW {differ}"
    )


def replay(manifest: Mapping[str, Any], zoo: str, episodes: int) -> dict[str, float]:
    """``manifest``'s weight played again on ``zoo`` with the episodes its benchmark played (its evaluation
    seed, ``episodes`` episodes): SUC, COL, AST and REW, to compare with its metrics."""
    name = f"weights:{manifest['benchmark']}/{manifest['method']}/{manifest['task']}"
    # weights measured before the zoos were made per task name the documents of the partners they played
    docs = manifest.get("zoo_documents")
    played: str | Path = REPO / str(docs) / f"{zoo}.json" if docs else zoo
    return play_as_cell(name, str(manifest["task"]), played, int(manifest["seed"]), episodes)


def play_as_cell(policy: str | Path, task: str, zoo: str | Path, seed: int, episodes: int) -> dict[str, float]:
    """The metrics of ``policy`` (any name :mod:`atdrone.resolve` knows) on ``zoo`` as a benchmark cell of seed
    ``seed`` evaluates it: ``episodes`` episodes of its evaluation seed, on one torch thread."""
    import torch

    from atdrone.benchmark.cells import EVAL_SEED
    from atdrone.resolve import resolve_policy
    from atdrone.teams.evaluation import evaluate

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        result = evaluate(resolve_policy(policy), task, zoo, episodes=episodes, seeds=[EVAL_SEED + seed])
    finally:
        torch.set_num_threads(threads)
    return {k: float(v) for k, v in result.mean.items()}
