"""Which policy a name means: the one answer for every command that takes a policy.

A name is tried as, in this order:

1. a rule drone: ``greedy``, ``vicsek``;
2. a registered MLflow model: ``models:/NAME@ALIAS`` or ``models:/NAME/VERSION`` (its
   checkpoint is downloaded from the tracking store, and the registry member with the
   same checkpoint digest is found when a registry has it); or a benchmark's kept weights:
   ``weights:METHOD/TASK`` or ``weights:BENCHMARK/METHOD/TASK`` (``weights/<method>/<task>.pt``
   and its manifest in a benchmark's results folder: those of ``$ATDRONE_WEIGHTS``, folders
   separated by ``os.pathsep``, else every ``benchmarks/results/*`` (the published ones) and
   ``runs/benchmarks/*/results/*`` (a benchmark's own); the file's sha256 must match the
   manifest's);
3. a checkpoint file (a path that exists);
4. a member id of a population registry (``hola-g3-0``): ``--db`` when given, else every
   registry under the runs folder (``runs/*/registry.db``). Every run numbers its members
   the same way, so an id held by several runs is named with its run, ``hola_quick/hola-g3-0``
   (or ``--run hola_quick``); the short id is enough where one run has it;
5. a zoo member: ``ZOO:MEMBER`` (``zoo1:greedy``) or a member name of the shipped zoos; a drone
   trained per task names its task, ``zoo2:sp_high@4p2e5o``.

:func:`resolve` returns a :class:`Resolved` (what the name was found as, its checkpoint
file, the registry member when there is one); :meth:`Resolved.policy` loads it. A name
that matches nothing raises :class:`PolicyNotFound`, one line that lists every reading
tried and why it failed. ``atdrone evaluate``, ``render`` and ``registry show`` call it;
so can the deploy job (:func:`resolve_checkpoint`).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from atdrone.config import ConfigError
from atdrone.fileio import user_cache
from atdrone.policies.base import Policy, PolicyError
from atdrone.policies.zoo import (
    RULES,
    TASK_FIELD,
    ZOO_NAMES,
    MemberSpec,
    build_policy,
    checkpoint_path,
    load_checkpoint,
    load_zoo,
)
from atdrone.registry import DEFAULT_PATH, ENV_VAR, Registry, RegistryError

__all__ = ["PolicyNotFound", "Resolved", "resolve", "resolve_checkpoint", "resolve_policy"]

MODEL_PREFIX = "models:/"
WEIGHTS_PREFIX = "weights:"
_WEIGHTS_PART = re.compile(r"[A-Za-z0-9_.-]+")  # a benchmark, method or task name: never a path
WEIGHTS_ENV = "ATDRONE_WEIGHTS"
REGISTRY_GLOB = "*/registry.db"


class PolicyNotFound(PolicyError):
    """No reading of a policy name matched; the message lists what was tried."""


@dataclass(frozen=True)
class Resolved:
    """What a policy name was found as.

    ``kind`` is one of rule, model, weights, checkpoint, member, zoo; ``checkpoint`` is the file
    behind it (None for a rule drone); ``member`` the registry row when the name led to
    one (a member id, or a model whose version names its member), with ``registry`` the
    file it came from; ``task`` the task it was trained on when known.
    """

    name: str
    kind: str
    label: str
    checkpoint: Path | None = None
    member: dict[str, Any] | None = None
    registry: Path | None = None
    task: str | None = None
    zoo_member: MemberSpec | None = field(default=None, repr=False)

    def policy(self) -> Policy:
        """The policy, loaded (a checkpoint's digest checked); PolicyError when it cannot be."""
        if self.kind == "rule":
            policy: Policy = RULES[self.name]()
        elif self.zoo_member is not None:
            policy = build_policy(self.zoo_member)
        elif self.checkpoint is None:
            raise PolicyError(f"member {self.label!r} of {self.registry} has no checkpoint")
        else:
            policy = load_checkpoint(self.checkpoint)
        policy.name = self.label
        return policy


def resolve(
    name: str | Path,
    *,
    db: Path | None = None,
    runs_dir: Path = Path("runs"),
    tracking_uri: str | None = None,
    run: str | None = None,
) -> Resolved:
    """The policy ``name`` means (see the module docstring); PolicyNotFound listing what was tried.

    ``run`` limits the registries searched to that run's (:func:`registry_of_run`).
    """
    if run is not None:
        db = registry_of_run(run, db, runs_dir)
    text = str(name).strip()
    if not text:
        raise PolicyNotFound("no policy given: name a rule (greedy, vicsek), a member id, a models:/ URI or a file")
    tried: list[str] = []
    for attempt in (_rule, _model, _weights, _file, _member, _zoo):
        found = attempt(text, db, runs_dir, tracking_uri, tried)
        if found is not None:
            return found
    raise PolicyNotFound(f"no policy {text!r}; tried as " + "; ".join(tried))


def resolve_policy(name: str | Path, **where: Any) -> Policy:
    """The loaded policy ``name`` means: :func:`resolve` then :meth:`Resolved.policy`."""
    return resolve(name, **where).policy()


def resolve_checkpoint(name: str | Path, **where: Any) -> Path:
    """The checkpoint file behind ``name`` (what a deploy config's member needs); PolicyError for a rule drone."""
    found = resolve(name, **where)
    if found.checkpoint is None:
        raise PolicyError(f"{found.label!r} is a {found.kind} drone, not a trained policy with a checkpoint")
    return found.checkpoint


# ----------------------------------------------------------------- registries
def find_registries(runs_dir: Path) -> list[Path]:
    """The registry files of the runs under ``runs_dir`` (``*/registry.db``), sorted."""
    return sorted(p for p in runs_dir.glob(REGISTRY_GLOB) if p.is_file())


def locate(db: Path | None, runs_dir: Path) -> list[Path]:
    """The registries a query reads: ``db``, else ``$ATDRONE_REGISTRY``, else those found (maybe none)."""
    if db is not None:
        return [db]
    if os.environ.get(ENV_VAR):
        return [Path(os.environ[ENV_VAR])]
    found = find_registries(runs_dir)
    if not found and Path(DEFAULT_PATH).is_file():
        found = [Path(DEFAULT_PATH)]
    return found


def locate_one(db: Path | None, runs_dir: Path) -> Path:
    """The one registry a query about one member or matrix reads; RegistryError when none or several."""
    paths = locate(db, runs_dir)
    if not paths:
        raise RegistryError(_none_found(runs_dir))
    if len(paths) > 1:
        raise RegistryError(
            f"several registries under {_dir(runs_dir)}: pass --run RUN or --db FILE ({', '.join(map(str, paths))})"
        )
    return paths[0]


def registry_of_run(run: str, db: Path | None, runs_dir: Path) -> Path:
    """The registry holding run ``run`` among those :func:`locate` finds; RegistryError naming the runs there are."""
    paths = locate(db, runs_dir)
    by_folder = [p for p in paths if p.parent.name == run]
    if by_folder:
        return by_folder[0]
    runs: dict[str, Path] = {}
    for path in paths:
        try:
            with Registry(path, create=False) as registry:
                names = set(registry.members()["run"]) | set(registry.generations()["run"])
        except (RegistryError, OSError):
            continue
        runs.update({str(name): path for name in names})
    if run in runs:
        return runs[run]
    known = ", ".join(sorted(runs)) or "none"
    where = f"--db {db}" if db is not None else f"{_dir(runs_dir)}{REGISTRY_GLOB}"
    raise RegistryError(f"no run {run!r} in {where} (runs there: {known})")


def split_member_id(name: str) -> tuple[str | None, str]:
    """``RUN/ID`` as (RUN, ID); a plain id as (None, ID)."""
    run, sep, short = name.rpartition("/")
    return (run, short) if sep and run and short else (None, name)


def _none_found(runs_dir: Path) -> str:
    return (
        f"no registry found (none at {_dir(runs_dir)}{REGISTRY_GLOB}, no ./{DEFAULT_PATH}): pass --db FILE "
        "or --runs-dir DIR; `atdrone registry runs` lists the registries found"
    )


def _dir(path: Path) -> str:
    return str(path).rstrip("/") + "/"


# ------------------------------------------------------------------ readings
def _rule(text: str, db: Path | None, runs_dir: Path, tracking: str | None, tried: list[str]) -> Resolved | None:
    if text in RULES:
        return Resolved(text, "rule", text)
    tried.append(f"a rule ({', '.join(RULES)})")
    return None


def _model(text: str, db: Path | None, runs_dir: Path, tracking: str | None, tried: list[str]) -> Resolved | None:
    if not text.startswith(MODEL_PREFIX):
        tried.append("a registered model (models:/NAME@ALIAS or models:/NAME/VERSION)")
        return None
    from atdrone.tracking import model_checkpoint

    try:
        path = Path(model_checkpoint(text, tracking))
    except KeyError as exc:  # the model, its alias or its file is missing: nothing else can match a models:/ URI
        raise PolicyNotFound(f"no policy {text!r}: {exc.args[0] if exc.args else exc}") from None
    if ".." in path.parts or not path.resolve().is_relative_to(user_cache("models").resolve()):
        raise PolicyError(f"{text}: its version's tags name a file outside the model cache ({path}); refused")
    header = _header(path)
    member, registry = _member_by_sha256(header.get("sha256"), db, runs_dir)
    label = member["id"] if member else text
    return Resolved(text, "model", label, path, member, registry, header.get("task"))


def weights_checkpoint(results: Path, method: str, task: str) -> Path:
    """Where a benchmark's results folder keeps the weights of ``method`` on ``task``."""
    return Path(results) / "weights" / method / f"{task}.pt"


def weights_manifest(results: Path, method: str, task: str) -> Path:
    """The manifest beside :func:`weights_checkpoint` (method, task, seed, budget, sha256, metrics)."""
    return weights_checkpoint(results, method, task).with_suffix(".json")


def weights_roots() -> list[Path]:
    """The benchmark results folders a ``weights:`` name is looked up in."""
    if os.environ.get(WEIGHTS_ENV):
        return [Path(p) for p in os.environ[WEIGHTS_ENV].split(os.pathsep) if p]
    from atdrone.config import repo_path

    bases = (Path("benchmarks/results"), repo_path("benchmarks/results"))
    roots = {p.resolve() for base in bases for p in base.glob("*")}
    roots |= {p.resolve() for p in Path("runs/benchmarks").glob("*/results/*")}  # a benchmark's default results
    return sorted(p for p in roots if (p / "weights").is_dir())


def _weights(text: str, db: Path | None, runs_dir: Path, tracking: str | None, tried: list[str]) -> Resolved | None:
    if not text.startswith(WEIGHTS_PREFIX):
        tried.append("a benchmark's weights (weights:METHOD/TASK)")
        return None
    import hashlib
    import json

    parts = text[len(WEIGHTS_PREFIX) :].split("/")
    if len(parts) not in (2, 3) or not all(_WEIGHTS_PART.fullmatch(p) and p not in (".", "..") for p in parts):
        raise PolicyNotFound(
            f"{text!r}: name weights as weights:METHOD/TASK or weights:BENCHMARK/METHOD/TASK (letters, digits, "
            "'_', '-' and '.'; no '..')"
        )
    *bench, method, task = parts
    roots = [r for r in weights_roots() if not bench or r.name == bench[0]]
    found = [r for r in roots if weights_manifest(r, method, task).is_file()]
    if not bench and len(found) > 1:  # a smoke test's weights answer the short name only when nothing else does
        kept = [r for r in found if not json.loads(weights_manifest(r, method, task).read_text()).get("smoke_test")]
        found = kept or found
    if not found:
        where = ", ".join(map(str, roots)) or f"no results folder (set {WEIGHTS_ENV})"
        raise PolicyNotFound(f"no weights {method}/{task} in {where}")
    if len(found) > 1:
        names = ", ".join(f"{WEIGHTS_PREFIX}{r.name}/{method}/{task}" for r in found)
        raise PolicyNotFound(f"weights {method}/{task} are kept by several benchmarks: name one ({names})")
    manifest = json.loads(weights_manifest(found[0], method, task).read_text())
    path = weights_checkpoint(found[0], method, task)
    if not path.is_file() or hashlib.sha256(path.read_bytes()).hexdigest() != manifest.get("sha256"):
        raise PolicyError(f"{path}: missing or not the file its manifest names (sha256 differs)")
    return Resolved(text, "weights", f"{method}-{task}", path, task=manifest.get("task"))


def _file(text: str, db: Path | None, runs_dir: Path, tracking: str | None, tried: list[str]) -> Resolved | None:
    path = Path(text).expanduser()
    if path.is_file():
        header = _header(path)
        member, registry = _member_by_sha256(header.get("sha256"), db, runs_dir)
        label = member["id"] if member else path.stem
        return Resolved(text, "checkpoint", label, path, member, registry, header.get("task"))
    if path.is_dir():  # a path that exists is what the user meant: nothing else to try
        raise PolicyNotFound(f"{text!r} is a directory, not a checkpoint file")
    tried.append("a checkpoint file (none there)")
    return None


def _member(text: str, db: Path | None, runs_dir: Path, tracking: str | None, tried: list[str]) -> Resolved | None:
    member, registry, searched = _find_member(text, db, runs_dir)
    if member is None or registry is None:
        tried.append(f"a member id (not in {searched})")
        return None
    checkpoint = Path(member["checkpoint"]) if member.get("checkpoint") else None
    return Resolved(text, "member", text, checkpoint, member, registry, member.get("task"))


def _zoo(text: str, db: Path | None, runs_dir: Path, tracking: str | None, tried: list[str]) -> Resolved | None:
    zoo_name, sep, member_name = text.partition(":")
    zoos = [zoo_name] if sep else list(ZOO_NAMES)
    wanted, at, task = (member_name if sep else text).partition("@")  # a drone made per task: member@task
    known = []
    for z in zoos:
        try:
            zoo = load_zoo(z, task) if at else load_zoo(z)
        except ConfigError:
            tried.append(f"a zoo member (no zoo {z!r}; known: {', '.join(ZOO_NAMES)})")
            return None
        for spec in zoo.spec.members:
            if spec.name == wanted:
                if TASK_FIELD in spec.checkpoint:
                    tried.append(f"a zoo member ({zoo.name}:{wanted} is made per task: name one, {text}@4p2e1o)")
                    return None
                checkpoint = checkpoint_path(spec) if spec.kind == "checkpoint" else None
                return Resolved(text, "zoo", spec.name, checkpoint, task=task or None, zoo_member=spec)
        known.append(f"{zoo.name}: {', '.join(zoo.names)}")
    tried.append(f"a zoo member ({'; '.join(known)})")
    return None


# ------------------------------------------------------------------- helpers
def find_member(member_id: str, db: Path | None = None, runs_dir: Path = Path("runs")) -> tuple[dict[str, Any], Path]:
    """The registry row of ``member_id`` and the registry file holding it; RegistryError naming where it looked."""
    member, registry, searched = _find_member(member_id, db, runs_dir)
    if member is None or registry is None:
        raise RegistryError(f"no member {member_id!r} in {searched}")
    return member, registry


def _find_member(member_id: str, db: Path | None, runs_dir: Path) -> tuple[dict[str, Any] | None, Path | None, str]:
    """The member, its registry and (when not found) where it was looked for; several matches are refused.

    ``member_id`` is an id (``hola-g3-0``) or a run-qualified one (``hola_quick/hola-g3-0``).
    """
    run, short = split_member_id(member_id)
    if run is not None:
        try:
            db = registry_of_run(run, db, runs_dir)
        except RegistryError as exc:
            return None, None, str(exc).removeprefix("no ")
    paths = locate(db, runs_dir)
    if not paths:
        return None, None, f"any registry (none under {_dir(runs_dir)}{REGISTRY_GLOB}; pass --db FILE)"
    hits: list[tuple[dict[str, Any], Path]] = []
    for path in paths:
        try:
            with Registry(path, create=False) as registry:
                found = registry.member(short)
                if run is None or found["run"] == run:
                    hits.append((found, path))
        except KeyError:
            continue
        except (RegistryError, OSError):  # a damaged registry beside good ones does not hide their members
            if len(paths) == 1:
                raise
            continue
    if len(hits) > 1:
        names = ", ".join(f"{m['run']}/{short}" for m, _ in hits)
        raise PolicyNotFound(
            f"member {member_id!r} is in several runs: name one as {names} (or pass --run RUN or --db FILE)"
        )
    if hits:
        return hits[0][0], hits[0][1], ""
    return None, None, f"the registry at {paths[0]}" if len(paths) == 1 else ", ".join(map(str, paths))


def _member_by_sha256(sha256: Any, db: Path | None, runs_dir: Path) -> tuple[dict[str, Any] | None, Path | None]:
    """The registry member whose checkpoint has this digest (a registered model's member), if any registry has it."""
    if not sha256:
        return None, None
    for path in locate(db, runs_dir):
        try:
            with Registry(path, create=False) as registry:
                frame = registry.members()
        except (RegistryError, OSError):
            continue
        rows = frame[frame["sha256"] == sha256]
        if len(rows):
            with Registry(path, create=False) as registry:
                return registry.member(str(rows["id"].iloc[-1])), path
    return None, None


def _header(path: Path) -> dict[str, Any]:
    """A checkpoint's header ({} when it cannot be read: loading it later reports the cause)."""
    try:
        from atdrone.models.checkpoint import read_header

        return read_header(path)
    except Exception:
        return {}
