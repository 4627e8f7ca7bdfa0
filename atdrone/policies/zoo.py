"""The unseen drone zoos (SPEC section 8): named sets of partner policies.

A zoo document (configs/zoos/<name>.json) lists members, each a rule-based drone
given by ``kind`` ("greedy", "vicsek") with optional constructor ``params``, or a
trained drone given by ``kind: "checkpoint"`` and a ``checkpoint`` path (relative
paths are taken from the repository root). A zoo whose checkpoint files are not
there yet still loads: :attr:`Zoo.missing` says which members are absent, and
asking for their policies raises :class:`ZooError` naming them.

Trained drones are made per task: a checkpoint path may hold ``{task}``, which
:meth:`Zoo.resolve` fills with the task a zoo is played on, so one document names
each trained member once. A checkpoint whose header names another task is refused
where it is played, unless the member says ``cross_task`` (the task it was trained
on; ``{task}`` then resolves to that task) and is then labelled
``name@task`` in every record. Checkpoints listed in the zoo manifest
(:mod:`atdrone.policies.manifest`) are checked against its sha256 when loaded.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

from atdrone.config import ConfigError, parse_document, read_document, repo_path
from atdrone.errors import UserError
from atdrone.policies.base import Policy, PolicyError
from atdrone.policies.manifest import TASK_FIELD, check_digest, task_version
from atdrone.policies.rules import GreedyPolicy, VicsekPolicy

ZOO_NAMES = ("zoo1", "zoo2", "zoo3", "zoo4")  # the unseen (test) zoos: the paper's three and the diverse Zoo 4
VALIDATION_ZOO = "validation"  # partners for selection only: shares no drone with ZOO_NAMES
RULES: dict[str, type] = {"greedy": GreedyPolicy, "vicsek": VicsekPolicy}


class ZooError(PolicyError):
    """A zoo cannot provide a member's policy (e.g. its checkpoint is missing)."""


@dataclass(frozen=True)
class MemberSpec:
    """One zoo member: a rule-based drone (kind + params) or a checkpoint file."""

    name: str
    kind: Literal["greedy", "vicsek", "checkpoint", "learner"]  # learner: the training learner's own copy
    checkpoint: str = ""
    params: dict[str, float] = field(default_factory=dict)
    note: str = ""
    cross_task: str = ""  # the task this drone was trained on, when it is played on others on purpose

    @property
    def label(self) -> str:
        """The name in records: ``name@task`` for a cross-task partner."""
        return f"{self.name}@{self.cross_task}" if self.cross_task else self.name


@dataclass(frozen=True)
class ZooSpec:
    """A zoo document: its name, a description and its members."""

    name: str
    members: tuple[MemberSpec, ...]
    description: str = ""


def checkpoint_path(spec: MemberSpec) -> Path:
    return repo_path(spec.checkpoint)


def _validate(spec: ZooSpec) -> None:
    if not spec.members:
        raise ConfigError("members", "a zoo needs at least one member")
    seen: set[str] = set()
    for i, m in enumerate(spec.members):
        if m.name in seen:
            raise ConfigError(f"members[{i}].name", f"duplicate member name {m.name!r}")
        seen.add(m.name)
        if m.kind == "learner":
            raise ConfigError(f"members[{i}].kind", "'learner' is the training learner's own copy, not a zoo member")
        if m.kind == "checkpoint" and not m.checkpoint:
            raise ConfigError(f"members[{i}].checkpoint", "missing key (a checkpoint member needs a file)")
        if m.kind != "checkpoint" and m.checkpoint:
            raise ConfigError(f"members[{i}].checkpoint", f"only checkpoint members take a file (kind {m.kind!r})")
        if m.cross_task and m.kind != "checkpoint":
            raise ConfigError(f"members[{i}].cross_task", "only trained (checkpoint) members have a task of their own")
        if m.kind in RULES:
            try:
                RULES[m.kind](**m.params)
            except TypeError as exc:
                raise ConfigError(f"members[{i}].params", f"bad parameters for {m.kind}: {exc}") from None


class Zoo:
    """A loaded zoo: member names, their policies, and which members are missing.

    A zoo whose checkpoint paths hold ``{task}`` is per task: :meth:`resolve` gives the
    zoo of one task; its policies cannot be built before.
    """

    def __init__(self, spec: ZooSpec, task: str = "") -> None:
        self.spec = spec
        self.task = task  # the task the checkpoint paths were resolved for ("" when not resolved)
        self.names = [m.label for m in spec.members]
        self.per_task = any(TASK_FIELD in m.checkpoint for m in spec.members)
        self.missing = [
            m.label
            for m in spec.members
            if m.kind == "checkpoint" and TASK_FIELD not in m.checkpoint and not checkpoint_path(m).is_file()
        ]
        self._policies: list[Policy] | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    def __len__(self) -> int:
        return len(self.spec.members)

    def resolve(self, task: Any) -> Zoo:
        """This zoo on ``task`` (a name or a TaskConfig): ``{task}`` filled in every checkpoint path."""
        name = task if isinstance(task, str) else task.name
        if self.task:
            if self.task != name:
                raise ZooError(f"zoo {self.name!r} was resolved for task {self.task}, not {name}")
            return self
        members = tuple(
            replace(m, checkpoint=m.checkpoint.replace(TASK_FIELD, m.cross_task or name)) for m in self.spec.members
        )
        return Zoo(replace(self.spec, members=members), task=name)

    @property
    def version(self) -> str:
        """The zoo manifest's version of this zoo's task ("" when not resolved or not in the manifest)."""
        return task_version(self.task) if self.task else ""

    def cross_task(self) -> list[str]:
        """The labels of the members trained on another task than the one played (``name@task``)."""
        return [m.label for m in self.spec.members if m.cross_task and m.cross_task != self.task]

    def check(self) -> None:
        """ZooError unless every member can be built: checkpoint files present, their headers and weights intact.

        What a config that names the zoo calls when it is loaded, so a run does not
        train for hours and then fail at its final evaluation.
        """
        self.policies()

    def policies(self) -> list[Policy]:
        """One policy per member, in member order; ZooError when a member is missing or of another task."""
        if self.per_task and not self.task:
            raise ZooError(f"zoo {self.name!r} holds a drone per task: resolve it for a task first")
        if self.missing:
            absent = [m for m in self.spec.members if m.label in self.missing]
            details = "; ".join(f"{m.label!r} needs {m.checkpoint}" for m in absent)
            raise ZooError(
                f"zoo {self.name!r} is incomplete: {details}. Train the drones with "
                "`python benchmarks/train_task_zoos.py` (see configs/zoos/checkpoints/README.md)."
            )
        if self._policies is None:
            self._policies = [build_policy(m, self.task, self.name) for m in self.spec.members]
        return self._policies


def build_policy(spec: MemberSpec, task: str = "", zoo: str = "") -> Policy:
    """The policy of one member spec: a rule-based drone, or a checkpoint loaded from disk.

    With ``task``, a checkpoint trained on another task is refused unless the member
    names that task as its ``cross_task``; a checkpoint the zoo manifest lists must
    match its sha256.
    """
    if spec.kind in RULES:
        policy = RULES[spec.kind](**spec.params)
    else:
        path = checkpoint_path(spec)
        check_digest(path)
        policy = load_checkpoint(path)
        trained_on = str(getattr(policy, "task", "") or "")
        where = f"zoo {zoo!r} member {spec.name!r}" if zoo else f"member {spec.name!r}"
        if spec.cross_task and trained_on and trained_on != spec.cross_task:
            mark = f"its cross_task {spec.cross_task}"
            raise ZooError(f"{where}: {spec.checkpoint} was trained on {trained_on}, not on {mark}")
        if task and trained_on and trained_on != task and not spec.cross_task:
            raise ZooError(
                f"{where}: {spec.checkpoint} was trained on {trained_on}, not on {task} "
                f'(mark the member "cross_task": "{trained_on}" to play it on another task)'
            )
    policy.name = spec.label
    return policy


def load_checkpoint(path: str | Path) -> Policy:
    """The policy saved in a checkpoint file; PolicyError when it cannot be loaded."""
    path = Path(path)
    if path.is_dir():
        raise PolicyError(f"{str(path)!r} is a directory, not a checkpoint file")
    if not path.is_file():
        raise PolicyError(f"no checkpoint file {str(path)!r}")
    from atdrone.policies.neural import load_policy  # torch, only when a checkpoint is loaded

    try:
        return load_policy(path)
    except UserError as exc:  # a damaged, edited or foreign file: its message names the file and the cause
        raise PolicyError(f"cannot load checkpoint: {exc}") from exc
    except Exception as exc:  # anything the checks did not foresee, still one line
        raise PolicyError(f"cannot load checkpoint {str(path)!r}: {type(exc).__name__}: {exc}") from exc


def policy_from_spec(spec: str | Path) -> Policy:
    """A policy named on a command line: a rule kind (greedy, vicsek) or a checkpoint path."""
    text = str(spec)
    if text in RULES:
        return RULES[text]()
    if not Path(text).exists():
        raise PolicyError(f"no policy {text!r}: give a rule ({', '.join(RULES)}) or a checkpoint file")
    return load_checkpoint(text)


def load_zoo(name_or_path: str | Path | dict[str, Any], task: Any = None) -> Zoo:
    """Load a zoo by name (zoo1-zoo4, validation), path or mapping; ConfigError when invalid.

    With ``task`` (a name or TaskConfig) the zoo comes resolved for that task.
    """
    names = (*ZOO_NAMES, VALIDATION_ZOO)
    doc = name_or_path if isinstance(name_or_path, dict) else read_document(name_or_path, "zoos", names)
    spec = parse_document(ZooSpec, doc)
    _validate(spec)
    zoo = Zoo(spec)
    return zoo if task is None else zoo.resolve(task)
