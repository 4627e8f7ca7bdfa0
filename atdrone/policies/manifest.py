"""The zoo manifest: every partner drone of every zoo, pool and the validation zoo, per task.

configs/zoos/manifest.json lists, per paper task, each member of Zoos 1-4, the
validation zoo and the training pools: a rule-based drone by kind and full parameters,
a trained drone by checkpoint path, file sha256, the task its header names and the
recipe that made it. The version of a task's zoos is a digest of that task's section:
every evaluation, registry row, MLflow run and benchmark cell records it, so results
measured with other partners are never mixed. A checkpoint the manifest lists is
refused when its bytes no longer match (:func:`check_digest`).

``atdrone zoos --write`` writes the manifest anew from the documents and files.
"""

from __future__ import annotations

import hashlib
import inspect
import json
from functools import lru_cache
from pathlib import Path
from typing import Any

from atdrone.config import TASK_NAMES, read_document, repo_path
from atdrone.policies.base import PolicyError

MANIFEST = "configs/zoos/manifest.json"
TASK_FIELD = "{task}"  # in a checkpoint path: the task the zoo is played on
FORMAT = 1
ZOOS = ("zoo1", "zoo2", "zoo3", "zoo4", "validation")
POOLS = ("train_pool",)


class ManifestError(PolicyError):
    """A checkpoint differs from the zoo manifest, or the manifest cannot be read."""


def rule_params(kind: str, params: dict[str, float]) -> dict[str, float]:
    """A rule-based drone's full parameters: its constructor's defaults overlaid with ``params``."""
    from atdrone.policies.rules import GreedyPolicy, VicsekPolicy

    rules: dict[str, type] = {"greedy": GreedyPolicy, "vicsek": VicsekPolicy}
    defaults = {
        k: p.default
        for k, p in inspect.signature(rules[kind]).parameters.items()
        if p.default is not inspect.Parameter.empty
    }
    return {k: float(v) for k, v in {**defaults, **params}.items()}


def file_sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def digest(section: Any) -> str:
    """A short stable digest of JSON data (sorted keys, no spaces): ``zv-`` and 16 hex digits."""
    text = json.dumps(section, sort_keys=True, separators=(",", ":"))
    return "zv-" + hashlib.sha256(text.encode()).hexdigest()[:16]


def _header(path: Path) -> dict[str, Any]:
    from atdrone.models.checkpoint import read_header

    return read_header(path)


def member_entry(member: dict[str, Any], task: str) -> dict[str, Any]:
    """One member of a zoo document as the manifest holds it on ``task``."""
    kind = member["kind"]
    entry: dict[str, Any] = {"name": member["name"], "kind": kind}
    if kind != "checkpoint":
        entry["params"] = rule_params(kind, member.get("params", {}))
        return entry
    cross = member.get("cross_task", "")
    rel = str(member["checkpoint"]).replace(TASK_FIELD, cross or task)
    entry["checkpoint"] = rel
    if cross:
        entry["cross_task"] = cross
    path = repo_path(rel)
    if not path.is_file():
        entry["missing"] = True
        return entry
    head = _header(path)
    config = head.get("config", {})
    entry.update(
        sha256=file_sha256(path),
        trained_on=head.get("task", ""),
        recipe=f"configs/train/{config.get('name', head.get('name', ''))}.json",
        seed=head.get("seed"),
        env_steps=head.get("step"),
        stop_at_suc=config.get("stop_at_suc"),
        last_eval_SUC=head.get("metrics", {}).get("eval/SUC"),
    )
    return entry


def build_manifest() -> dict[str, Any]:
    """The manifest of the committed zoo and pool documents and the checkpoint files on disk."""
    tasks: dict[str, Any] = {}
    for task in TASK_NAMES:
        section: dict[str, Any] = {}
        for kind, names in (("zoos", ZOOS), ("pools", POOLS)):
            for name in names:
                doc = read_document(name, kind, (name,))
                section[name] = [member_entry(m, task) for m in doc["members"]]
        tasks[task] = {"version": digest(section), "sets": section}
    return {"format": FORMAT, "version": digest({t: s["version"] for t, s in tasks.items()}), "tasks": tasks}


def write_manifest(path: Path | None = None) -> dict[str, Any]:
    """Write the manifest (atomically) and return it."""
    from atdrone.fileio import atomic_write_bytes

    manifest = build_manifest()
    atomic_write_bytes(path or repo_path(MANIFEST), (json.dumps(manifest, indent=1) + "\n").encode())
    _load.cache_clear()
    return manifest


@lru_cache(maxsize=4)
def _load(path: str, mtime_ns: int) -> dict[str, Any]:
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ManifestError(f"cannot read the zoo manifest {path}: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise ManifestError(f"{path}: not a zoo manifest of format {FORMAT}")
    return doc


def load_manifest() -> dict[str, Any] | None:
    """The committed manifest, or None when there is none."""
    path = repo_path(MANIFEST)
    if not path.is_file():
        return None
    return _load(str(path), path.stat().st_mtime_ns)


def task_version(task: str) -> str:
    """The version of ``task``'s zoos in the manifest ("" when the manifest does not hold the task)."""
    manifest = load_manifest()
    if manifest is None or task not in manifest["tasks"]:
        return ""
    return str(manifest["tasks"][task]["version"])


def digests() -> dict[str, str]:
    """Repository-relative checkpoint path -> the manifest's sha256, for every listed checkpoint."""
    manifest = load_manifest()
    found: dict[str, str] = {}
    for section in (manifest or {}).get("tasks", {}).values():
        for members in section["sets"].values():
            for m in members:
                if "sha256" in m:
                    found[str(repo_path(m["checkpoint"]).resolve())] = m["sha256"]
    return found


def check_digest(path: Path) -> None:
    """ManifestError when the manifest lists ``path`` and the file's sha256 is another."""
    expected = digests().get(str(path.resolve()))
    if expected is None or not path.is_file():
        return
    actual = file_sha256(path)
    if actual != expected:
        raise ManifestError(
            f"{path}: sha256 {actual[:12]}... differs from the zoo manifest's {expected[:12]}... ({MANIFEST}); "
            "a changed drone is a new zoo version: run `atdrone zoos --write` and re-run what used it"
        )
