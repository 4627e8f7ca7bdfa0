"""HOLA-Drone V2 functions: a worked example computed by hand, and a plain reference on random match tables."""

from __future__ import annotations

import itertools
import math
from fractions import Fraction

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from atdrone.population.hypergraph import (
    distribution_entropy,
    hyperedge_weights,
    missing_hyperedges,
    partner_distribution,
    preference_centrality,
    preference_hypergraph,
    sample_profiles,
    team_key,
    uniform_distribution,
    update_population,
)

NAN = float("nan")

# The worked example: 4 members A, B, C, D in teams of 3 slots (slot order shuffled on purpose).
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
#   A: B (AAB), C (ACD), D (ACD) -> 3;  B: nobody -> 0;  C: A, D -> 2;  D: A, C -> 2
# Degree: sum over its teams of |distinct members| - 1.
#   A: AAB 1 + ABC 2 + ACD 2 = 5;  B: AAB 1 + ABC 2 + BCC 1 + BDD 1 = 5
#   C: ABC 2 + ACD 2 + BCC 1 = 5;  D: ACD 2 + BDD 1 + DDD 0 = 3
# eta = in-degree / degree; E (passed in nodes=, no team) -> 0.
HAND_ETA = {"A": Fraction(3, 5), "B": Fraction(0), "C": Fraction(2, 5), "D": Fraction(2, 3), "E": Fraction(0)}


def hand_table() -> pd.DataFrame:
    return pd.DataFrame({"team": [list(t) for t, _ in HAND_ROWS], "score": [s for _, s in HAND_ROWS]})


def test_team_key_sorts_and_keeps_duplicates():
    assert team_key(["p3", "L", "p1", "L"]) == ("L", "L", "p1", "p3")
    assert team_key(np.array(["b", "a"])) == ("a", "b")


def test_worked_example_weights_preferences_and_eta():
    weights = hyperedge_weights(hand_table())
    assert weights == HAND_WEIGHTS
    assert preference_hypergraph(weights) == HAND_PREFERRED
    assert preference_hypergraph(dict(reversed(weights.items()))) == HAND_PREFERRED  # ties: by key, not dict order
    eta = preference_centrality(weights, nodes=["E"])
    assert eta == {node: float(value) for node, value in HAND_ETA.items()}


def test_worked_example_partner_distribution_in_exact_fractions():
    eta = {node: float(value) for node, value in HAND_ETA.items()}
    # eps = 0 over A, C, D: 1/eta = 5/3, 5/2, 3/2, total 17/3 -> rho = 5/17, 15/34, 9/34
    rho = partner_distribution(eta, ["A", "C", "D"], eps=0.0)
    assert rho == pytest.approx({"A": 5 / 17, "C": 15 / 34, "D": 9 / 34}, rel=1e-12)
    # eps = 1/10 over B, C, D: 1/(eta + eps) = 10, 2, 30/23, total 306/23 -> 115/153, 23/153, 15/153
    rho = partner_distribution(eta, ["B", "C", "D"], eps=0.1)
    assert rho == pytest.approx({"B": 115 / 153, "C": 23 / 153, "D": 15 / 153}, rel=1e-12)
    # The default eps: B (eta 0) drawn most, then C, A, D, in increasing eta.
    rho = partner_distribution(eta, ["A", "B", "C", "D"])
    assert rho["B"] > rho["C"] > rho["A"] > rho["D"] > 0
    assert sum(rho.values()) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="positive"):
        partner_distribution(eta, ["B"], eps=0.0)
    with pytest.raises(KeyError, match="F"):
        partner_distribution(eta, ["A", "F"])


def test_entropy_in_nats():
    assert distribution_entropy(uniform_distribution(["A", "B", "C", "D", "A"])) == pytest.approx(math.log(4))
    assert distribution_entropy({"A": 1.0, "B": 0.0}) == 0.0
    rho = {"A": 5 / 17, "C": 15 / 34, "D": 9 / 34}
    assert distribution_entropy(rho) == pytest.approx(-sum(p * math.log(p) for p in rho.values()))


def test_worked_example_population_update():
    eta = {node: float(value) for node, value in HAND_ETA.items()}
    # One learner L over capacity 4: B (eta 0) goes.
    assert update_population(["A", "B", "C", "D"], eta, ["L"], 4) == (["A", "C", "D", "L"], ["B"])
    # Capacity 3: B (0), then C (2/5).
    assert update_population(["A", "B", "C", "D"], eta, ["L"], 3) == (["A", "D", "L"], ["B", "C"])
    # Room left: nothing goes.
    assert update_population(["A", "B"], eta, ["L"], 4) == (["A", "B", "L"], [])
    # Ties go to the oldest member.
    assert update_population(["x", "y", "z"], {"x": 0.5, "y": 0.2, "z": 0.2}, ["L"], 3) == (["x", "z", "L"], ["y"])
    with pytest.raises(ValueError, match="capacity"):
        update_population(["A"], eta, ["L1", "L2"], 1)


def test_worked_example_missing_hyperedges():
    # L fills 2 slots, the 2 partner slots take every multiset of {A, B}: AA, AB, BB; AALL is known.
    missing = missing_hyperedges(["A", "B", "L"], ["L"], 2, 2, known=[("L", "A", "L", "A")])
    assert missing == [("A", "B", "L", "L"), ("B", "B", "L", "L")]


def test_sample_profiles_are_seeded_and_shaped():
    rho = {"A": 5 / 17, "C": 15 / 34, "D": 9 / 34}
    first = sample_profiles(rho, 7, 3, np.random.default_rng(4))
    assert first == sample_profiles(rho, 7, 3, np.random.default_rng(4))
    assert len(first) == 7 and all(len(p) == 3 and set(p) <= set(rho) for p in first)
    assert sample_profiles(rho, 0, 3, np.random.default_rng(0)) == []
    assert sample_profiles({"A": 0.0, "C": 1.0}, 5, 2, np.random.default_rng(0)) == [("C", "C")] * 5


# ---- a plain reference, written as literally as possible ----


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


def plain_eta(weights, extra_nodes):
    preferred = plain_preferences(weights)
    eta = {}
    for node in plain_nodes(weights) + list(extra_nodes):
        degree = 0
        for team in weights:
            if node in team:
                degree += len(set(team)) - 1
        in_degree = 0
        for source, team in preferred.items():
            if source != node and node in team:
                in_degree += 1
        eta[node] = in_degree / degree if degree > 0 else 0.0
    return eta


def plain_rho(eta, candidates, eps):
    inverse = {}
    for candidate in candidates:
        inverse[candidate] = 1.0 / (eta[candidate] + eps)
    total = sum(inverse.values())
    return {candidate: value / total for candidate, value in inverse.items()}


def plain_update(population, eta, learners, capacity):
    members = list(population) + [learner for learner in learners if learner not in population]
    removed = []
    while len(members) > capacity:
        worst = None
        for member in members:
            if member in learners:
                continue
            if worst is None or eta[member] < eta[worst]:  # strict: the earliest of equals stays the worst
                worst = member
        members.remove(worst)
        removed.append(worst)
    return members, removed


MEMBERS = ["a", "b", "c", "d", "e", "f"]
SCORES = st.one_of(st.sampled_from([0.0, 0.25, 0.5, 0.75, 1.0]), st.floats(-1, 1), st.just(NAN))


@st.composite
def match_rows(draw):
    """Rows (team, score): a few teams of 2-4 slots, each played several times in shuffled slot orders."""
    teams = draw(st.lists(st.lists(st.sampled_from(MEMBERS), min_size=2, max_size=4), min_size=1, max_size=8))
    rows = []
    for _ in range(draw(st.integers(1, 30))):
        team = teams[draw(st.integers(0, len(teams) - 1))]
        rows.append((tuple(draw(st.permutations(team))), draw(SCORES)))
    return rows


@settings(max_examples=200, deadline=None)
@given(rows=match_rows(), extra=st.lists(st.sampled_from(["x", "y"]), unique=True), eps=st.sampled_from([1e-3, 0.1]))
def test_hola_functions_agree_with_plain_reference(rows, extra, eps):
    table = pd.DataFrame({"team": [list(t) for t, _ in rows], "outcome": [s for _, s in rows]})
    weights = hyperedge_weights(table, outcome="outcome")
    expected_weights = plain_weights(rows)
    assert weights == pytest.approx(expected_weights, rel=1e-12, abs=1e-15)
    assert preference_hypergraph(weights) == plain_preferences(expected_weights)
    assert preference_hypergraph(dict(reversed(weights.items()))) == plain_preferences(expected_weights)
    eta = preference_centrality(weights, nodes=extra)
    assert eta == pytest.approx(plain_eta(expected_weights, extra), rel=1e-12)
    assert all(0.0 <= value <= 1.0 for value in eta.values())
    candidates = sorted(eta)
    if not candidates:  # every row NaN and no extra node: nobody to draw
        with pytest.raises(ValueError, match="no candidates"):
            partner_distribution(eta, candidates, eps=eps)
        return
    rho = partner_distribution(eta, candidates, eps=eps)
    assert list(rho) == candidates
    assert rho == pytest.approx(plain_rho(eta, candidates, eps), rel=1e-9)


@settings(max_examples=200, deadline=None)
@given(
    eta=st.dictionaries(st.sampled_from(MEMBERS), st.sampled_from([0.0, 0.2, 0.5, 1.0]) | st.floats(0, 1), min_size=1),
    eps=st.sampled_from([1e-3, 0.1, 1.0]),
)
def test_rho_is_a_positive_distribution_decreasing_in_eta(eta, eps):
    rho = partner_distribution(eta, eta, eps=eps)
    assert sum(rho.values()) == pytest.approx(1.0)
    assert all(p > 0 for p in rho.values())
    for i, j in itertools.product(eta, eta):
        if eta[i] <= eta[j]:
            assert rho[i] >= rho[j]


@settings(max_examples=20, deadline=None)
@given(weights=st.lists(st.floats(0.01, 1.0), min_size=1, max_size=5), seed=st.integers(0, 2**32 - 1))
def test_sample_profiles_frequencies_converge_to_rho(weights, seed):
    total = sum(weights)
    rho = {f"m{i}": w / total for i, w in enumerate(weights)}
    profiles = sample_profiles(rho, 5000, 4, np.random.default_rng(seed))
    draws = [member for profile in profiles for member in profile]
    for member, p in rho.items():
        assert draws.count(member) / len(draws) == pytest.approx(p, abs=0.02)  # 20000 draws: sd <= 0.0036


@settings(max_examples=200, deadline=None)
@given(
    population=st.lists(st.sampled_from([f"m{i}" for i in range(8)]), unique=True, max_size=8),
    learners=st.lists(st.sampled_from(["L0", "L1", "m0"]), unique=True, min_size=1),
    scores=st.lists(st.sampled_from([0.0, 0.3, 0.3, 0.7]) | st.floats(0, 1), min_size=8, max_size=8),
    room=st.integers(0, 10),
)
def test_update_population_keeps_learners_and_drops_the_lowest_eta(population, learners, scores, room):
    eta = {f"m{i}": score for i, score in enumerate(scores)}
    capacity = len(learners) + room
    new, removed = update_population(population, eta, learners, capacity)
    everyone = population + [m for m in learners if m not in population]
    assert (new, removed) == plain_update(population, eta, learners, capacity)
    assert len(new) == min(capacity, len(everyone))
    assert set(learners) <= set(new)
    assert sorted(new + removed) == sorted(everyone) and not set(new) & set(removed)
    kept = [m for m in new if m not in learners]
    for gone in removed:
        for stays in kept:
            assert (eta[gone], everyone.index(gone)) < (eta[stays], everyone.index(stays))


@settings(max_examples=200, deadline=None)
@given(
    population=st.lists(st.sampled_from(["a", "b", "c", "d", "L0"]), unique=True, max_size=5),
    learners=st.lists(st.sampled_from(["L0", "L1"]), unique=True, min_size=1),
    num_ctrl=st.integers(1, 2),
    num_partners=st.integers(0, 3),
    known=st.lists(st.lists(st.sampled_from(["a", "b", "c", "d", "L0", "L1"]), min_size=1, max_size=5), max_size=10),
)
def test_missing_hyperedges_touch_learners_skip_known_and_run_out(population, learners, num_ctrl, num_partners, known):
    known_keys = {team_key(team) for team in known}
    missing = missing_hyperedges(population, learners, num_ctrl, num_partners, known)
    assert len(missing) == len(set(missing))
    for team in missing:
        assert team == team_key(team) and len(team) == num_ctrl + num_partners
        assert any(team.count(learner) >= num_ctrl for learner in learners)
        assert team not in known_keys
    # The plain enumeration: every slot assignment of partners, as a set of team_keys.
    expected = set()
    for learner in learners:
        pool = [m for m in population if m != learner]
        for partners in itertools.product(pool, repeat=num_partners):
            expected.add(tuple(sorted([learner] * num_ctrl + list(partners))))
    assert set(missing) == expected - known_keys
    assert missing_hyperedges(population, learners, num_ctrl, num_partners, [*known, *missing]) == []


def test_missing_hyperedges_count_per_learner():
    # 8 members besides the learner, 2 partner slots: C(8 + 2 - 1, 2) = 36 teams.
    population = [f"m{i}" for i in range(8)]
    assert len(missing_hyperedges(population, ["L"], 2, 2, known=[])) == math.comb(9, 2) == 36
    assert len(missing_hyperedges([*population, "m8"], ["L"], 1, 3, known=[])) == math.comb(11, 3) == 165
