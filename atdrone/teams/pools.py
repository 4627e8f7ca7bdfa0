"""Training pools: named sets of partners to train with, kept apart from the evaluation zoos.

A pool document (configs/pools/<name>.json) has the zoo document's format
(:mod:`atdrone.policies.zoo`): rule-based drones with their parameters and trained
drones as checkpoint files. Teammate-modelling learners (MAPPO, NAHT-D) and FCP train
against a pool, partners drawn per environment and per episode, slots shuffled. A
result counts as one with *unseen* partners only when no pool member is an evaluation
partner: :func:`shared_members` finds members that are the same drone as a member of
Zoos 1-3 (the same rule with the same parameters, defaults filled in, or a checkpoint
with the same weights digest), and :func:`check_pool` refuses such a pool unless the
config says it trains a best response on purpose.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from atdrone.config import CONFIG_DIR, TASK_NAMES, ConfigError, read_document
from atdrone.errors import UserError
from atdrone.policies.manifest import rule_params
from atdrone.policies.zoo import RULES, ZOO_NAMES, MemberSpec, Zoo, checkpoint_path, load_zoo

BEST_RESPONSE_LABEL = "best response (the training pool shares partners with the evaluation zoos)"
UNSEEN_LABEL = "unseen partners"


def pool_names() -> tuple[str, ...]:
    """The pools shipped in configs/pools/."""
    return tuple(sorted(p.stem for p in (CONFIG_DIR / "pools").glob("*.json")))


def pool_path(name_or_path: str | Path) -> str:
    """The document path of a pool given by name (configs/pools/<name>.json) or path."""
    text = str(name_or_path)
    return str(CONFIG_DIR / "pools" / f"{text}.json") if text in pool_names() else text


def load_pool(name_or_path: str | Path) -> Zoo:
    """A training pool by name (configs/pools/<name>.json) or path; ConfigError when invalid."""
    return load_zoo(read_document(name_or_path, "pools", pool_names()))


def identity(spec: MemberSpec) -> str:
    """What makes two members the same drone: a rule with its full parameters, or a checkpoint's weights."""
    if spec.kind in RULES:
        return f"{spec.kind}:{json.dumps(rule_params(spec.kind, spec.params), sort_keys=True)}"
    path = checkpoint_path(spec)
    if path.is_file():
        from atdrone.models.checkpoint import read_header  # torch, only for checkpoint members

        return f"weights:{read_header(path)['sha256']}"
    return f"file:{path.resolve()}"


def shared_members(pool: Zoo, zoos: Sequence[str] = ZOO_NAMES) -> list[str]:
    """ "pool member = zoo:member" for every pool member that is also a member of one of ``zoos``: the same rule
    drone, or the same weights (or file) on some task (drones made per task are compared task by task)."""
    tasks = [pool.task] if pool.task else list(TASK_NAMES)
    shared: dict[str, set[str]] = {}
    for task in tasks:
        seen: dict[str, list[str]] = {}
        for zoo_name in zoos:
            zoo = load_zoo(zoo_name, task)
            for spec in zoo.spec.members:
                seen.setdefault(identity(spec), []).append(f"{zoo.name}:{spec.name}")
        for m in pool.resolve(task).spec.members:
            if identity(m) in seen:
                shared.setdefault(m.name, set()).update(seen[identity(m)])
    return [f"{m.name} = {', '.join(sorted(shared[m.name]))}" for m in pool.spec.members if m.name in shared]


def check_pool(name_or_path: str, best_response: bool, path: str, task: str | None = None) -> Zoo:
    """The pool, refused (ConfigError at ``path``) when it shares a member with Zoos 1-3 unless ``best_response``.

    With ``task`` every member is built on that task (a pool of drones per task is checked only then).
    """
    try:
        pool = load_pool(name_or_path)
        if task is not None:
            pool.resolve(task).check()
        elif not pool.per_task:
            pool.check()
    except ConfigError as exc:  # the document's own field, when it names one
        where = "" if exc.path == "<root>" else f"{exc.path}: "
        raise ConfigError(path, where + str(exc).split(": ", 1)[1]) from None
    except UserError as exc:  # a missing or damaged checkpoint: PolicyError's one line
        raise ConfigError(path, str(exc)) from None
    shared = shared_members(pool)
    if shared and not best_response:
        raise ConfigError(
            path,
            f"training pool {pool.name!r} shares members with the evaluation zoos ({'; '.join(shared)}): "
            'its results would not be unseen-partner results; use another pool, or set "best_response": true',
        )
    return pool


def result_label(best_response: bool) -> str:
    """How registry rows, MLflow runs and reports name a result trained against a pool."""
    return BEST_RESPONSE_LABEL if best_response else UNSEEN_LABEL


def pool_document(name: str, members: Sequence[tuple[str, str]], description: str) -> dict[str, Any]:
    """A pool document of checkpoint members ((name, checkpoint path) pairs), e.g. FCP's frozen partners."""
    return {
        "name": name,
        "description": description,
        "members": [{"name": n, "kind": "checkpoint", "checkpoint": c} for n, c in members],
    }
