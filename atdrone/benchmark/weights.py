"""The weights a benchmark keeps: per (method, task) the final learner of the seed that scored best on the
selection (validation) zoo, copied into the results folder with a manifest.

``<results>/weights/<method>/<task>.pt`` is the checkpoint (the project's format: JSON
header + tensors, digest-checked when loaded) and ``<task>.json`` its manifest: method,
task, seed, algorithm, member, the budget it was trained with, the sha256 of the file
(and of its tensors alone, ``weights_sha256``, which the header carries),
its metrics on every zoo and what it was chosen on. Only the selection zoo's scores
choose (SUC, then REW, then the lower seed), never a test zoo's. The manifest is
written after the file, so a manifest names a complete file. ``weights:METHOD/TASK``
(or ``weights:BENCHMARK/METHOD/TASK``) names it wherever a policy is named
(:mod:`atdrone.resolve`).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from typing import Any

from atdrone.benchmark.config import BenchmarkConfig
from atdrone.fileio import atomic_write_bytes
from atdrone.models.checkpoint import read_header
from atdrone.resolve import weights_checkpoint, weights_manifest
from atdrone.rundir import RunError


def choose(cfg: BenchmarkConfig, records: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The record of the run the selection zoo prefers among ``records`` (one method and task)."""
    zoo = cfg.select_zoo

    def key(rec: dict[str, Any]) -> tuple[float, float, int]:
        scores = rec["metrics"].get(zoo, {}) if zoo else {}
        return (scores.get("SUC", float("-inf")), scores.get("REW", float("-inf")), -int(rec["cell"]["seed"]))

    return max(records, key=key)


def keep_weights(cfg: BenchmarkConfig, records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Copy the chosen final learner of every (method, task) into the results folder; the manifests."""
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
            }
            text = json.dumps(manifest, indent=2, sort_keys=True)
            atomic_write_bytes(weights_manifest(cfg.results, method, task), text.encode())
            manifests.append(manifest)
    return manifests
