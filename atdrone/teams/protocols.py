"""Evaluation and training protocols with team events: a zoo plus the swaps, drops and joins of every episode.

A protocol document (configs/protocols/<name>.json) names a zoo and the events each
episode has::

    {"name": "zoo3+drop+join", "zoo": "zoo3",
     "events": [{"kind": "drop", "steps": [20, 100]},
                {"kind": "join", "steps": [10, 40], "slots": "partners"}]}

``steps`` is the inclusive range of the step an event happens at (a join: of the steps
after the drop before it); ``slots`` which slots it may hit: "partners" (default),
"learners" or "any". Each episode draws its own schedule from its key
(:mod:`atdrone.envs.events`), so a protocol is played the same wherever a zoo is:
``atdrone evaluate --zoo zoo3+swap``, a training config's ``"protocol"`` key.

A training protocol may also draw the split of the team: ``"learners": [lo, hi]``, how
many of its slots the learner flies in each episode (uniform in lo..hi, at most the
slots its training mode gives it); the mode's partners fly the others, and those
drone-steps are not trained on (:class:`~atdrone.teams.match.Match`). It may draw the
team's size too: ``"sizes": [lo, hi]``, pursuers per team (the task's variants
``<P>p<E>e<O>o`` for P in lo..hi must ship), drawn for each rollout
(:mod:`atdrone.learn.sizes`: the learner keeps its slots, partners fill the others).
With a split or sizes the events may be left out. Evaluation plays every split and size
itself (``atdrone evaluate --splits``, a task variant), so a protocol with a split or
sizes is for training only.

The metrics of an episode with events split at the first event that happened:
  EVT      % of episodes that lived to their first event;
  SUC_pre  % of all episodes that caught every evader before it, COL_pre with a collision;
  SUC_post % of the episodes that lived to it that went on to catch every evader, COL_post
           that ended in a collision after it;
  REC      recovery time: mean steps from the event to the next capture, over the episodes
           with a capture after it (REC_none: % of those that lived to it without one).
Percentages carry Wilson's interval, REC the normal interval of a mean, as the other metrics.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from atdrone.config import CONFIG_DIR, ConfigError, read_json
from atdrone.envs.events import SLOT_CHOICES, EventPlan, EventSpec

if TYPE_CHECKING:
    import pandas as pd

PROTOCOL_DIR = CONFIG_DIR / "protocols"
EVENT_METRICS = ("EVT", "SUC_pre", "COL_pre", "SUC_post", "COL_post", "REC", "REC_none")
EVENT_FIELDS = {"events": object, "event_step": np.int64, "recovery": np.int64}  # per-episode record columns


@dataclass(frozen=True)
class Protocol:
    """A zoo and the team events of every episode (see the module docstring)."""

    name: str
    zoo: str
    plan: EventPlan
    description: str = ""
    split: tuple[int, int] | None = None  # the "learners" range: slots the learner flies, drawn per episode
    sizes: tuple[int, int] | None = None  # the "sizes" range: pursuers per team, drawn per rollout

    def to_dict(self) -> dict[str, Any]:
        """The document's form (what a run records)."""
        events = [{"kind": e.kind, "steps": list(e.steps), "slots": e.slots} for e in self.plan.events]
        doc: dict[str, Any] = {"name": self.name, "zoo": self.zoo, "description": self.description, "events": events}
        if self.split is not None:
            doc["learners"] = list(self.split)
        if self.sizes is not None:
            doc["sizes"] = list(self.sizes)
        return doc


def protocol_names() -> tuple[str, ...]:
    """The shipped protocols (configs/protocols/*.json), by name."""
    return tuple(sorted(p.stem for p in PROTOCOL_DIR.glob("*.json")))


def is_protocol(name_or_path: str | Path) -> bool:
    """Whether ``name_or_path`` names a shipped protocol or a JSON file holding one (it has "events",
    "learners" or "sizes")."""
    text = str(name_or_path)
    if text in protocol_names():
        return True
    path = Path(text)
    if path.suffix != ".json" or not path.is_file():
        return False
    document = read_json(path)
    return isinstance(document, dict) and bool({"events", "learners", "sizes"} & set(document))


def zoo_of(name: str) -> tuple[str, EventPlan | None]:
    """The zoo behind a zoo name and the team events to play with it: a protocol's zoo and plan, or the zoo
    itself and None (wherever a zoo is named, a protocol may be)."""
    if is_protocol(name):
        protocol = evaluation_protocol(name)
        return protocol.zoo, protocol.plan
    return name, None


def check_split(split: tuple[int, int] | None, slots: int, path: str) -> None:
    """ConfigError at ``path`` when a protocol's ``learners`` range asks for more than the ``slots`` a training
    mode's learner fills."""
    if split is not None and split[1] > slots:
        raise ConfigError(
            f"{path}.learners", f"the learner fills {slots} slots here, so at most {slots}; got {list(split)}"
        )


def evaluation_protocol(name_or_path: str | Path | Protocol) -> Protocol:
    """:func:`load_protocol` for evaluation: ConfigError for a protocol that draws the team's split or size
    (training only; evaluation plays every split itself, ``atdrone evaluate --splits``, and a size as its task)."""
    protocol = load_protocol(name_or_path)
    if protocol.sizes is not None:
        raise ConfigError(
            "sizes",
            f"protocol {protocol.name!r} draws the team's size, which only training does "
            "(play a size as its task instead: --task configs/tasks/6p2e1o.json --cross-task)",
        )
    if protocol.split is not None:
        raise ConfigError(
            "learners",
            f"protocol {protocol.name!r} draws the team's split, which only training does "
            "(evaluation plays every split: atdrone evaluate --splits)",
        )
    return protocol


def load_protocol(name_or_path: str | Path | Protocol) -> Protocol:
    """A protocol by name (configs/protocols/<name>.json) or path; ConfigError naming the field when invalid."""
    if isinstance(name_or_path, Protocol):
        return name_or_path
    text = str(name_or_path)
    path = PROTOCOL_DIR / f"{text}.json" if text in protocol_names() else Path(text)
    if not path.is_file():
        raise ConfigError(None, f"no protocol named {text!r} (known: {', '.join(protocol_names())}) and no such file")
    return parse_protocol(read_json(path), fallback_name=path.stem)


def parse_protocol(document: Any, fallback_name: str = "") -> Protocol:
    """A protocol from its parsed document (see the module docstring)."""
    if not isinstance(document, dict):
        raise ConfigError("", "a protocol document is a JSON object")
    unknown = set(document) - {"name", "zoo", "description", "events", "learners", "sizes"}
    if unknown:
        raise ConfigError(sorted(unknown)[0], "unknown key (known: name, zoo, description, events, learners, sizes)")
    zoo = document.get("zoo")
    if not isinstance(zoo, str) or not zoo:
        raise ConfigError("zoo", "the zoo the partners come from (e.g. zoo3) is required")
    split, sizes = _range(document, "learners", 1), _range(document, "sizes", 2)
    raw = document.get("events", [] if split is not None or sizes is not None else None)
    if not isinstance(raw, list) or (not raw and split is None and sizes is None):
        raise ConfigError("events", "a non-empty list of events is required (or a learners or sizes range)")
    specs = []
    for i, entry in enumerate(raw):
        where = f"events[{i}]"
        if not isinstance(entry, dict):
            raise ConfigError(where, "an event is an object with kind, steps and slots")
        extra = set(entry) - {"kind", "steps", "slots"}
        if extra:
            raise ConfigError(f"{where}.{sorted(extra)[0]}", "unknown key (known: kind, steps, slots)")
        kind = entry.get("kind")
        if kind not in ("swap", "drop", "join"):
            raise ConfigError(f"{where}.kind", f"must be swap, drop or join, got {kind!r}")
        steps = entry.get("steps")
        if not (
            isinstance(steps, list)
            and len(steps) == 2
            and all(isinstance(s, int) and not isinstance(s, bool) for s in steps)
            and 0 <= steps[0] <= steps[1]
        ):
            raise ConfigError(f"{where}.steps", f"must be [low, high] integers, 0 <= low <= high, got {steps!r}")
        slots = entry.get("slots", "partners")
        if slots not in SLOT_CHOICES:
            raise ConfigError(f"{where}.slots", f"must be one of {', '.join(SLOT_CHOICES)}, got {slots!r}")
        if kind == "join" and (i == 0 or raw[i - 1].get("kind") != "drop"):
            raise ConfigError(f"{where}.kind", "a join must follow a drop (it refills the dropped slot)")
        specs.append(EventSpec(kind, (steps[0], steps[1]), slots))
    name = document.get("name", fallback_name)
    if not isinstance(name, str) or not name:
        raise ConfigError("name", "must be a non-empty string")
    return Protocol(
        name=name,
        zoo=zoo,
        plan=EventPlan(tuple(specs)),
        description=str(document.get("description", "")),
        split=split,
        sizes=sizes,
    )


def _range(document: dict[str, Any], key: str, low: int) -> tuple[int, int] | None:
    """A document's optional ``[lo, hi]`` integer range at ``key`` (``low`` <= lo <= hi); ConfigError else."""
    value = document.get(key)
    if value is None:
        return None
    if not (
        isinstance(value, list)
        and len(value) == 2
        and all(isinstance(k, int) and not isinstance(k, bool) for k in value)
        and low <= value[0] <= value[1]
    ):
        raise ConfigError(key, f"must be [low, high] integers, {low} <= low <= high, got {value!r}")
    return value[0], value[1]


def event_counts(records: pd.DataFrame) -> tuple[dict[str, tuple[int, int]], np.ndarray]:
    """(hits, out of) of each percentage of EVENT_METRICS, and the recovery times (steps) REC averages."""
    n = len(records)
    reached = records["event_step"].to_numpy() >= 0
    success, collided = records["success"].to_numpy(bool), records["collided"].to_numpy(bool)
    rec = records["recovery"].to_numpy()
    after = reached & (rec >= 0)
    m = int(reached.sum())
    counts = {
        "EVT": (m, n),
        "SUC_pre": (int((success & ~reached).sum()), n),
        "COL_pre": (int((collided & ~reached).sum()), n),
        "SUC_post": (int((success & reached).sum()), m),
        "COL_post": (int((collided & reached).sum()), m),
        "REC_none": (int((reached & ~after).sum()), m),
    }
    return counts, rec[after]


def event_metrics(records: pd.DataFrame) -> dict[str, float]:
    """EVT, SUC/COL before and after the first event, REC and REC_none of episode records (module docstring)."""
    counts, rec = event_counts(records)
    out = {k: 100.0 * hits / total if total else float("nan") for k, (hits, total) in counts.items()}
    out["REC"] = float(rec.mean()) if len(rec) else float("nan")
    return {k: out[k] for k in EVENT_METRICS}
