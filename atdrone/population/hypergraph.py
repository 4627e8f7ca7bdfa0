"""HOLA-Drone V2 (SPEC section 10; the paper's appendix "HOLA-Drone (V2) Algorithm"): the maths.

Pure functions, so the algorithm module (:mod:`atdrone.population.hola`) reads top to
bottom and every step can be checked against a worked example and a plain reference.

Vocabulary:

- A *member* is a policy of the population Pi, named by a string id.
- A *team* (a hyperedge) is the multiset of member ids filling the pursuer slots, e.g.
  ``("L", "L", "p1", "p3")`` when learner ``L`` fills its N = 2 learner slots next to
  partners ``p1`` and ``p3``. The N learner drones share one policy (IPPO parameter
  sharing, as in self-play and the public HOLA-Drone code), so they are one node: a
  hyperedge's node set is its set of *distinct* members and ``|e|`` their number. The
  canonical form of a team is :func:`team_key`, the sorted tuple.
- A team's *weight* is its mean outcome over its evaluation episodes (with a standard
  error, see :func:`pooled` and :func:`contested_preferences`).

One generation t, as :class:`atdrone.population.hola.Hola` runs it::

    edges = learner_hyperedges(N_t, Pi - N_t, num_ctrl, M)    # G'_t
    ...                                                       # evaluate until contested_preferences is empty
    eta = preference_centrality(weights, nodes)               # in PG'_t / degree in G'_t
    rho = partner_distribution(smoothed_centrality(weights, nodes, prior), Pi - N_t)
    profiles = profile_distribution(rho, M)                   # teams of M distinct members
    ...                                                       # max step: PPO on those draws
    population, removed = update_population(...)              # only with a cap

The "w/o g" ablation replaces rho by :func:`uniform_distribution`.

*Degree.* The appendix's "degree of node i in G" is read as the sum over the hyperedges
e containing i of ``|e| - 1`` (the number of (hyperedge, co-member) incidences), not the
number of hyperedges containing i. Reason: every node counted in i's in-degree is a
co-member of i in some hyperedge, so in-degree <= sum of ``|e| - 1`` and eta stays in
[0, 1]. With the count reading a node in one hyperedge of four members that all three
others prefer has eta = 3 / 1.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Sequence

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


def check_finite(weights: dict[Team, float], what: str = "weight") -> None:
    """ValueError naming the team when a weight is NaN or infinite: it would silently decide a preference."""
    for team, value in weights.items():
        if not math.isfinite(value):
            raise ValueError(f"hyperedge {list(team)} has {what} {value!r}: preferences need finite weights")


def preference_hypergraph(weights: dict[Team, float], rng: np.random.Generator | None = None) -> dict[str, Team]:
    """Each node's single outgoing hyperedge: the highest-weight team it belongs to.

    Ties go to the lowest team_key, so the graph depends on the weights only, unless
    ``rng`` is given: then tied teams are ordered by a random permutation drawn from it
    (the generation's generator), so no member wins ties by its name. A team with one
    distinct member (self-play: the member fills every slot) links the node to no one,
    and carries no degree either (``|e| - 1 = 0``), so it is never a preference: a node
    whose only teams are such teams gets no outgoing edge and is absent from the result.
    Keys are node ids, sorted. A NaN or infinite weight is a ValueError.
    """
    check_finite(weights)
    order = sorted(weights)
    rank = dict(zip(order, rng.permutation(len(order)).tolist(), strict=True)) if rng is not None else {}
    preferred: dict[str, Team] = {}
    for team in sorted(weights, key=lambda t: (-weights[t], rank.get(t, 0), t)):
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


def preference_centrality(
    weights: dict[Team, float], nodes: Iterable[str] | None = None, rng: np.random.Generator | None = None
) -> dict[str, float]:
    """eta(i) = in-degree of i in the preference hypergraph / degree of i in the hypergraph.

    eta is in [0, 1]: every j counted in i's in-degree is another member of a hyperedge e
    containing i, and e holds at most ``|e| - 1`` such j, which is e's share of degree(i).
    A high eta marks a member many others choose as a teammate; a low one, a member nobody
    picks. Nodes of degree 0 (only self-play teams, or no team at all) get eta 0; ``nodes``
    adds such members with no evaluated team. Keys: every node of ``weights`` and ``nodes``,
    sorted.
    """
    degree = hypergraph_degrees(weights)
    in_degree = preference_in_degrees(preference_hypergraph(weights, rng))
    everyone = set(degree) | set(nodes or ())
    return {
        node: in_degree.get(node, 0) / degree[node] if degree.get(node, 0) > 0 else 0.0 for node in sorted(everyone)
    }


def smoothed_centrality(
    weights: dict[Team, float],
    nodes: Iterable[str],
    prior: float,
    centre: float = 0.5,
    rng: np.random.Generator | None = None,
) -> dict[str, float]:
    """eta with a prior count: ``(in-degree + 2 prior centre) / (degree + 2 prior)``.

    With ``centre`` 1/2 that is ``(in-degree + prior) / (degree + 2 prior)``, Laplace's rule
    for prior = 1; :func:`mean_centrality` gives the centre HOLA uses by default, the
    candidates' mean raw eta, so a member with few hyperedges shrinks towards a typical
    member, not towards 1/2 (typical eta is about 1 / (n - 1)).

    The min step needs 1 / eta, which the raw eta of a member nobody prefers (in-degree
    0) makes infinite. The prior counts ``prior`` virtual preferences out of ``2 prior``
    virtual opportunities, so eta is in (0, 1) and shrinks toward 1/2 where a member has
    few hyperedges. In G'_t every non-learner has the same degree d (when every
    hyperedge is played), so rho is proportional to ``1 / (in-degree + prior)``: a member
    nobody prefers is drawn ``(d eta + prior) / prior`` times as often as one of eta
    ``eta``, e.g. 3x for d = 4, eta = 0.5, prior = 1 (one such member among three at 0.5
    gets rho = 3 / 6 = 0.5). ``prior`` must be > 0.
    """
    if not prior > 0:
        raise ValueError(f"prior must be > 0, got {prior}")
    if not 0 < centre <= 1:
        raise ValueError(f"centre must be in (0, 1], got {centre}")
    degree = hypergraph_degrees(weights)
    in_degree = preference_in_degrees(preference_hypergraph(weights, rng))
    everyone = set(degree) | set(nodes)
    return {n: (in_degree.get(n, 0) + 2 * prior * centre) / (degree.get(n, 0) + 2 * prior) for n in sorted(everyone)}


def mean_centrality(
    weights: dict[Team, float], candidates: Iterable[str], rng: np.random.Generator | None = None
) -> float:
    """The mean raw eta of the candidates that have a hyperedge (1/2 when none has any in-degree)."""
    eta = preference_centrality(weights, rng=rng)
    degree = hypergraph_degrees(weights)
    values = [eta[c] for c in dict.fromkeys(candidates) if degree.get(c, 0) > 0]
    mean = float(np.mean(values)) if values else 0.0
    return mean if mean > 0 else 0.5


def softmin_profiles(weights: dict[Team, float], learners: Sequence[str], temperature: float) -> dict[Team, float]:
    """The appendix's mixed strategy: the learners' hyperedges as partner profiles, P proportional to
    exp(-(w - min w) / temperature) (a softmin of the learners' outcomes: an entropy-regularised
    minimiser), averaged over learners. Keys: the profiles (partners of each hyperedge, sorted)."""
    if not temperature > 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    check_finite(weights)
    out: dict[Team, float] = {}
    for learner in dict.fromkeys(learners):
        own = {t: w for t, w in weights.items() if learner in t}
        if not own:
            continue
        low = min(own.values())
        mass = {t: math.exp(-(w - low) / temperature) for t, w in own.items()}
        total = math.fsum(mass.values())
        for team, m in mass.items():
            profile = tuple(x for x in team if x != learner)
            out[profile] = out.get(profile, 0.0) + m / total
    if not out:
        raise ValueError(f"no hyperedge of the learners {list(learners)}")
    total = math.fsum(out.values())
    return {p: v / total for p, v in out.items()}


def softmin_rho(
    weights: dict[Team, float],
    learners: Sequence[str],
    candidates: Iterable[str],
    num_partners: int,
    temperature: float,
) -> tuple[dict[str, float], dict[Team, float]]:
    """rho over ``candidates`` under the softmin (each member's share of the ``num_partners`` partner slots
    of :func:`softmin_profiles`), and those profiles."""
    draws = softmin_profiles(weights, learners, temperature)
    shares = member_shares(draws)
    return {m: shares.get(m, 0.0) / num_partners for m in candidates}, draws


def rho_statistics(rhos: Iterable[dict[str, float]]) -> dict[str, float]:
    """Over draws of rho: the mean and standard deviation (ddof 1) of its entropy, the mean of its largest
    value, and the number of draws."""
    entropies, largest = [], []
    for rho in rhos:
        entropies.append(distribution_entropy(rho))
        largest.append(max(rho.values()))
    return {
        "entropy": float(np.mean(entropies)),
        "entropy_sd": float(np.std(entropies, ddof=1)) if len(entropies) > 1 else 0.0,
        "max_rho": float(np.mean(largest)),
        "trials": float(len(entropies)),
    }


def null_rho(
    weights: dict[Team, float],
    rho_of: Callable[[dict[Team, float]], dict[str, float]],
    rng: np.random.Generator,
    trials: int = 200,
) -> dict[str, float]:
    """What the min step gives with no signal: ``rho_of`` the measured weights permuted at random
    over the same hyperedges (the same design and scale, no link between a team and its outcome).

    Returns :func:`rho_statistics` over ``trials`` permutations: the baseline a measured rho must
    differ from before it can be said to have found a preference (at generation 1 the in-degrees
    are largely fixed by the design, whatever the weights).
    """
    check_finite(weights)
    keys, values = list(weights), np.array(list(weights.values()), dtype=np.float64)
    return rho_statistics(rho_of(dict(zip(keys, rng.permutation(values).tolist(), strict=True))) for _ in range(trials))


def _unique(candidates: Iterable[str]) -> list[str]:
    ids = list(dict.fromkeys(candidates))
    if not ids:
        raise ValueError("no candidates to draw partners from")
    return ids


def partner_distribution(eta: dict[str, float], candidates: Iterable[str]) -> dict[str, float]:
    """The min step: rho over ``candidates`` (Pi minus N_t), the normalised reciprocal of eta.

    The members nobody likes to play with (low eta) get the most mass: the worst-case
    partners. eta must be positive for every candidate (use :func:`smoothed_centrality`);
    a candidate missing from ``eta`` is an error rather than a silent eta. Duplicate
    candidates count once; keys keep the candidates' order.
    """
    ids = _unique(candidates)
    missing = [c for c in ids if c not in eta]
    if missing:
        raise KeyError(f"no eta for candidate(s) {missing}")
    values = np.array([eta[c] for c in ids], dtype=np.float64)
    if not np.all(values > 0):
        raise ValueError(
            f"eta must be positive to take its reciprocal, got {dict(zip(ids, values.tolist(), strict=True))}"
        )
    inverse = 1.0 / values
    return dict(zip(ids, (inverse / inverse.sum()).tolist(), strict=True))


def uniform_distribution(candidates: Iterable[str]) -> dict[str, float]:
    """The "w/o g" ablation: every candidate equally likely (duplicates count once)."""
    ids = _unique(candidates)
    return dict.fromkeys(ids, 1.0 / len(ids))


def distribution_entropy(rho: dict[str, float]) -> float:
    """The Shannon entropy of rho in nats (log of the number of members when uniform)."""
    return -math.fsum(p * math.log(p) for p in rho.values() if p > 0)


def _subsets(ids: Sequence[str], size: int) -> Iterable[tuple[str, ...]]:
    """M-subsets of distinct members; multisets when there are fewer members than slots."""
    if len(ids) >= size:
        return itertools.combinations(ids, size)
    return itertools.combinations_with_replacement(ids, size)


def profile_distribution(rho: dict[str, float], num_partners: int) -> dict[Team, float]:
    """``M ~ rho`` as teams: P(profile) proportional to the product of rho over its members.

    A profile is ``num_partners`` *distinct* members of rho's support (every
    ``num_partners``-subset; multisets when the pool has fewer members than slots), so an
    episode never puts one partner policy in two slots while others are available. The
    product form keeps rho's order (a member with more rho is in more profiles) and makes
    the drawn profiles testable against exact probabilities. Keys: profiles in the
    order of rho's keys; values sum to 1.
    """
    if num_partners < 1:
        raise ValueError(f"num_partners must be >= 1, got {num_partners}")
    ids = [m for m, p in rho.items() if p > 0]
    if not ids or not all(p >= 0 for p in rho.values()):  # also refuses NaN
        raise ValueError(f"rho must be a distribution with some positive mass, got {rho}")
    weights = {profile: math.prod(rho[m] for m in profile) for profile in _subsets(ids, num_partners)}
    total = math.fsum(weights.values())
    return {profile: w / total for profile, w in weights.items()}


def member_shares(profiles: dict[Team, float]) -> dict[str, float]:
    """The expected partner slots per episode each member fills under a profile distribution (sums to M).

    With distinct members this is the share of episodes the member plays in.
    """
    share: dict[str, float] = {}
    for profile, p in profiles.items():
        for m in profile:
            share[m] = share.get(m, 0.0) + p
    return share


def learner_hyperedges(learners: Sequence[str], others: Sequence[str], num_ctrl: int, num_partners: int) -> list[Team]:
    """The hyperedges of G'_t in slot order: each learner in its ``num_ctrl`` slots with every M-subset of ``others``.

    ``others`` is Pi minus N_t; M = ``num_partners`` distinct members per team (multisets
    when there are fewer than M others, as :func:`profile_distribution` draws them). With
    n others that is C(n, M) teams per learner, e.g. 28 for n = 8 and M = 2.
    """
    if num_ctrl < 1 or num_partners < 1:
        raise ValueError(f"need num_ctrl >= 1 and num_partners >= 1, got {num_ctrl}, {num_partners}")
    pool = [m for m in dict.fromkeys(others) if m not in set(learners)]
    if not pool:
        raise ValueError("Pi minus N_t is empty: no partners to build hyperedges with")
    return [
        (learner,) * num_ctrl + profile
        for learner in dict.fromkeys(learners)
        for profile in _subsets(pool, num_partners)
    ]


def pooled(batches: Iterable[tuple[int, float, float]]) -> tuple[float, float, int]:
    """(mean, standard error, n) of the episodes of several batches, each (n, mean, sample variance).

    The pooled sample variance is exact (within-batch plus between-batch sums of squares),
    so a team's weight and its error do not depend on how its episodes were split. For a
    success rate the batch variance is the Bernoulli sample variance ``n p (1 - p) / (n - 1)``.
    """
    rows = [(int(n), float(m), float(v)) for n, m, v in batches]
    total = sum(n for n, _, _ in rows)
    if total < 2:
        raise ValueError(f"need at least 2 episodes for a standard error, got {total}")
    mean = math.fsum(n * m for n, m, _ in rows) / total
    squares = math.fsum((n - 1) * v + n * (m - mean) ** 2 for n, m, v in rows)
    return mean, math.sqrt(squares / (total - 1) / total), total


def uncertain_softmin(
    stats: dict[Team, tuple[float, float]], learners: Sequence[str], temperature: float, z: float, reach: float = 3.0
) -> set[Team]:
    """The learners' hyperedges whose softmin mass is not yet measured well enough: those that may hold mass
    (their weight minus ``z`` standard errors is within ``reach`` temperatures of the lowest weight; a
    hyperedge further up gets under exp(-reach) of the top's mass) and whose standard error is over half a
    temperature (their mass is then uncertain by more than a factor exp(z / 2)). The matches worth more
    episodes when rho is the softmin, which reads only the learners' own hyperedges.
    """
    check_finite({t: w for t, (w, _) in stats.items()})
    check_finite({t: se for t, (_, se) in stats.items()}, "standard error")
    own = {t: v for t, v in stats.items() if set(t) & set(learners)}
    if not own:
        return set()
    lowest = min(w for w, _ in own.values())
    return {t for t, (w, se) in own.items() if se > temperature / 2 and w - z * se <= lowest + reach * temperature}


def contested_preferences(stats: dict[Team, tuple[float, float]], z: float) -> dict[str, set[Team]]:
    """The nodes whose preferred hyperedge is not resolved, with the hyperedges that contest it.

    ``stats``: team_key -> (weight, standard error). A node's preferred hyperedge (the
    highest weight among the teams with >= 2 distinct members containing it, as
    :func:`preference_hypergraph`) is *resolved* when it beats each other such team e of
    the node by more than ``z * sqrt(se_best^2 + se_e^2)``. For every unresolved node the
    value holds the preferred hyperedge and its contenders: the matches worth more
    episodes. Equal weights with zero error (e.g. SUC 0 against 0) are unresolved.
    """
    check_finite({t: w for t, (w, _) in stats.items()})
    check_finite({t: se for t, (_, se) in stats.items()}, "standard error")
    by_node: dict[str, list[Team]] = {}
    for team in stats:
        members = _distinct(team)
        if len(members) < 2:
            continue
        for node in members:
            by_node.setdefault(node, []).append(team)
    out: dict[str, set[Team]] = {}
    for node, teams in sorted(by_node.items()):
        best = min(teams, key=lambda t: (-stats[t][0], t))
        w_best, se_best = stats[best]
        close = [t for t in teams if t != best and w_best - stats[t][0] <= z * math.hypot(se_best, stats[t][1])]
        if close:
            out[node] = {best, *close}
    return out


RETIRE_RULES = ("oldest", "lowest_eta")


def update_population(
    population: Sequence[str],
    learners: Sequence[str],
    capacity: int,
    rule: str = "oldest",
    eta: dict[str, float] | None = None,
) -> tuple[list[str], list[str]]:
    """Add the learners; with a ``capacity`` (0: none, the paper's growing population), retire by ``rule``.

    Rules: ``"oldest"`` removes the earliest non-learners of ``population``;
    ``"lowest_eta"`` (the public HOLA-Drone code) the lowest-eta ones, ties to the oldest,
    and every removable member must be in ``eta``. Learners are always kept. Returns
    (new population, removed members in order of removal).
    """
    if rule not in RETIRE_RULES:
        raise ValueError(f"rule must be one of {RETIRE_RULES}, got {rule!r}")
    new_learners = list(dict.fromkeys(learners))
    if capacity and len(new_learners) > capacity:
        raise ValueError(f"capacity {capacity} cannot hold the {len(new_learners)} learners")
    members = list(dict.fromkeys(population))
    members += [m for m in new_learners if m not in members]
    excess = len(members) - capacity if capacity else 0
    if excess <= 0:
        return members, []
    others = [m for m in members if m not in set(new_learners)]
    if rule == "lowest_eta":
        eta = eta or {}
        missing = [m for m in others if m not in eta]
        if missing:
            raise KeyError(f"no eta for member(s) {missing}")
        others = [others[i] for i in sorted(range(len(others)), key=lambda i: (eta[others[i]], i))]
    removed = others[:excess]
    return [m for m in members if m not in set(removed)], removed
