"""benchmarks/hola_report.py's noise null: rho when the learner's hyperedges differ by measurement noise only."""

from __future__ import annotations

import math
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def report_mod(load_script) -> ModuleType:
    return load_script(ROOT / "benchmarks" / "hola_report.py")


def _graph(weights: list[float], ses: list[float]) -> dict:
    """Learner L (two slots) with every pair of the partners a, b, c: three hyperedges, as hypergraph.json has them."""
    teams = [["L", "L", "a", "b"], ["L", "L", "a", "c"], ["L", "L", "b", "c"]]
    return {
        "learners": ["L"],
        "weight": "return",
        "hyperedges": [{"team": t, "return": w, "return_se": s} for t, w, s in zip(teams, weights, ses, strict=True)],
        "rho": {"a": 0.2, "b": 0.4, "c": 0.4},
    }


def test_without_noise_every_profile_is_alike_and_rho_is_uniform(report_mod: ModuleType) -> None:
    """Standard errors 0: every drawn weight is the mean, softmin is uniform over the three profiles, each partner
    is in two of them: rho 1/3 each, entropy ln 3. The two lowest weights (10 and 4) differ by 6 over sqrt(2) x 2."""
    out = report_mod.noise_null(_graph([10.0, 4.0, 16.0], [0.0, 0.0, 0.0]), temperature=2.0, seed=0, trials=5)
    assert out["noise_entropy"] == pytest.approx(math.log(3), abs=1e-12)
    assert out["noise_max_rho"] == pytest.approx(1 / 3, abs=1e-12)
    assert math.isinf(out["gap_z"])  # no noise at all: any gap stands out infinitely
    out = report_mod.noise_null(_graph([10.0, 4.0, 16.0], [2.0, 2.0, 2.0]), temperature=2.0, seed=0, trials=5)
    assert out["gap_z"] == pytest.approx(6 / (2 * math.sqrt(2)))


def test_noise_alone_spreads_rho_less_than_a_planted_worst_profile(report_mod: ModuleType) -> None:
    """One profile 20 below the others with standard errors of 1: the measured softmin puts nearly all its mass on
    that profile's two partners (entropy near ln 2), the noise null (temperature 2, noise sd 1) stays near uniform."""
    import atdrone.population.hypergraph as hg

    graph = _graph([20.0, 0.0, 20.0], [1.0, 1.0, 1.0])
    out = report_mod.noise_null(graph, temperature=2.0, seed=0, trials=400)
    teams = {tuple(e["team"]): e["return"] for e in graph["hyperedges"]}
    shares = hg.member_shares(hg.softmin_profiles(teams, ["L"], 2.0))
    measured = hg.distribution_entropy({m: v / 2 for m, v in shares.items()})
    assert measured == pytest.approx(math.log(2), abs=1e-3)
    assert out["noise_entropy"] > math.log(3) - 0.1 > measured + 0.3
    assert out["gap_z"] == pytest.approx(20 / math.sqrt(2))
    again = report_mod.noise_null(graph, temperature=2.0, seed=0, trials=400)
    assert again == out  # seeded: the report is reproducible


def test_noise_much_wider_than_the_temperature_makes_one_profile_win_each_draw(report_mod: ModuleType) -> None:
    """Equal outcomes measured with a standard error of 10 (temperature 2): in each draw one profile is lowest by
    several temperatures and takes nearly all the mass, so rho is about 1/2 on its two partners: entropy near
    ln 2 (0.69), not ln 3 (1.10). A null that ignored the standard errors would give ln 3."""
    out = report_mod.noise_null(_graph([5.0, 5.0, 5.0], [10.0, 10.0, 10.0]), temperature=2.0, seed=1, trials=400)
    assert out["noise_entropy"] < 0.85 and out["noise_max_rho"] > 0.45
    assert out["gap_z"] == 0.0


def test_a_graph_with_one_hyperedge_has_no_noise_null(report_mod: ModuleType) -> None:
    graph = _graph([1.0, 2.0, 3.0], [1.0, 1.0, 1.0])
    graph["hyperedges"] = graph["hyperedges"][:1]
    assert report_mod.noise_null(graph, temperature=2.0, seed=0) == {}


def test_pi0s_early_members_are_each_seeds_snapshots_before_its_last(report_mod: ModuleType, tmp_path: Path) -> None:
    """pi0.json lists the members seed by seed, one per skill level: 2 seeds x 3 levels -> the first two of each."""
    import json

    gens = tmp_path / "generations"
    assert report_mod.pi0_members(gens) is None  # a run without the file (older archives)
    (gens / "000").mkdir(parents=True)
    members = ["s0a", "s0b", "s0c", "s1a", "s1b", "s1c"]
    (gens / "000" / "pi0.json").write_text(json.dumps({"seeds": 2, "levels": [5, 5, 6], "members": members}))
    assert report_mod.pi0_members(gens) == (set(members), {"s0a", "s0b", "s1a", "s1b"})
