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

from atdrone.config import CONFIG_DIR, ConfigError, parse_document, read_document
from atdrone.policies.base import Policy
from atdrone.policies.rules import GreedyPolicy, VicsekPolicy

ZOO_NAMES = ("zoo1", "zoo2", "zoo3")
REPO_ROOT = CONFIG_DIR.parent
RULES: dict[str, type] = {"greedy": GreedyPolicy, "vicsek": VicsekPolicy}


class ZooError(RuntimeError):
    """A zoo cannot provide a member's policy (e.g. its checkpoint is missing)."""


@dataclass(frozen=True)
class MemberSpec:
    """One zoo member: a rule-based drone (kind + params) or a checkpoint file."""

    name: str
    kind: Literal["greedy", "vicsek", "checkpoint"]
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
    path = Path(spec.checkpoint)
    return path if path.is_absolute() else REPO_ROOT / path


def _validate(spec: ZooSpec) -> None:
    if not spec.members:
        raise ConfigError("members", "a zoo needs at least one member")
    seen: set[str] = set()
    for i, m in enumerate(spec.members):
        if m.name in seen:
            raise ConfigError(f"members[{i}].name", f"duplicate member name {m.name!r}")
        seen.add(m.name)
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

    def policies(self) -> list[Policy]:
        """One policy per member, in member order; ZooError when a member is missing."""
        if self.missing:
            details = "; ".join(f"{m.name!r} needs {m.checkpoint}" for m in self.spec.members if m.name in self.missing)
            raise ZooError(
                f"zoo {self.name!r} is incomplete: {details}. Train the self-play drones with "
                "`atdrone train configs/train/sp_high.json` / `sp_low.json` (see README)."
            )
        if self._policies is None:
            self._policies = [_build(m) for m in self.spec.members]
        return self._policies


def _build(spec: MemberSpec) -> Policy:
    if spec.kind in RULES:
        policy = RULES[spec.kind](**spec.params)
    else:
        from atdrone.checkpoint import load_policy

        policy = load_policy(checkpoint_path(spec))
    policy.name = spec.name
    return policy


def load_zoo(name_or_path: str | Path | dict[str, Any]) -> Zoo:
    """Load a zoo by name (zoo1, zoo2, zoo3), path or mapping; ConfigError when invalid."""
    doc = name_or_path if isinstance(name_or_path, dict) else read_document(name_or_path, "zoos", ZOO_NAMES)
    spec = parse_document(ZooSpec, doc)
    _validate(spec)
    return Zoo(spec)
