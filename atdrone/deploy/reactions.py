"""Fault reactions: one severity order, the most severe reaction taken and named.

The shield decides per drone (:class:`~atdrone.deploy.shield.Action`); the flight reacts
as a whole, in this order of severity::

    hold < land one < land all < stop one < stop all

A lost link counts as a landing (the loop keeps sending that drone the land command).
Any landing ends the flight: every drone lands, the one that fired first. The reason
printed and logged is the rule (or rules) behind the most severe reaction, not the first
seen. A drone already landing under the onboard planner is not emergency-stopped unless
it leaves its landing column (:data:`LANDING_COLUMN` from where its landing began): the
planner brings it down more gently than a motor cut from any height.

One exception to "any landing ends the flight": a partner drone (or a backup) whose battery
runs low or whose link is lost is **dropped** alone (:func:`drops`): it lands (or, lost, is
left to its firmware's watchdog), its slot is empty, and the others fly on.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from atdrone.deploy.shield import Action, ShieldDecision

LANDING_COLUMN = 0.3  # m (x, y) from where its landing began that a landing drone may drift before it is stopped
NOT_RULES = ("speed", "separation", "step")  # clamps and holds: they shape setpoints, they end nothing


class Reaction(IntEnum):
    """What the flight does, least to most severe."""

    NONE = 0
    HOLD = 1
    LAND_ONE = 2
    LAND_ALL = 3
    STOP_ONE = 4
    STOP_ALL = 5

    @property
    def text(self) -> str:
        return self.name.lower().replace("_", " ")


def severity(action: int) -> int:
    """The rank of a shield action in the flight's order: a lost link lands (between LAND and STOP)."""
    return {Action.TRACK: 0, Action.HOLD: 1, Action.LAND: 2, Action.LOST: 2, Action.STOP: 3}[Action(action)]


@dataclass(frozen=True)
class Verdict:
    """The most severe reaction of one tick, the rules behind it and the drones they fired for."""

    reaction: Reaction
    rules: tuple[str, ...]
    drones: tuple[str, ...]

    def line(self) -> str:
        """e.g. ``stop one: locked (cf3)``."""
        return f"{self.reaction.text}: {','.join(self.rules)} ({', '.join(self.drones)})"


def verdict(decision: ShieldDecision, airborne: np.ndarray) -> Verdict:
    """The most severe reaction the shield's ``decision`` calls for among ``airborne`` drones (all drones when
    none is airborne)."""
    ranks = np.array([severity(a) for a in decision.action])
    scope = airborne if airborne.any() else np.ones(len(ranks), dtype=bool)
    top = int(ranks[scope].max()) if scope.any() else 0
    if top == 0:
        return Verdict(Reaction.NONE, (), ())
    hit = scope & (ranks == top)
    every = bool(hit[scope].all()) and int(scope.sum()) > 1
    reaction = {
        1: Reaction.HOLD,
        2: Reaction.LAND_ALL if every else Reaction.LAND_ONE,
        3: Reaction.STOP_ALL if every else Reaction.STOP_ONE,
    }[top]
    names = [n for n, h in zip(decision.names, hit, strict=True) if h]
    rules = sorted(  # the rules that asked for this much (or more, where less was taken: a spared landing)
        {e.rule for e in decision.events if e.drone in names and severity(e.action) >= top and e.rule not in NOT_RULES}
    )
    return Verdict(reaction, tuple(rules), tuple(names))


DROP_RULES = {int(Action.LAND): "battery", int(Action.LOST): "link_lost"}  # the faults that drop a drone alone


def drops(decision: ShieldDecision, droppable: np.ndarray) -> dict[str, str]:
    """The ``droppable`` (D,) drones this tick's ``decision`` lands for their own battery or lost link alone: no
    other rule asked as much of them. Per drone, that rule (``battery`` or ``link_lost``)."""
    out = {}
    for i, n in enumerate(decision.names):
        rule = DROP_RULES.get(int(decision.action[i]))
        if not droppable[i] or rule is None:
            continue
        asked = {e.rule for e in decision.events if e.drone == n and severity(e.action) >= severity(Action.LAND)}
        if asked == {rule}:
            out[n] = rule
    return out


def spare_landing(
    stop: Sequence[str], state: Mapping[str, str], pos: Mapping[str, np.ndarray], began: Mapping[str, np.ndarray]
) -> list[str]:
    """The drones of ``stop`` that are really stopped: those not landing, and landing ones measured outside their
    landing column (a landing drone with no pose, or no recorded start, is left to its planner)."""
    out = []
    for n in stop:
        if state.get(n) != "landing":
            out.append(n)
            continue
        p, b = pos.get(n), began.get(n)
        if p is None or b is None or not (np.isfinite(p[:2]).all() and np.isfinite(b[:2]).all()):
            continue
        if float(np.hypot(*(p[:2] - b[:2]))) > LANDING_COLUMN:
            out.append(n)
    return out
