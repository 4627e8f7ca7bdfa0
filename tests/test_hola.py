"""HOLA-Drone V2 (atdrone.population.hypergraph): worked examples computed by hand, and plain references.

Every expected value below is derived by hand in the comments from the definitions of the
paper's appendix ("HOLA-Drone (V2) Algorithm") and the module's docstrings, not copied from
a run of the code.
"""

from __future__ import annotations

import itertools
import math
from fractions import Fraction

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from atdrone.config import ConfigError
from atdrone.population.hola import Hola, HolaConfig
from atdrone.population.hypergraph import (
    contested_preferences,
    distribution_entropy,
    hyperedge_weights,
    hypergraph_degrees,
    learner_hyperedges,
    member_shares,
    partner_distribution,
    pooled,
    preference_centrality,
    preference_hypergraph,
    preference_in_degrees,
    profile_distribution,
    smoothed_centrality,
    team_key,
    uniform_distribution,
    update_population,
)
from atdrone.teams.partners import Profiles, profiles

NAN = float("nan")


def approx(expected, rel=1e-12):
    """pytest.approx of a Fraction (or a dict of them) as floats."""
    if isinstance(expected, dict):
        return pytest.approx({k: float(v) for k, v in expected.items()}, rel=rel, abs=1e-15)
    return pytest.approx(float(expected), rel=rel, abs=1e-15)


# ==================================================================================
# 1. A general match table: 4 members A, B, C, D in teams of 3 slots (slot order shuffled on purpose).
# ==================================================================================

HAND_ROWS = [
    (("A", "A", "B"), 0.5),
    (("B", "A", "A"), 1.0),  # AAB: (0.5 + 1.0) / 2 = 0.75
    (("A", "B", "C"), 0.5),
    (("C", "B", "A"), NAN),  # ABC: the NaN row is left out -> 0.5
    (("C", "A", "D"), 0.75),
    (("A", "D", "C"), 1.0),  # ACD: 0.875
    (("B", "C", "C"), 0.25),  # BCC: 0.25
    (("B", "D", "D"), 0.5),
    (("D", "B", "D"), 1.0),
    (("D", "D", "B"), 0.75),  # BDD: 2.25 / 3 = 0.75, ties with AAB
    (("D", "D", "D"), 1.0),  # DDD: self-play, 1.0, the best weight of all but one distinct member
    (("C", "C", "D"), NAN),  # CCD: only a NaN row -> no hyperedge
]
HAND_WEIGHTS = {
    ("A", "A", "B"): 0.75,
    ("A", "B", "C"): 0.5,
    ("A", "C", "D"): 0.875,
    ("B", "C", "C"): 0.25,
    ("B", "D", "D"): 0.75,
    ("D", "D", "D"): 1.0,
}
# Preferred hyperedge (best team with >= 2 distinct members; ties -> lowest team_key):
#   A: AAB .75, ABC .5, ACD .875                 -> ACD
#   B: AAB .75, ABC .5, BCC .25, BDD .75         -> AAB (ties with BDD; ("A","A","B") < ("B","D","D"))
#   C: ABC .5, ACD .875, BCC .25                 -> ACD
#   D: ACD .875, BDD .75 (DDD 1.0 is self-play)  -> ACD (it would be DDD if self-play counted)
HAND_PREFERRED = {"A": ("A", "C", "D"), "B": ("A", "A", "B"), "C": ("A", "C", "D"), "D": ("A", "C", "D")}
# In-degree: the other nodes whose preferred team contains the node.
#   A: B (AAB), C (ACD), D (ACD) -> 3;  B: nobody -> 0 (absent);  C: A, D -> 2;  D: A, C -> 2
HAND_IN_DEGREES = {"A": 3, "C": 2, "D": 2}
# Degree: sum over its teams of |distinct members| - 1.
#   A: AAB 1 + ABC 2 + ACD 2 = 5;  B: AAB 1 + ABC 2 + BCC 1 + BDD 1 = 5
#   C: ABC 2 + ACD 2 + BCC 1 = 5;  D: ACD 2 + BDD 1 + DDD 0 = 3
HAND_DEGREES = {"A": 5, "B": 5, "C": 5, "D": 3}
# eta = in-degree / degree; E (passed in nodes=, no team) -> 0.
HAND_ETA = {"A": Fraction(3, 5), "B": Fraction(0), "C": Fraction(2, 5), "D": Fraction(2, 3), "E": Fraction(0)}
# Smoothed with prior 1, (in + 1) / (degree + 2); E: degree 0 -> 1/2.
#   A: 4/7;  B: 1/7;  C: 3/7;  D: 3/5;  E: 1/2
HAND_SMOOTHED = {
    "A": Fraction(4, 7),
    "B": Fraction(1, 7),
    "C": Fraction(3, 7),
    "D": Fraction(3, 5),
    "E": Fraction(1, 2),
}


def hand_table() -> pd.DataFrame:
    return pd.DataFrame({"team": [list(t) for t, _ in HAND_ROWS], "score": [s for _, s in HAND_ROWS]})


def test_team_key_sorts_and_keeps_duplicates():
    assert team_key(["p3", "L", "p1", "L"]) == ("L", "L", "p1", "p3")
    assert team_key(np.array(["b", "a"])) == ("a", "b")


def test_hyperedge_weights_refuses_a_table_without_its_columns():
    with pytest.raises(ValueError, match="score"):
        hyperedge_weights(pd.DataFrame({"team": [["A", "B"]], "REW": [1.0]}))


def test_match_table_weights_preferences_degrees_and_eta():
    weights = hyperedge_weights(hand_table())
    assert weights == HAND_WEIGHTS
    assert preference_hypergraph(weights) == HAND_PREFERRED
    assert preference_hypergraph(dict(reversed(weights.items()))) == HAND_PREFERRED  # ties: by key, not dict order
    assert preference_in_degrees(HAND_PREFERRED) == HAND_IN_DEGREES
    assert hypergraph_degrees(weights) == HAND_DEGREES
    assert preference_centrality(weights, nodes=["E"]) == approx(HAND_ETA)
    assert smoothed_centrality(weights, ["E"], 1.0) == approx(HAND_SMOOTHED)
    # prior 2: (in + 2) / (degree + 4): A 5/9, B 2/9, C 4/9, D 4/7, E 1/2
    assert smoothed_centrality(weights, ["E"], 2.0) == approx(
        {"A": Fraction(5, 9), "B": Fraction(2, 9), "C": Fraction(4, 9), "D": Fraction(4, 7), "E": Fraction(1, 2)}
    )


def test_match_table_partner_distribution_in_exact_fractions():
    eta = {node: float(value) for node, value in HAND_ETA.items()}
    # Raw eta over A, C, D: 1/eta = 5/3, 5/2, 3/2, total 17/3 -> rho = 5/17, 15/34, 9/34
    rho = partner_distribution(eta, ["A", "C", "D"])
    assert rho == approx({"A": Fraction(5, 17), "C": Fraction(15, 34), "D": Fraction(9, 34)})
    assert list(rho) == ["A", "C", "D"]
    # Smoothed over B, C, D: 1/eta = 7, 7/3, 5/3, total 33/3 = 11 -> 7/11, 7/33, 5/33
    rho = partner_distribution(smoothed_centrality(HAND_WEIGHTS, [], 1.0), ["B", "C", "D"])
    assert rho == approx({"B": Fraction(7, 11), "C": Fraction(7, 33), "D": Fraction(5, 33)})


def test_entropy_in_nats():
    assert distribution_entropy(uniform_distribution(["A", "B", "C", "D", "A"])) == pytest.approx(math.log(4))
    assert uniform_distribution(["A", "B", "A"]) == {"A": 0.5, "B": 0.5}
    assert distribution_entropy({"A": 1.0, "B": 0.0}) == 0.0
    # 1/2, 1/4, 1/4: 1/2 ln 2 + 2 * 1/4 ln 4 = 1.5 ln 2
    assert distribution_entropy({"A": 0.5, "B": 0.25, "C": 0.25}) == pytest.approx(1.5 * math.log(2), rel=1e-12)


# ==================================================================================
# 2. The appendix's G'_t, by hand: learner L (its N = 2 drones share one policy: one node)
#    and non-learners a, b, c, d; M = 2 partners.
# ==================================================================================

G_OTHERS = ["a", "b", "c", "d"]
# Every 2-subset of {a, b, c, d} next to L's two slots: C(4, 2) = 6 teams, L's slots first.
G_EDGES = [
    ("L", "L", "a", "b"),
    ("L", "L", "a", "c"),
    ("L", "L", "a", "d"),
    ("L", "L", "b", "c"),
    ("L", "L", "b", "d"),
    ("L", "L", "c", "d"),
]
# Weights chosen by hand ("L" < "a" in sorting, so every team is its own team_key):
G_WEIGHTS = {
    ("L", "L", "a", "b"): 0.9,
    ("L", "L", "a", "c"): 0.4,
    ("L", "L", "a", "d"): 0.7,
    ("L", "L", "b", "c"): 0.9,  # ties with LLab
    ("L", "L", "b", "d"): 0.2,
    ("L", "L", "c", "d"): 0.8,
}
# Preference hypergraph (best team; ties -> lowest team_key):
#   L: all six; 0.9 for LLab and LLbc -> LLab (lower key)
#   a: LLab .9, LLac .4, LLad .7 -> LLab
#   b: LLab .9, LLbc .9, LLbd .2 -> LLab (tie, lower key)
#   c: LLac .4, LLbc .9, LLcd .8 -> LLbc
#   d: LLad .7, LLbd .2, LLcd .8 -> LLcd
G_PREFERRED = {
    "L": ("L", "L", "a", "b"),
    "a": ("L", "L", "a", "b"),
    "b": ("L", "L", "a", "b"),
    "c": ("L", "L", "b", "c"),
    "d": ("L", "L", "c", "d"),
}
# In-degree (other nodes whose preferred team holds the node; L's two slots count once):
#   L: a, b, c, d (every team holds L) -> 4
#   a: L, b (LLab) -> 2;  b: L, a (LLab), c (LLbc) -> 3;  c: d (LLcd) -> 1;  d: nobody -> 0 (absent)
G_IN = {"L": 4, "a": 2, "b": 3, "c": 1}
# Degree: every team has |e| = 3 distinct members (L, x, y), so |e| - 1 = 2 per team.
#   L is in 6 teams -> 12;  each of a..d is in 3 teams (one per other partner) -> 6
G_DEGREE = {"L": 12, "a": 6, "b": 6, "c": 6, "d": 6}
# Raw eta = in / degree: L 4/12 = 1/3, a 2/6 = 1/3, b 3/6 = 1/2, c 1/6, d 0
G_ETA = {"L": Fraction(1, 3), "a": Fraction(1, 3), "b": Fraction(1, 2), "c": Fraction(1, 6), "d": Fraction(0)}
# Smoothed, prior 1, (in + 1) / (degree + 2): L 5/14, a 3/8, b 4/8 = 1/2, c 2/8 = 1/4, d 1/8
G_SMOOTHED = {"L": Fraction(5, 14), "a": Fraction(3, 8), "b": Fraction(1, 2), "c": Fraction(1, 4), "d": Fraction(1, 8)}
# rho over a..d: reciprocals 8/3, 2, 4, 8, total 50/3 ->
#   a (8/3)(3/50) = 8/50 = 4/25;  b 6/50 = 3/25;  c 12/50 = 6/25;  d 24/50 = 12/25   (4 + 3 + 6 + 12 = 25)
# (equal degree 6, so rho is proportional to 1 / (in + 1) = 1/3, 1/4, 1/2, 1, i.e. 4 : 3 : 6 : 12)
G_RHO = {"a": Fraction(4, 25), "b": Fraction(3, 25), "c": Fraction(6, 25), "d": Fraction(12, 25)}
# Profiles, P({x, y}) proportional to rho(x) rho(y); in units of 1/625:
#   ab 4*3 = 12, ac 4*6 = 24, ad 4*12 = 48, bc 3*6 = 18, bd 3*12 = 36, cd 6*12 = 72; total 210
#   -> ab 12/210 = 2/35, ac 4/35, ad 8/35, bc 3/35, bd 6/35, cd 12/35   (2 + 4 + 8 + 3 + 6 + 12 = 35)
G_PROFILES = {
    ("a", "b"): Fraction(2, 35),
    ("a", "c"): Fraction(4, 35),
    ("a", "d"): Fraction(8, 35),
    ("b", "c"): Fraction(3, 35),
    ("b", "d"): Fraction(6, 35),
    ("c", "d"): Fraction(12, 35),
}
# Member shares (sum of the profiles holding the member; they sum to M = 2):
#   a: 2 + 4 + 8 = 14/35 = 2/5;  b: 2 + 3 + 6 = 11/35;  c: 4 + 3 + 12 = 19/35;  d: 8 + 6 + 12 = 26/35
G_SHARES = {"a": Fraction(2, 5), "b": Fraction(11, 35), "c": Fraction(19, 35), "d": Fraction(26, 35)}


def test_gprime_hyperedges_are_the_learner_with_every_pair_of_others():
    assert learner_hyperedges(["L"], G_OTHERS, 2, 2) == G_EDGES
    assert all(team_key(e) == e for e in G_EDGES)


def test_gprime_worked_example_from_weights_to_profiles():
    weights = {team_key(e): G_WEIGHTS[e] for e in learner_hyperedges(["L"], G_OTHERS, 2, 2)}
    assert set(weights) == set(G_EDGES)
    preferred = preference_hypergraph(weights)
    assert preferred == G_PREFERRED
    assert preference_in_degrees(preferred) == G_IN
    assert hypergraph_degrees(weights) == G_DEGREE
    population = ["L", *G_OTHERS]
    assert preference_centrality(weights, nodes=population) == approx(G_ETA)
    smoothed = smoothed_centrality(weights, population, 1.0)
    assert smoothed == approx(G_SMOOTHED)
    rho = partner_distribution(smoothed, G_OTHERS)
    assert list(rho) == G_OTHERS
    assert rho == approx(G_RHO)
    draws = profile_distribution(rho, 2)
    assert list(draws) == list(G_PROFILES)  # in the order of rho's keys
    assert draws == approx(G_PROFILES)
    assert member_shares(draws) == approx(G_SHARES)
    # Entropy of rho: -(4/25 ln 4/25 + 3/25 ln 3/25 + 6/25 ln 6/25 + 12/25 ln 12/25)
    #   = .16 * 1.8326 + .12 * 2.1203 + .24 * 1.4271 + .48 * 0.7340 = .2932 + .2544 + .3425 + .3523, about 1.2425 nats
    expected = -sum(p * math.log(p) for p in (0.16, 0.12, 0.24, 0.48))
    assert distribution_entropy(rho) == pytest.approx(expected, rel=1e-12)
    assert 1.24 < expected < 1.245 < math.log(4)  # less than uniform over four members
    # The "w/o g" ablation: uniform over the same candidates, entropy ln 4.
    assert distribution_entropy(uniform_distribution(G_OTHERS)) == pytest.approx(math.log(4), rel=1e-12)
    # Raw eta cannot be inverted: d is at 0.
    with pytest.raises(ValueError, match="positive"):
        partner_distribution(preference_centrality(weights, nodes=population), G_OTHERS)


def test_gprime_worked_example_with_prior_two():
    # (in + 2) / (6 + 4): a 4/10, b 5/10, c 3/10, d 2/10 -> reciprocals 5/2, 2, 10/3, 5; total 77/6
    #   a (5/2)(6/77) = 15/77;  b 12/77;  c 20/77;  d 30/77   (15 + 12 + 20 + 30 = 77)
    smoothed = smoothed_centrality(G_WEIGHTS, ["L", *G_OTHERS], 2.0)
    expected = {"a": Fraction(15, 77), "b": Fraction(12, 77), "c": Fraction(20, 77), "d": Fraction(30, 77)}
    assert partner_distribution(smoothed, G_OTHERS) == approx(expected)


# ==================================================================================
# 3. The eta = 0 rule: a prior count keeps 1 / eta finite without handing all the mass over.
# ==================================================================================


def equal_degree_table(d: int, k: int) -> dict[tuple[str, ...], float]:
    """w, whom nobody prefers, and k members x0.. at eta 1/2; every one of them has degree d.

    d hubs H0.. form one team of weight 1 (so no hub prefers a pair); w pairs (weight 0.5)
    with every hub; each x pairs with d/2 hubs and with d/2 fans, each fan playing only
    that pair (so it prefers it). Pairs have |e| - 1 = 1, so degree(w) = d,
    degree(x) = d/2 + d/2 = d, in-degree(w) = 0, in-degree(x) = d/2 (its fans): eta(x) = 1/2.
    The candidates' own preferences point at hubs or fans, never at another candidate.
    """
    hubs = [f"H{i}" for i in range(d)]
    weights = {team_key(hubs): 1.0}
    for hub in hubs:
        weights[team_key(["w", hub])] = 0.5
    for j in range(k):
        x = f"x{j}"
        for hub in hubs[: d // 2]:
            weights[team_key([x, hub])] = 0.5
        for f in range(d // 2):
            weights[team_key([x, f"fan{j}.{f}"])] = 0.5
    return weights


@pytest.mark.parametrize(
    ("d", "k", "prior"),
    [
        (4, 3, Fraction(1)),  # the docstring's case: (2 + 1) / (3 + 3) = 1/2
        (2, 1, Fraction(1)),  # (1 + 1) / (2 + 1) = 2/3
        (6, 2, Fraction(1)),  # (3 + 1) / (4 + 2) = 2/3
        (6, 1, Fraction(1)),  # (3 + 1) / (4 + 1) = 4/5
        (4, 3, Fraction(2)),  # (2 + 2) / (4 + 3 * 2) = 2/5
        (4, 1, Fraction(1, 2)),  # (2 + 1/2) / (5/2 + 1/2) = 5/6
    ],
)
def test_member_nobody_prefers_gets_the_documented_share(d, k, prior):
    weights = equal_degree_table(d, k)
    candidates = ["w", *(f"x{j}" for j in range(k))]
    degree = hypergraph_degrees(weights)
    assert all(degree[c] == d for c in candidates)
    eta = preference_centrality(weights)
    assert eta["w"] == 0.0 and all(eta[c] == 0.5 for c in candidates[1:])
    rho = partner_distribution(smoothed_centrality(weights, candidates, float(prior)), candidates)
    # smoothed: w a / (d + 2a), x (d/2 + a) / (d + 2a); rho proportional to 1/a and 1/(d/2 + a), so
    # rho(w) = (1/a) / (1/a + k / (d/2 + a)) = (d/2 + a) / (d/2 + a + k a)
    half = Fraction(d, 2)
    share = (half + prior) / (half + prior + k * prior)
    assert rho["w"] == approx(share)
    assert all(rho[c] == approx((1 - share) / k) for c in candidates[1:])
    assert rho["w"] / rho["x0"] == approx((half + prior) / prior)  # "(d eta + prior) / prior times as often"
    assert rho["w"] < 0.9


def test_member_nobody_prefers_in_the_docstring_case():
    weights = equal_degree_table(4, 3)
    candidates = ["w", "x0", "x1", "x2"]
    # smoothed: w 1/6, x 3/6 -> reciprocals 6, 2, 2, 2 -> w 6/12 = 1/2, each x 2/12 = 1/6
    rho = partner_distribution(smoothed_centrality(weights, candidates, 1.0), candidates)
    assert rho == approx({"w": Fraction(1, 2), "x0": Fraction(1, 6), "x1": Fraction(1, 6), "x2": Fraction(1, 6)})
    assert rho["w"] < 0.9


def test_smoothed_centrality_and_partner_distribution_refusals():
    for prior in (0.0, -1.0, NAN):
        with pytest.raises(ValueError, match="prior"):
            smoothed_centrality(G_WEIGHTS, G_OTHERS, prior)
    with pytest.raises(ValueError, match="positive"):
        partner_distribution({"a": 0.5, "b": 0.0}, ["a", "b"])
    with pytest.raises(ValueError, match="positive"):
        partner_distribution({"a": 0.5, "b": -0.25}, ["a", "b"])
    with pytest.raises(KeyError, match="z"):
        partner_distribution({"a": 0.5, "b": 0.25}, ["a", "z"])
    with pytest.raises(ValueError, match="no candidates"):
        partner_distribution({"a": 0.5}, [])
    # Duplicates count once: 1/0.5 = 2 and 1/0.25 = 4 -> 1/3, 2/3
    assert partner_distribution({"a": 0.5, "b": 0.25}, ["a", "b", "a"]) == approx(
        {"a": Fraction(1, 3), "b": Fraction(2, 3)}
    )


# ==================================================================================
# 4. Plain references on random tables.
# ==================================================================================


def plain_weights(rows):
    totals, counts = {}, {}
    for team, score in rows:
        if math.isnan(score):
            continue
        key = tuple(sorted(team))
        totals[key] = totals.get(key, 0.0) + score
        counts[key] = counts.get(key, 0) + 1
    return {key: totals[key] / counts[key] for key in totals}


def plain_nodes(weights):
    nodes = []
    for team in weights:
        for member in team:
            if member not in nodes:
                nodes.append(member)
    return nodes


def plain_preferences(weights):
    preferred = {}
    for node in plain_nodes(weights):
        best = None
        for team, weight in weights.items():
            if node not in team or len(set(team)) < 2:
                continue
            if best is None or weight > weights[best] or (weight == weights[best] and team < best):
                best = team
        if best is not None:
            preferred[node] = best
    return preferred


def plain_degree(weights, node):
    degree = 0
    for team in weights:
        if node in team:
            degree += len(set(team)) - 1
    return degree


def plain_in_degree(preferred, node):
    count = 0
    for source, team in preferred.items():
        if source != node and node in team:
            count += 1
    return count


def plain_eta(weights, extra_nodes):
    preferred = plain_preferences(weights)
    eta = {}
    for node in plain_nodes(weights) + list(extra_nodes):
        degree = plain_degree(weights, node)
        eta[node] = plain_in_degree(preferred, node) / degree if degree > 0 else 0.0
    return eta


def plain_smoothed(weights, extra_nodes, prior):
    preferred = plain_preferences(weights)
    out = {}
    for node in plain_nodes(weights) + list(extra_nodes):
        out[node] = (plain_in_degree(preferred, node) + prior) / (plain_degree(weights, node) + 2 * prior)
    return out


def plain_rho(eta, candidates):
    inverse = {}
    for candidate in candidates:
        inverse[candidate] = 1.0 / eta[candidate]
    total = sum(inverse.values())
    return {candidate: value / total for candidate, value in inverse.items()}


def plain_choose(ids, size, repeat):
    """Every size-combination of ids in their order (with repetition when repeat)."""
    if size == 0:
        return [()]
    out = []
    for i, first in enumerate(ids):
        rest = ids[i:] if repeat else ids[i + 1 :]
        for tail in plain_choose(rest, size - 1, repeat):
            out.append((first, *tail))
    return out


def plain_profiles(rho, num_partners):
    ids = [m for m in rho if rho[m] > 0]
    weights = {}
    for profile in plain_choose(ids, num_partners, repeat=len(ids) < num_partners):
        product = 1.0
        for member in profile:
            product *= rho[member]
        weights[profile] = product
    total = sum(weights.values())
    return {profile: w / total for profile, w in weights.items()}


WEIGHT_VALUES = st.one_of(st.sampled_from([0.0, 0.25, 0.5, 1.0]), st.floats(-1, 1))


@st.composite
def gprime_tables(draw):
    """A G'_t: 1-2 learners of 1-2 slots, 3-7 non-learners, M in {1, 2, 3}, weights with ties; some unplayed."""
    learners = ["L0", "L1"][: draw(st.integers(1, 2))]
    others = [f"p{i}" for i in range(draw(st.integers(3, 7)))]
    num_ctrl = draw(st.integers(1, 2))
    num_partners = draw(st.sampled_from([1, 2, 3]))
    edges = learner_hyperedges(learners, others, num_ctrl, num_partners)
    full = draw(st.booleans())
    weights = {}
    for edge in edges:
        if full or draw(st.booleans()):
            weights[team_key(edge)] = draw(WEIGHT_VALUES)
    return learners, others, num_ctrl, num_partners, edges, full, weights


@settings(max_examples=60, deadline=None)
@given(table=gprime_tables(), prior=st.sampled_from([1.0, 0.5, 2.0]))
def test_gprime_functions_agree_with_plain_reference(table, prior):
    learners, others, num_ctrl, num_partners, edges, full, weights = table
    # G'_t itself: every learner in its slots with every M-subset of the others.
    expected_edges = [
        (learner,) * num_ctrl + profile for learner in learners for profile in plain_choose(others, num_partners, False)
    ]
    assert edges == expected_edges
    assert len(edges) == len(learners) * math.comb(len(others), num_partners)
    population = learners + others
    preferred = plain_preferences(weights)
    assert preference_hypergraph(weights) == preferred
    assert hypergraph_degrees(weights) == {n: plain_degree(weights, n) for n in sorted(plain_nodes(weights))}
    in_degree = {n: plain_in_degree(preferred, n) for n in sorted(plain_nodes(weights))}
    assert preference_in_degrees(preferred) == {n: v for n, v in in_degree.items() if v > 0}
    eta = preference_centrality(weights, nodes=population)
    assert eta == pytest.approx(plain_eta(weights, population), rel=1e-12)
    assert all(0.0 <= v <= 1.0 for v in eta.values())
    smoothed = smoothed_centrality(weights, population, prior)
    assert smoothed == pytest.approx(plain_smoothed(weights, population, prior), rel=1e-12)
    assert all(0.0 < v < 1.0 for v in smoothed.values())
    rho = partner_distribution(smoothed, others)
    assert list(rho) == others
    assert rho == pytest.approx(plain_rho(smoothed, others), rel=1e-12)
    if full:
        # Every non-learner is in C(n - 1, M - 1) teams per learner, each of |e| = M + 1 distinct members.
        d = len(learners) * math.comb(len(others) - 1, num_partners - 1) * num_partners
        assert all(plain_degree(weights, m) == d for m in others)
        # So rho is proportional to 1 / (in + prior).
        inverse = {m: 1.0 / (in_degree.get(m, 0) + prior) for m in others}
        assert rho == pytest.approx({m: v / sum(inverse.values()) for m, v in inverse.items()}, rel=1e-12)
    draws = profile_distribution(rho, num_partners)
    assert draws == pytest.approx(plain_profiles(rho, num_partners), rel=1e-12)
    assert all(len(set(p)) == num_partners for p in draws)  # 3+ others >= M: distinct members
    assert math.fsum(draws.values()) == pytest.approx(1.0)
    assert math.fsum(member_shares(draws).values()) == pytest.approx(num_partners)


MEMBERS = ["a", "b", "c", "d", "e", "f"]
SCORES = st.one_of(st.sampled_from([0.0, 0.25, 0.5, 0.75, 1.0]), st.floats(-1, 1), st.just(NAN))


@st.composite
def match_rows(draw):
    """Rows (team, score): a few teams of 2-4 slots over 2-6 members, played several times in shuffled slot orders."""
    members = MEMBERS[: draw(st.integers(2, 6))]
    teams = draw(st.lists(st.lists(st.sampled_from(members), min_size=2, max_size=4), min_size=1, max_size=8))
    rows = []
    for _ in range(draw(st.integers(1, 30))):
        team = teams[draw(st.integers(0, len(teams) - 1))]
        rows.append((tuple(draw(st.permutations(team))), draw(SCORES)))
    return rows


@settings(max_examples=80, deadline=None)
@given(rows=match_rows(), extra=st.lists(st.sampled_from(["x", "y"]), unique=True))
def test_match_table_functions_agree_with_plain_reference(rows, extra):
    table = pd.DataFrame({"team": [list(t) for t, _ in rows], "outcome": [s for _, s in rows]})
    weights = hyperedge_weights(table, outcome="outcome")
    expected_weights = plain_weights(rows)
    assert weights == pytest.approx(expected_weights, rel=1e-12, abs=1e-15)
    assert preference_hypergraph(weights) == plain_preferences(expected_weights)
    assert preference_hypergraph(dict(reversed(weights.items()))) == plain_preferences(expected_weights)
    eta = preference_centrality(weights, nodes=extra)
    assert eta == pytest.approx(plain_eta(expected_weights, extra), rel=1e-12)
    assert all(0.0 <= value <= 1.0 for value in eta.values())  # in [0, 1] for any table
    smoothed = smoothed_centrality(weights, extra, 1.0)
    assert smoothed == pytest.approx(plain_smoothed(expected_weights, extra, 1.0), rel=1e-12)
    candidates = sorted(smoothed)
    if not candidates:  # every row NaN and no extra node: nobody to draw
        with pytest.raises(ValueError, match="no candidates"):
            partner_distribution(smoothed, candidates)
        return
    assert partner_distribution(smoothed, candidates) == pytest.approx(plain_rho(smoothed, candidates), rel=1e-12)


@settings(max_examples=80, deadline=None)
@given(
    eta=st.dictionaries(
        st.sampled_from(MEMBERS), st.sampled_from([0.2, 0.5, 1.0]) | st.floats(0.01, 1), min_size=1, max_size=6
    )
)
def test_rho_is_a_positive_distribution_decreasing_in_eta(eta):
    rho = partner_distribution(eta, eta)
    assert sum(rho.values()) == pytest.approx(1.0)
    assert all(p > 0 for p in rho.values())
    for i, j in itertools.product(eta, eta):
        if eta[i] <= eta[j]:
            assert rho[i] >= rho[j]


# ==================================================================================
# 5. pooled(): a team's weight and standard error from several evaluation batches.
# ==================================================================================


def test_pooled_hand_example_equals_the_concatenated_sample():
    # Batch 1: 1, 2, 3 -> n 3, mean 2, sample variance (1 + 0 + 1) / 2 = 1
    # Batch 2: 5, 7    -> n 2, mean 6, sample variance (1 + 1) / 1 = 2
    # Together: mean 18/5 = 3.6; squares about it 6.76 + 2.56 + 0.36 + 1.96 + 11.56 = 23.2
    #   (= within 2*1 + 1*2 = 4 plus between 3*(2 - 3.6)^2 + 2*(6 - 3.6)^2 = 7.68 + 11.52 = 19.2)
    # variance 23.2 / 4 = 5.8; standard error sqrt(5.8 / 5) = sqrt(1.16)
    mean, se, n = pooled([(3, 2.0, 1.0), (2, 6.0, 2.0)])
    assert n == 5
    assert mean == pytest.approx(3.6, rel=1e-12)
    assert se == pytest.approx(math.sqrt(1.16), rel=1e-12)
    sample = np.array([1.0, 2.0, 3.0, 5.0, 7.0])
    assert mean == pytest.approx(sample.mean(), rel=1e-12)
    assert se == pytest.approx(math.sqrt(sample.var(ddof=1) / sample.size), rel=1e-12)


def test_pooled_bernoulli_batches():
    # Successes 1, 1, 0, 0 and 1, 1: p = 1/2 with n p (1 - p) / (n - 1) = 1/3, and p = 1 with variance 0.
    # Together 4 of 6: mean 2/3; variance (4 * 1/9 + 2 * 4/9) / 5 = (12/9) / 5 = 4/15; se sqrt(4/15 / 6) = sqrt(2/45)
    mean, se, n = pooled([(4, 0.5, 4 * 0.25 / 3), (2, 1.0, 0.0)])
    assert (n, mean) == (6, pytest.approx(2 / 3, rel=1e-12))
    assert se == pytest.approx(math.sqrt(2 / 45), rel=1e-12)


def test_pooled_refuses_fewer_than_two_episodes():
    with pytest.raises(ValueError, match="2 episodes"):
        pooled([(1, 0.5, 0.0)])
    with pytest.raises(ValueError, match="2 episodes"):
        pooled([])


@settings(max_examples=80, deadline=None)
@given(
    sample=st.lists(st.floats(-100, 100) | st.sampled_from([0.0, 1.0]), min_size=2, max_size=40),
    data=st.data(),
)
def test_pooled_does_not_depend_on_the_split(sample, data):
    cuts = sorted(data.draw(st.sets(st.integers(1, len(sample) - 1), max_size=len(sample) - 1)))
    batches = []
    for start, stop in itertools.pairwise([0, *cuts, len(sample)]):
        part = np.array(sample[start:stop])
        variance = float(part.var(ddof=1)) if part.size > 1 else 0.0  # (n - 1) * variance is 0 for one episode
        batches.append((part.size, float(part.mean()), variance))
    whole = np.array(sample)
    mean, se, n = pooled(batches)
    assert n == len(sample)
    assert mean == pytest.approx(whole.mean(), rel=1e-9, abs=1e-9)
    assert se == pytest.approx(math.sqrt(whole.var(ddof=1) / whole.size), rel=1e-9, abs=1e-9)
    assert pooled([(whole.size, float(whole.mean()), float(whole.var(ddof=1)))]) == pytest.approx(
        (mean, se, n), rel=1e-9, abs=1e-9
    )


# ==================================================================================
# 6. contested_preferences(): which preferences need more episodes.
# ==================================================================================

AB, AC, BC = ("L", "L", "a", "b"), ("L", "L", "a", "c"), ("L", "L", "b", "c")


def test_contested_preferences_hand_example():
    stats = {AB: (0.9, 0.05), AC: (0.5, 0.05), BC: (0.8, 0.1), ("L", "L", "L", "L"): (5.0, 0.0)}
    # z = 2 (self-play LLLL is no one's preference):
    #   L: best AB .9; vs AC: .4 > 2 * hypot(.05, .05) = .141 (resolved); vs BC: .1 <= 2 * hypot(.05, .1) = .224
    #      -> contested by BC
    #   a: AB .9 vs AC .5: .4 > .141 -> resolved
    #   b: AB .9 vs BC .8: .1 <= .224 -> contested
    #   c: best BC .8 vs AC .5: .3 > 2 * hypot(.1, .05) = .224 -> resolved
    assert contested_preferences(stats, 2.0) == {"L": {AB, BC}, "b": {AB, BC}}
    # z = 1: L and b still contested (.1 <= .112), the others stay resolved
    assert contested_preferences(stats, 1.0) == {"L": {AB, BC}, "b": {AB, BC}}
    # z = 5: 5 * hypot(.05, .05) = .354 < .4, so AC still loses to AB (L and a); BC stays close to AB (L and b);
    #   c: BC .8 vs AC .5: .3 <= 5 * hypot(.1, .05) = .559 -> contested now
    assert contested_preferences(stats, 5.0) == {"L": {AB, BC}, "b": {AB, BC}, "c": {BC, AC}}
    # z = 0: anything strictly better resolves
    assert contested_preferences(stats, 0.0) == {}


def test_contested_preferences_ties_and_zero_errors():
    # Equal weights with zero error: 0 - 0 <= z * 0 -> contested, for any z.
    stats = {AB: (0.0, 0.0), AC: (0.0, 0.0)}
    # L and a are in both teams; b (AB only) and c (AC only) have no rival.
    for z in (0.0, 2.0):
        assert contested_preferences(stats, z) == {"L": {AB, AC}, "a": {AB, AC}}
    # z = 0 resolves a hair's difference even with large errors.
    assert contested_preferences({AB: (0.5 + 1e-9, 10.0), AC: (0.5, 10.0)}, 0.0) == {}
    assert contested_preferences({AB: (0.5 + 1e-9, 10.0), AC: (0.5, 10.0)}, 2.0) == {"L": {AB, AC}, "a": {AB, AC}}
    assert contested_preferences({}, 2.0) == {}


# ==================================================================================
# 7. profile_distribution() and the Profiles the rollout draws from.
# ==================================================================================


def test_profile_distribution_exact_probabilities_and_distinct_members():
    # rho 1/2, 1/4, 1/4, M = 2: ab 1/8, ac 1/8, bc 1/16; total 5/16 -> 2/5, 2/5, 1/5
    rho = {"a": 0.5, "b": 0.25, "c": 0.25}
    assert profile_distribution(rho, 2) == approx(
        {("a", "b"): Fraction(2, 5), ("a", "c"): Fraction(2, 5), ("b", "c"): Fraction(1, 5)}
    )
    # M = 1: rho itself, as 1-tuples
    assert profile_distribution(rho, 1) == approx(
        {("a",): Fraction(1, 2), ("b",): Fraction(1, 4), ("c",): Fraction(1, 4)}
    )
    # M = 3 = pool size: the one team of all three
    assert profile_distribution(rho, 3) == {("a", "b", "c"): 1.0}
    # A member without mass is not in the pool: only ab is left.
    assert profile_distribution({"a": 0.5, "b": 0.5, "c": 0.0}, 2) == {("a", "b"): 1.0}


def test_profile_distribution_multisets_when_the_pool_is_short():
    # rho a 1/3, b 2/3, M = 3 > 2 members: aaa 1/27, aab 2/27, abb 4/27, bbb 8/27; total 15/27
    #   -> 1/15, 2/15, 4/15, 8/15
    dist = profile_distribution({"a": 1 / 3, "b": 2 / 3}, 3)
    assert dist == approx(
        {
            ("a", "a", "a"): Fraction(1, 15),
            ("a", "a", "b"): Fraction(2, 15),
            ("a", "b", "b"): Fraction(4, 15),
            ("b", "b", "b"): Fraction(8, 15),
        }
    )
    # member_shares counts slots, so the shares sum to M = 3: a in aaa 3 times, aab twice, abb once ->
    #   3/15 + 2 * 2/15 + 4/15 = 11/15;  b: 2/15 + 2 * 4/15 + 3 * 8/15 = 34/15   (11 + 34 = 45 = 3 * 15)
    assert member_shares(dist) == approx({"a": Fraction(11, 15), "b": Fraction(34, 15)})
    assert profile_distribution({"a": 1.0, "c": 0.0}, 2) == {("a", "a"): 1.0}


def test_profile_distribution_refusals():
    for m in (0, -1):
        with pytest.raises(ValueError, match="num_partners"):
            profile_distribution({"a": 1.0}, m)
    for rho in ({}, {"a": 0.0, "b": 0.0}, {"a": 1.0, "b": -0.5}, {"a": float("nan"), "b": 1.0}):
        with pytest.raises(ValueError, match="rho"):
            profile_distribution(rho, 1)


def chi_square(counts, expected):
    return sum((c - e) ** 2 / e for c, e in zip(counts, expected, strict=True))


# Upper critical value of the chi-square distribution, 5 degrees of freedom, at probability 0.999
# (significance 0.001): 20.515, from the NIST/SEMATECH e-Handbook of Statistical Methods, section 1.3.6.7.4.
CHI2_5_999 = 20.515


def test_profiles_draws_match_the_profile_probabilities():
    dist = profile_distribution(partner_distribution(smoothed_centrality(G_WEIGHTS, ["L"], 1.0), G_OTHERS), 2)
    sampler = profiles(dist)
    assert isinstance(sampler, Profiles)
    assert sampler.members == ("a", "b", "c", "d")
    assert sampler.names == ["a|b", "a|c", "a|d", "b|c", "b|d", "c|d"]
    n = 20000
    drawn = sampler.draw(np.random.default_rng(12345), n, 2)
    assert drawn.shape == (n, 2)
    names = [tuple(sampler.members[i] for i in row) for row in drawn]
    assert set(names) <= set(G_PROFILES)  # whole profiles, two distinct members each
    counts = [names.count(p) for p in G_PROFILES]
    expected = [float(p) * n for p in G_PROFILES.values()]  # 1142.9, 2285.7, 4571.4, 1714.3, 3428.6, 6857.1
    statistic = chi_square(counts, expected)
    assert statistic < CHI2_5_999
    try:
        from scipy import stats
    except ImportError:  # scipy is not a dependency of the project
        return
    assert stats.chi2.ppf(0.999, 5) == pytest.approx(CHI2_5_999, abs=1e-3)
    result = stats.chisquare(counts, expected)
    assert result.statistic == pytest.approx(statistic, rel=1e-9)
    assert result.pvalue > 0.001


def test_profiles_draws_are_reproducible_and_check_the_slot_count():
    sampler = profiles({("a", "b"): 0.25, ("b", "c"): 0.75})
    first = sampler.draw(np.random.default_rng(7), 50, 2)
    np.testing.assert_array_equal(first, sampler.draw(np.random.default_rng(7), 50, 2))
    assert not np.array_equal(first, sampler.draw(np.random.default_rng(8), 50, 2))
    with pytest.raises(ValueError, match="slots"):
        sampler.draw(np.random.default_rng(7), 5, 3)
    with pytest.raises(ValueError, match="slots"):
        sampler.draw(np.random.default_rng(7), 5, 1)


# ==================================================================================
# 8. update_population(): retirement only with a cap.
# ==================================================================================


def test_update_population_without_a_cap_only_grows():
    assert update_population(["a", "b", "c"], ["L"], 0) == (["a", "b", "c", "L"], [])
    assert update_population(["a", "b", "c"], ["L"], 0, "lowest_eta", {}) == (["a", "b", "c", "L"], [])
    assert update_population([f"m{i}" for i in range(50)], ["L1", "L2"], 0)[1] == []


def test_update_population_oldest():
    # a, b, c, d + L = 5 over capacity 3: the two earliest non-learners, a then b, go.
    assert update_population(["a", "b", "c", "d"], ["L"], 3) == (["c", "d", "L"], ["a", "b"])
    # The last learner L0 is an ordinary member now: only the new learner L1 is protected.
    assert update_population(["L0", "a", "b"], ["L1"], 3, "oldest") == (["a", "b", "L1"], ["L0"])
    # A learner already in the population is kept where it is; a (earliest other) goes.
    assert update_population(["L0", "a", "b"], ["L0", "L1"], 3) == (["L0", "b", "L1"], ["a"])
    # Room left: nothing goes.
    assert update_population(["a", "b"], ["L"], 4) == (["a", "b", "L"], [])


def test_update_population_lowest_eta():
    eta = {"a": 0.5, "b": 0.2, "c": 0.2, "d": 0.1}
    # Excess 2: d (0.1), then b (0.2, older than c).
    assert update_population(["a", "b", "c", "d"], ["L"], 3, "lowest_eta", eta) == (["a", "c", "L"], ["d", "b"])
    # Excess 1: d.
    assert update_population(["a", "b", "c", "d"], ["L"], 4, "lowest_eta", eta) == (["a", "b", "c", "L"], ["d"])
    # A learner's eta is not needed; a learner of low eta is still kept.
    assert update_population(["a", "b"], ["b", "L"], 2, "lowest_eta", {"a": 0.9}) == (["b", "L"], ["a"])
    with pytest.raises(KeyError, match=r"\['c'\]"):
        update_population(["a", "b", "c", "d"], ["L"], 3, "lowest_eta", {"a": 0.5, "b": 0.2, "d": 0.1})
    with pytest.raises(KeyError):
        update_population(["a", "b", "c", "d"], ["L"], 3, "lowest_eta")


def test_update_population_refusals():
    with pytest.raises(ValueError, match="capacity"):
        update_population(["a"], ["L1", "L2"], 1)
    with pytest.raises(ValueError, match="rule"):
        update_population(["a"], ["L"], 2, "youngest")


def plain_update(population, learners, capacity, rule, eta):
    members = []
    for m in list(population) + list(learners):
        if m not in members:
            members.append(m)
    removed = []
    while capacity and len(members) > capacity:
        worst = None
        for member in members:
            if member in learners:
                continue
            if worst is None or (rule == "lowest_eta" and eta[member] < eta[worst]):  # strict: earliest of equals
                worst = member
        members.remove(worst)
        removed.append(worst)
    return members, removed


@settings(max_examples=80, deadline=None)
@given(
    population=st.lists(st.sampled_from([f"m{i}" for i in range(8)]), unique=True, max_size=8),
    learners=st.lists(st.sampled_from(["L0", "L1", "m0"]), unique=True, min_size=1),
    scores=st.lists(st.sampled_from([0.0, 0.3, 0.3, 0.7]) | st.floats(0, 1), min_size=8, max_size=8),
    room=st.integers(-1, 10),
    rule=st.sampled_from(["oldest", "lowest_eta"]),
)
def test_update_population_agrees_with_plain_reference(population, learners, scores, room, rule):
    eta = {f"m{i}": score for i, score in enumerate(scores)}
    capacity = 0 if room < 0 else len(learners) + room
    new, removed = update_population(population, learners, capacity, rule, eta)
    everyone = population + [m for m in learners if m not in population]
    assert (new, removed) == plain_update(population, learners, capacity, rule, eta)
    assert len(new) == (min(capacity, len(everyone)) if capacity else len(everyone))
    assert set(learners) <= set(new)
    assert sorted(new + removed) == sorted(everyone) and not set(new) & set(removed)
    if rule == "lowest_eta":
        for gone in removed:
            for stays in (m for m in new if m not in learners):
                assert (eta[gone], everyone.index(gone)) < (eta[stays], everyone.index(stays))


# ==================================================================================
# 9. learner_hyperedges(): the hyperedges of G'_t.
# ==================================================================================


def test_learner_hyperedges_count_per_learner():
    others = [f"m{i}" for i in range(8)]
    assert len(learner_hyperedges(["L"], others, 2, 2)) == math.comb(8, 2) == 28
    assert len(learner_hyperedges(["L"], others, 1, 3)) == math.comb(8, 3) == 56
    assert learner_hyperedges(["L"], others[:3], 3, 1) == [
        ("L", "L", "L", "m0"),
        ("L", "L", "L", "m1"),
        ("L", "L", "L", "m2"),
    ]
    # Every team holds M distinct others and the learner in exactly num_ctrl slots.
    for team in learner_hyperedges(["L"], others, 2, 3):
        assert team[:2] == ("L", "L") and len(set(team[2:])) == 3 and "L" not in team[2:]


def test_learner_hyperedges_several_learners_and_excluded_learners():
    # Two learners, others a, b, c, M = 2: 3 pairs each, learner slots first, learners never partners.
    assert learner_hyperedges(["L1", "L2"], ["a", "L2", "b", "c", "a"], 1, 2) == [
        ("L1", "a", "b"),
        ("L1", "a", "c"),
        ("L1", "b", "c"),
        ("L2", "a", "b"),
        ("L2", "a", "c"),
        ("L2", "b", "c"),
    ]
    assert learner_hyperedges(["L"], ["a", "L", "b"], 2, 1) == [("L", "L", "a"), ("L", "L", "b")]


def test_learner_hyperedges_multisets_when_the_pool_is_short():
    # Two others for three partner slots: the multisets aaa, aab, abb, bbb (C(2 + 3 - 1, 3) = 4).
    assert learner_hyperedges(["L"], ["a", "b"], 1, 3) == [
        ("L", "a", "a", "a"),
        ("L", "a", "a", "b"),
        ("L", "a", "b", "b"),
        ("L", "b", "b", "b"),
    ]
    assert learner_hyperedges(["L"], ["a"], 2, 2) == [("L", "L", "a", "a")]


def test_learner_hyperedges_refusals():
    with pytest.raises(ValueError, match="empty"):
        learner_hyperedges(["L"], [], 2, 2)
    with pytest.raises(ValueError, match="empty"):
        learner_hyperedges(["L"], ["L"], 2, 2)
    with pytest.raises(ValueError, match="num_ctrl"):
        learner_hyperedges(["L"], ["a"], 0, 2)
    with pytest.raises(ValueError, match="num_partners"):
        learner_hyperedges(["L"], ["a"], 2, 0)


# ==================================================================================
# 10. HolaConfig validation.
# ==================================================================================


def test_hola_config_defaults_parse():
    assert Hola.parse_config({}, "hola") == HolaConfig()
    # population_size 5 = 2 seeds x 2 levels + 1 learner: the smallest cap allowed
    assert Hola.parse_config({"population_size": 5, "retire": "lowest_eta"}, "hola").population_size == 5
    assert Hola.parse_config({"weight": "SUC", "learner_start": "scratch"}, "hola").weight == "SUC"


@pytest.mark.parametrize(
    ("section", "field"),
    [
        ({"weight": "banana"}, "weight"),
        ({"eta_prior": 0}, "eta_prior"),
        ({"eta_prior": -1.0}, "eta_prior"),
        ({"min_episodes": 1}, "min_episodes"),
        ({"min_episodes": 8, "max_episodes": 4}, "max_episodes"),
        ({"max_episodes": 16}, "max_episodes"),  # below the default min_episodes 32
        ({"learner_start": "x"}, "learner_start"),
        ({"retire": "x"}, "retire"),
        ({"population_size": 4}, "population_size"),  # Pi_0 (2 x 2) plus one learner needs 5
        ({"pi0_seeds": 3, "pi0_levels": 3, "population_size": 9}, "population_size"),  # 3 x 3 + 1 = 10
        ({"learners_per_generation": 3}, "learners_per_generation"),  # more than pi0_seeds = 2
        ({"z": -1.0}, "z"),
        ({"max_hyperedges": -1}, "max_hyperedges"),
    ],
)
def test_hola_config_errors_name_the_field(section, field):
    with pytest.raises(ConfigError) as info:
        Hola.parse_config(section, "hola")
    assert info.value.path == f"hola.{field}"
    assert f"hola.{field}" in str(info.value)
