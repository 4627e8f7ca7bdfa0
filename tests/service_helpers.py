"""What the service tests share (tests/test_service.py, tests/test_service_runs.py): a tiny experiment config, a
small HOLA run, and the checks of a generation's budget and of a HOLA generation's hypergraph and training."""

from __future__ import annotations

import itertools
from typing import Any

from atdrone.service.experiment import load_experiment

TINY: dict[str, Any] = {
    "task": "4p2e1o",
    "updates_per_generation": 1,
    "num_workers": 2,
    "eval_episodes": 4,
    "final_zoo": "zoo1",
    "final_episodes": 4,
    "gif": False,
    "ppo": {"epochs": 2, "entity_dim": 16, "hidden": 32, "minibatch_size": 64, "num_envs": 8, "rollout_steps": 16},
}


def _cfg(tmp_path, name, **kw):
    return load_experiment({**TINY, "name": name, "out_dir": str(tmp_path), **kw})


# a small HOLA run: Pi_0 is one self-play seed frozen at 3 skill levels (one update each), then 3 updates a generation
HOLA = {"pi0_seeds": 1, "pi0_levels": 3, "min_episodes": 4, "max_episodes": 8}


def _check_budget(cfg, reports) -> None:
    """Every training took updates x num_envs x rollout_steps env steps; the budget is the running total."""
    steps = samples = eval_steps = 0
    for report in reports:
        for t in report.training:
            assert t.env_steps == len(t.history) * cfg.ppo["num_envs"] * cfg.ppo["rollout_steps"]
            assert t.samples == sum(h["train/samples"] for h in t.history) > 0
        steps += sum(t.env_steps for t in report.training)
        samples += sum(t.samples for t in report.training)
        eval_steps += sum(int(m.metrics["steps"]) for m in report.matches)
        assert report.budget == {"env_steps": steps, "learner_samples": samples, "eval_env_steps": eval_steps}


def _check_hola_generation(report, learner: str, others: list[str]) -> dict:
    """Generation t of HOLA with N_t = [learner]: G'_t, rho over Pi minus N_t, training on draws from its profiles."""
    graph = report.documents["hypergraph.json"]
    g_t = {(learner, learner, *pair) for pair in itertools.combinations(others, 2)}
    assert {m.team for m in report.matches} == g_t  # every match is a hyperedge of G'_t, and each was played
    assert graph["learners"] == [learner]
    assert {tuple(e["team"]) for e in graph["hyperedges"]} == g_t
    assert all(4 <= e["episodes"] <= 8 for e in graph["hyperedges"]) and graph["rounds"] >= 1
    assert list(graph["rho"]) == others and abs(sum(graph["rho"].values()) - 1) < 1e-9  # never N_t
    assert set(graph["eta"]) == {learner, *others}
    assert set(graph["profiles"]) == {"|".join(sorted(p)) for p in itertools.combinations(others, 2)}
    assert abs(sum(graph["profiles"].values()) - 1) < 1e-9
    (trained,) = report.training
    assert report.learners == [trained.member] and report.population[-1] == trained.member
    assert trained.parent == learner  # learner_start "last": N_t's member, continued
    assert trained.partners["kind"] == "Profiles" and set(trained.partners["members"]) == set(others)
    # the rollout's counts of the profiles it drew: rho's members only, and what hypergraph.json reports
    assert sum(trained.drawn.values()) > 0
    assert all(set(profile.split("|")) <= set(others) for profile in trained.drawn)
    assert set(trained.drawn) <= set(graph["profiles"])
    assert graph["drawn_profiles"] == trained.drawn
    slots = {m: sum(n for profile, n in trained.drawn.items() if m in profile.split("|")) for m in others}
    assert graph["drawn_members"] == {m: n for m, n in sorted(slots.items()) if n}
    return graph
