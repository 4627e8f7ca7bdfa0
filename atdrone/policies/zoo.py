"""The unseen drone zoos (SPEC section 8): named sets of partner policies.

A zoo document (configs/zoos/<name>.json) lists members, each a rule-based drone
given by ``kind`` ("greedy", "vicsek") with optional constructor ``params``, or a
trained drone given by ``kind: "checkpoint"`` and a ``checkpoint`` path (relative
paths are taken from the repository root). A zoo whose checkpoint files are not
there yet still loads: :attr:`Zoo.missing` says which members are absent, and
asking for their policies raises :class:`ZooError` naming them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from atdrone.config import ConfigError, parse_document, read_document, repo_path
from atdrone.errors import UserError
from atdrone.policies.base import Policy, PolicyError
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
        if m.kind in RULES:
            try:
                RULES[m.kind](**m.params)
            except TypeError as exc:
                raise ConfigError(f"members[{i}].params", f"bad parameters for {m.kind}: {exc}") from None


class Zoo:
    """A loaded zoo: member names, their policies, and which members are missing."""

    def __init__(self, spec: ZooSpec) -> None:
        self.spec = spec
        self.names = [m.name for m in spec.members]
        self.missing = [m.name for m in spec.members if m.kind == "checkpoint" and not checkpoint_path(m).is_file()]
        self._policies: list[Policy] | None = None

    @property
    def name(self) -> str:
        return self.spec.name

    def __len__(self) -> int:
        return len(self.spec.members)

    def check(self) -> None:
        """ZooError unless every member can be built: checkpoint files present, their headers and weights intact.

        What a config that names the zoo calls when it is loaded, so a run does not
        train for hours and then fail at its final evaluation.
        """
        self.policies()

    def policies(self) -> list[Policy]:
        """One policy per member, in member order; ZooError when a member is missing."""
        if self.missing:
            details = "; ".join(f"{m.name!r} needs {m.checkpoint}" for m in self.spec.members if m.name in self.missing)
            raise ZooError(
                f"zoo {self.name!r} is incomplete: {details}. Train the self-play drones with "
                "`atdrone train configs/train/sp_high.json` / `sp_low.json` (see README)."
            )
        if self._policies is None:
            self._policies = [build_policy(m) for m in self.spec.members]
        return self._policies


def build_policy(spec: MemberSpec) -> Policy:
    """The policy of one member spec: a rule-based drone, or a checkpoint loaded from disk."""
    policy = RULES[spec.kind](**spec.params) if spec.kind in RULES else load_checkpoint(checkpoint_path(spec))
    policy.name = spec.name
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


def load_zoo(name_or_path: str | Path | dict[str, Any]) -> Zoo:
    """Load a zoo by name (zoo1-zoo4, validation), path or mapping; ConfigError when invalid."""
    names = (*ZOO_NAMES, VALIDATION_ZOO)
    doc = name_or_path if isinstance(name_or_path, dict) else read_document(name_or_path, "zoos", names)
    spec = parse_document(ZooSpec, doc)
    _validate(spec)
    return Zoo(spec)
