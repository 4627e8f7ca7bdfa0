"""Partner distributions: how each episode's partner slots are filled from named members.

An algorithm hands one of these to the rollout; the rollout draws from it per
environment and per episode (through :class:`~atdrone.teams.match.Match`'s sampler)
and records what it drew. ``members`` names the pool (population member ids or zoo
members); ``draw`` returns indices into it. Any class with these two members plugs in.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from atdrone.teams.match import PartnerSampler


@runtime_checkable
class PartnerDistribution(Protocol):
    """A distribution over the partner slots of an episode."""

    @property
    def members(self) -> tuple[str, ...]:
        """The pool's member ids."""
        ...

    def draw(self, rng: np.random.Generator, n: int, slots: int) -> np.ndarray:
        """(n, slots) indices into ``members`` for n fresh episodes."""
        ...


@dataclass(frozen=True)
class Uniform:
    """Every slot drawn uniformly and independently from ``members``."""

    members: tuple[str, ...]

    def draw(self, rng: np.random.Generator, n: int, slots: int) -> np.ndarray:
        return rng.integers(len(self.members), size=(n, slots))


LEARNER_COPY = "self"  # a partner slot flown by a copy of the training learner (its steps are not trained on)


@dataclass(frozen=True)
class VariableCount:
    """Each episode draws how many partners it has, then who they are.

    The count c is uniform in ``min_partners``..slots; c slots get members of the pool
    (``members`` but the last), uniformly and independently; the others get the last
    member, :data:`LEARNER_COPY` (the Match shuffles every episode's slots).
    """

    members: tuple[str, ...]
    min_partners: int = 1

    def __post_init__(self) -> None:
        if len(self.members) < 2 or self.members[-1] != LEARNER_COPY:
            raise ValueError(f"members must be a pool followed by {LEARNER_COPY!r}, got {self.members}")
        if self.min_partners < 0:
            raise ValueError(f"min_partners must be >= 0, got {self.min_partners}")

    def draw(self, rng: np.random.Generator, n: int, slots: int) -> np.ndarray:
        pool = len(self.members) - 1
        counts = rng.integers(min(self.min_partners, slots), slots + 1, size=n)
        picks = rng.integers(pool, size=(n, slots))
        return np.where(np.arange(slots)[None] < counts[:, None], picks, pool)


@dataclass(frozen=True)
class Weighted:
    """Every slot drawn independently from ``members`` with probabilities ``probs``."""

    members: tuple[str, ...]
    probs: tuple[float, ...] = field(default=())

    def __post_init__(self) -> None:
        p = np.asarray(self.probs, dtype=np.float64)
        if len(p) != len(self.members) or np.any(p < 0) or not p.sum() > 0:
            raise ValueError(f"probs must be {len(self.members)} non-negative weights, not all 0; got {self.probs}")

    def draw(self, rng: np.random.Generator, n: int, slots: int) -> np.ndarray:
        p = np.asarray(self.probs, dtype=np.float64)
        return rng.choice(len(self.members), size=(n, slots), p=p / p.sum())


@dataclass(frozen=True)
class Profiles:
    """Whole partner teams: each episode draws one profile with probability ``probs``.

    ``profiles[k]`` holds indices into ``members``, one per partner slot (the Match
    shuffles every episode's slots, so no member is tied to a slot).
    """

    members: tuple[str, ...]
    profiles: tuple[tuple[int, ...], ...]
    probs: tuple[float, ...]

    def __post_init__(self) -> None:
        p = np.asarray(self.probs, dtype=np.float64)
        if len(p) != len(self.profiles) or not len(p) or np.any(p < 0) or not p.sum() > 0:
            raise ValueError(f"probs must be {len(self.profiles)} non-negative weights, not all 0; got {self.probs}")
        sizes = {len(t) for t in self.profiles}
        if len(sizes) != 1 or any(not 0 <= i < len(self.members) for t in self.profiles for i in t):
            raise ValueError(f"profiles must be equally long index tuples into {len(self.members)} members")

    @property
    def names(self) -> list[str]:
        """Each profile as "a|b" (member ids in profile order)."""
        return ["|".join(self.members[i] for i in t) for t in self.profiles]

    def draw(self, rng: np.random.Generator, n: int, slots: int) -> np.ndarray:
        if len(self.profiles[0]) != slots:
            raise ValueError(f"profiles fill {len(self.profiles[0])} slots, the episode has {slots}")
        p = np.asarray(self.probs, dtype=np.float64)
        picks = rng.choice(len(self.profiles), size=n, p=p / p.sum())
        return np.asarray(self.profiles, dtype=np.int64)[picks]

    def resized(self, slots: int) -> PartnerSampler:
        """A sampler for teams of ``slots`` partner slots, the profiles' own count or another (team sizes drawn
        in training): each episode draws a profile as :meth:`draw` does, then with fewer slots keeps a random
        subset of its members (without replacement), and with more fills the extra slots from its members
        (uniformly, with replacement), so a team of any size holds the drawn profile's members alone."""
        if slots <= 0:
            raise ValueError(f"slots must be positive, got {slots}")
        m = len(self.profiles[0])

        def sample(rng: np.random.Generator, n: int) -> np.ndarray:
            picks = self.draw(rng, n, m)
            rows = np.arange(n)[:, None]
            if slots < m:
                return picks[rows, np.argsort(rng.random((n, m)), axis=1)[:, :slots]]
            if slots > m:
                return np.concatenate([picks, picks[rows, rng.integers(m, size=(n, slots - m))]], axis=1)
            return picks

        return sample


def profiles(dist: Mapping[tuple[str, ...], float]) -> Profiles:
    """A Profiles distribution from {profile (member ids): probability}."""
    members = tuple(dict.fromkeys(m for profile in dist for m in profile))
    index = {m: i for i, m in enumerate(members)}
    return Profiles(members, tuple(tuple(index[m] for m in t) for t in dist), tuple(float(p) for p in dist.values()))


def slot_counts(drawn: Mapping[str, int]) -> dict[str, int]:
    """Partner slots each member filled, from drawn profile counts ({"a|b": episodes})."""
    slots: dict[str, int] = {}
    for profile, n in drawn.items():
        for member in profile.split("|"):
            slots[member] = slots.get(member, 0) + n
    return dict(sorted(slots.items()))


def describe(dist: PartnerDistribution | None) -> dict[str, Any]:
    """A JSON summary of a distribution (its class, members and, when weighted, probabilities)."""
    if dist is None:
        return {"kind": "self-play"}
    out: dict[str, Any] = {"kind": type(dist).__name__, "members": list(dist.members)}
    if isinstance(dist, Profiles):
        out["profiles"] = dist.names
    if isinstance(dist, VariableCount):
        out["min_partners"] = dist.min_partners
    if hasattr(dist, "probs"):
        out["probs"] = [float(p) for p in dist.probs]
    return out


def as_sampler(dist: PartnerDistribution, slots: int) -> PartnerSampler:
    """The Match sampler that draws ``slots`` partners per episode from ``dist``."""
    return lambda rng, n: dist.draw(rng, n, slots)


def weighted(weights: dict[str, float], members: Sequence[str] | None = None) -> Weighted:
    """A Weighted distribution from a {member: weight} mapping (in ``members`` order when given)."""
    ids = tuple(members if members is not None else weights)
    return Weighted(ids, tuple(float(weights[m]) for m in ids))
