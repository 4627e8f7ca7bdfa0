"""HOLA-Drone V2 (SPEC section 10): the preference hypergraph over a population of policies.

Pure functions over a table of evaluation matches, so the Ray coordinator holds no
algorithm of its own and every step can be tested against a plain reference.

Vocabulary:

- A *member* is a policy of the population, named by a string id.
- A *team* (a hyperedge) is the multiset of member ids filling the pursuer slots, e.g.
  ``("L", "L", "p1", "p3")`` when learner ``L`` fills 2 learner slots next to partners
  ``p1`` and ``p3``. Its canonical form is :func:`team_key`, the sorted tuple. For degrees
  the hyperedge's node set is its set of *distinct* members and ``|e|`` is their number,
  so a team is linked to each of its distinct co-members once, however many slots they fill.
- A team's *weight* is its mean outcome over its evaluation matches.

One generation of the algorithm, as the coordinator calls it::

    population, removed = update_population(population, eta, learners, capacity)
    to_play = missing_hyperedges(population, learners, num_ctrl, num_partners, known)
    ...                                   # evaluate to_play, append to the match table
    weights = hyperedge_weights(matches)
    eta = preference_centrality(weights, nodes=population)
    rho = partner_distribution(eta, [m for m in population if m not in learners])
    profiles = sample_profiles(rho, num_profiles, num_partners, rng)   # max step: PPO

The "w/o g" ablation replaces ``partner_distribution`` by :func:`uniform_distribution`.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Sequence

import numpy as np
import pandas as pd

Team = tuple[str, ...]


def team_key(members: Iterable[str]) -> Team:
    """The canonical form of a team: its member ids sorted, duplicates kept (slot counts matter)."""
    return tuple(sorted(str(m) for m in members))


def hyperedge_weights(matches: pd.DataFrame, outcome: str = "score") -> dict[Team, float]:
    """Each team's weight: the mean of ``outcome`` over all its rows of ``matches``.

    ``matches`` has a column ``"team"`` (a sequence of member ids, in any slot order) and
    the ``outcome`` column. Several evaluation matches of one team are averaged. Rows whose
    outcome is NaN are left out (e.g. a time-to-capture with no capture), as in
    ``DataFrame.mean``; a team with no other row gets no hyperedge. Keys are team_keys,
    sorted.
    """
    missing = {"team", outcome} - set(matches.columns)
    if missing:
        raise ValueError(f"match table lacks column(s) {sorted(missing)}; it has {list(matches.columns)}")
    values = pd.to_numeric(matches[outcome]).to_numpy(dtype=np.float64)
    keep = ~np.isnan(values)
    keys = [team_key(team) for team, k in zip(matches["team"], keep, strict=True) if k]
    index: dict[Team, int] = {}
    codes = np.fromiter((index.setdefault(k, len(index)) for k in keys), dtype=np.intp, count=len(keys))
    sums = np.bincount(codes, weights=values[keep], minlength=len(index))
    counts = np.bincount(codes, minlength=len(index))
    return {key: float(sums[i] / counts[i]) for key, i in sorted(index.items())}


def _distinct(team: Team) -> frozenset[str]:
    return frozenset(team)


def preference_hypergraph(weights: dict[Team, float]) -> dict[str, Team]:
    """Each node's single outgoing hyperedge: the highest-weight team it belongs to.

    Ties go to the lowest team_key, so the graph depends on the weights only. A team with
    one distinct member (self-play: the member fills every slot) links the node to no one,
    and carries no degree either (``|e| - 1 = 0``), so it is never a preference: a node whose
    only teams are such teams gets no outgoing edge and is absent from the result. Keys are
    node ids, sorted.
    """
    preferred: dict[str, Team] = {}
    for team in sorted(weights, key=lambda t: (-weights[t], t)):
        members = _distinct(team)
        if len(members) < 2:
            continue
        for node in members:
            preferred.setdefault(node, team)
    return dict(sorted(preferred.items()))


def hypergraph_degrees(weights: dict[Team, float]) -> dict[str, int]:
    """degree(i) = sum over the hyperedges e containing i of ``|e| - 1`` (``|e|``: distinct members).

    Every node of every hyperedge is a key, with degree 0 when it only plays self-play teams.
    """
    degree: dict[str, int] = {}
    for team in weights:
        members = _distinct(team)
        for node in members:
            degree[node] = degree.get(node, 0) + len(members) - 1
    return dict(sorted(degree.items()))


def preference_in_degrees(preferred: dict[str, Team]) -> dict[str, int]:
    """in-degree(i) = the number of other nodes j whose preferred hyperedge contains i.

    Each such j counts once, however many slots i fills in j's team: in-degree measures how
    many members want to play with i. Nodes nobody prefers are absent (in-degree 0).
    """
    in_degree: dict[str, int] = {}
    for source, team in preferred.items():
        for node in _distinct(team) - {source}:
            in_degree[node] = in_degree.get(node, 0) + 1
    return dict(sorted(in_degree.items()))


def preference_centrality(weights: dict[Team, float], nodes: Iterable[str] | None = None) -> dict[str, float]:
    """eta(i) = in-degree of i in the preference hypergraph / degree of i in the hypergraph.

    eta is in [0, 1]: every j counted in i's in-degree is another member of a hyperedge e
    containing i, and e holds at most ``|e| - 1`` such j, which is e's share of degree(i).
    A high eta marks a member many others choose as a teammate; a low one, a member nobody
    picks. Nodes of degree 0 (only self-play teams, or no team at all) get eta 0; ``nodes``
    adds such members with no evaluated team. Keys: every node of ``weights`` and ``nodes``,
    sorted.
    """
    degree = hypergraph_degrees(weights)
    in_degree = preference_in_degrees(preference_hypergraph(weights))
    everyone = set(degree) | set(nodes or ())
    return {
        node: in_degree.get(node, 0) / degree[node] if degree.get(node, 0) > 0 else 0.0 for node in sorted(everyone)
    }


def _unique(candidates: Iterable[str]) -> list[str]:
    ids = list(dict.fromkeys(candidates))
    if not ids:
        raise ValueError("no candidates to draw partners from")
    return ids


def partner_distribution(eta: dict[str, float], candidates: Iterable[str], eps: float = 1e-3) -> dict[str, float]:
    """The min step: rho over ``candidates`` proportional to ``1 / (eta + eps)``, normalised.

    The learners train against partners drawn from rho, so the members nobody likes to
    play with (low eta) are drawn most often: the worst-case partners for generalisation.
    ``eps`` keeps a member of eta 0 finite; it must keep every ``eta + eps`` positive.
    Every candidate must be in ``eta`` (compute eta with ``nodes=population``): a missing id
    is an error rather than a silent eta 0, which would make it the most drawn partner.
    Duplicate candidates count once; keys keep the candidates' order.
    """
    ids = _unique(candidates)
    missing = [c for c in ids if c not in eta]
    if missing:
        raise KeyError(f"no eta for candidate(s) {missing}")
    shifted = np.array([eta[c] + eps for c in ids], dtype=np.float64)
    if not np.all(shifted > 0):
        raise ValueError(f"eta + eps must be positive, got {dict(zip(ids, shifted.tolist(), strict=True))}")
    inverse = 1.0 / shifted
    rho = inverse / inverse.sum()
    return dict(zip(ids, rho.tolist(), strict=True))


def uniform_distribution(candidates: Iterable[str]) -> dict[str, float]:
    """The "w/o g" ablation: every candidate drawn equally often (duplicates count once)."""
    ids = _unique(candidates)
    return dict.fromkeys(ids, 1.0 / len(ids))


def distribution_entropy(rho: dict[str, float]) -> float:
    """The Shannon entropy of rho in nats (log of the number of members when uniform)."""
    return -math.fsum(p * math.log(p) for p in rho.values() if p > 0)


def sample_profiles(
    rho: dict[str, float], num_profiles: int, num_partners: int, rng: np.random.Generator
) -> list[tuple[str, ...]]:
    """``num_profiles`` partner profiles, each ``num_partners`` ids drawn i.i.d. from rho.

    Draws are with replacement, so a profile may hold one member in several slots, as the
    weights of rho ask. A profile lists the partner slots in draw order (not a team_key).
    """
    if num_profiles < 0 or num_partners < 0:
        raise ValueError(f"num_profiles and num_partners must be >= 0, got {num_profiles}, {num_partners}")
    ids = list(rho)
    p = np.array([rho[i] for i in ids], dtype=np.float64)
    if not ids or np.any(p < 0) or not p.sum() > 0:
        raise ValueError(f"rho must be a non-empty distribution with non-negative weights, got {rho}")
    draws = rng.choice(len(ids), size=(num_profiles, num_partners), p=p / p.sum())
    return [tuple(ids[j] for j in row) for row in draws]


def missing_hyperedges(
    population: Sequence[str],
    learners: Sequence[str],
    num_ctrl: int,
    num_partners: int,
    known: Iterable[tuple],
) -> list[Team]:
    """The teams touching the learners that have no evaluation yet, as team_keys.

    Each learner fills its ``num_ctrl`` slots and the ``num_partners`` partner slots take
    every multiset of population members other than that learner (with repetition, as
    :func:`sample_profiles` draws them; other learners of the population are partners too).
    Teams already in ``known`` (any slot order) are left out. With n members besides the
    learner that is ``C(n + num_partners - 1, num_partners)`` teams per learner, e.g. 36 for
    n = 8 and 2 partners, 165 for n = 9 and 3: the generation's evaluation budget. Teams in
    which a learner fills other than ``num_ctrl`` slots are never asked for. Order: by
    learner, then lexicographic over the population's order; no duplicates.
    """
    if num_ctrl < 1 or num_partners < 0:
        raise ValueError(f"need num_ctrl >= 1 and num_partners >= 0, got {num_ctrl}, {num_partners}")
    seen = {team_key(team) for team in known}
    members = list(dict.fromkeys(population))
    missing: list[Team] = []
    for learner in dict.fromkeys(learners):
        pool = [m for m in members if m != learner]
        for partners in itertools.combinations_with_replacement(pool, num_partners):
            team = team_key((learner,) * num_ctrl + partners)
            if team not in seen:
                seen.add(team)
                missing.append(team)
    return missing


def update_population(
    population: Sequence[str], eta: dict[str, float], learners: Sequence[str], capacity: int
) -> tuple[list[str], list[str]]:
    """Add the learners; while over ``capacity``, remove the lowest-eta member that is not a learner.

    Ties go to the oldest member, the earliest in ``population``. The learners are always
    kept (so ``capacity`` must hold them all); members keep their order and learners not yet
    in the population are appended. Every member that may be removed must be in ``eta``: a missing id
    is an error rather than a silent eta 0. Returns (new population, removed members in
    order of removal).
    """
    new_learners = list(dict.fromkeys(learners))
    if len(new_learners) > capacity:
        raise ValueError(f"capacity {capacity} cannot hold the {len(new_learners)} learners")
    members = list(dict.fromkeys(population))
    members += [m for m in new_learners if m not in members]
    protected = set(new_learners)
    removed: list[str] = []
    excess = len(members) - capacity
    if excess > 0:
        others = [m for m in members if m not in protected]
        missing = [m for m in others if m not in eta]
        if missing:
            raise KeyError(f"no eta for member(s) {missing}")
        order = sorted(range(len(others)), key=lambda i: (eta[others[i]], i))
        removed = [others[i] for i in order[:excess]]
        members = [m for m in members if m not in set(removed)]
    return members, removed
