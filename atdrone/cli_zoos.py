"""``atdrone zoos``: the partner zoos per task, their trained drones and the manifest's versions."""

from __future__ import annotations

import argparse
import json
from typing import Any

from atdrone.errors import UserError


def add_zoos(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "zoos",
        help="the partner zoos and pools per task: members, trained drones, versions (the zoo manifest)",
        description="List every zoo (zoo1-zoo4, validation) and training pool per task: how many members, which "
        "trained drones are present or missing, and the version each task's zoos have in configs/zoos/manifest.json "
        "(every evaluation, registry row, MLflow run and benchmark cell records it). --write makes the manifest anew "
        "from the zoo documents and the checkpoint files; --check compares every listed file with its sha256.",
    )
    p.add_argument("--task", default=None, help="only this task")
    p.add_argument("--write", action="store_true", help="write configs/zoos/manifest.json anew")
    p.add_argument("--check", action="store_true", help="exit 1 when a listed checkpoint differs from the manifest")
    p.add_argument("--format", choices=("table", "json"), default="table", help="table (default) or json")
    return p


def run_zoos(args: argparse.Namespace) -> int:
    from atdrone.config import TASK_NAMES, repo_path
    from atdrone.policies.manifest import MANIFEST, build_manifest, file_sha256, load_manifest, write_manifest

    if args.task is not None and args.task not in TASK_NAMES:
        raise UserError(f"--task: no task {args.task!r} (tasks: {', '.join(TASK_NAMES)})")
    committed = load_manifest()
    manifest = write_manifest() if args.write else build_manifest()
    tasks = [args.task] if args.task else list(TASK_NAMES)
    if args.format == "json":
        print(json.dumps({t: manifest["tasks"][t] for t in tasks}, indent=1))
    else:
        print(f"{'task':8} {'set':11} {'members':>7} {'trained':>7} {'missing':>7}  version")
        for task in tasks:
            section = manifest["tasks"][task]
            for name, members in section["sets"].items():
                trained = [m for m in members if m["kind"] == "checkpoint"]
                missing = [m["name"] for m in trained if m.get("missing")]
                print(
                    f"{task:8} {name:11} {len(members):7d} {len(trained) - len(missing):7d} {len(missing):7d}  "
                    f"{section['version']}" + (f"  (missing: {', '.join(missing)})" if missing else "")
                )
    if args.write:
        print(f"wrote {MANIFEST} (version {manifest['version']})")
    elif committed is None or committed["version"] != manifest["version"]:
        print(f"note: {MANIFEST} is not up to date with the files: `atdrone zoos --write` makes it anew")
    if args.check:
        bad = []
        for task in tasks:
            for members in (committed or manifest)["tasks"][task]["sets"].values():
                for m in members:
                    path = repo_path(m["checkpoint"]) if "sha256" in m else None
                    if path is not None and (not path.is_file() or file_sha256(path) != m["sha256"]):
                        bad.append(m["checkpoint"])
        if bad:
            print(f"differ from {MANIFEST}: {', '.join(sorted(set(bad)))}")
            return 1
        print("every listed checkpoint matches the manifest")
    return 0
