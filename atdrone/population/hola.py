"""HOLA-Drone V2 (SPEC section 10; the paper's appendix "HOLA-Drone (V2) Algorithm") and its "w/o g" ablation.

One generation reads like PSRO's iteration, over the pure functions of
:mod:`atdrone.population.hypergraph`:

    missing hyperedges (teams of the last learners not yet played)
    -> evaluate them -> hyperedge weights (team SUC) -> eta (preference centrality)
    -> rho over the partners (1 / eta; uniform for hola_no_g)
    -> best responses trained against partners drawn from rho
    -> population update (the lowest-eta non-learner leaves when full)

Generation 0 bootstraps the population with a self-play learner. The partners the
learners train with are exactly the draws from rho that the rollout records per
episode (the report's ``drawn`` counts, beside rho).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

import atdrone.population.hypergraph as hg
from atdrone.config import ConfigError
from atdrone.population.base import Algorithm, GenerationReport, Oracle, Team, record, require_population
from atdrone.teams.partners import weighted


@dataclass(frozen=True)
class HolaConfig:
    """population_size: the population's capacity; learners_per_generation: best responses per generation."""

    population_size: int = 4
    learners_per_generation: int = 1


class Hola(Algorithm):
    name = "hola"
    Config = HolaConfig
    uniform = False  # the "w/o g" ablation draws partners uniformly

    def __init__(self, config: HolaConfig, seed: int) -> None:
        super().__init__(config, seed)
        self.learners: list[str] = []  # N_t: the last generation's learners
        self.eta: dict[str, float] = {}
        self.matches: list[dict[str, Any]] = []  # {"team": [...], "SUC": ...}: played teams of current members

    @classmethod
    def check_config(cls, cfg: Any, path: str) -> None:
        require_population(cfg, path)
        if not 1 <= cfg.learners_per_generation <= cfg.population_size:
            raise ConfigError(
                f"{path}.learners_per_generation",
                f"must be in 1..population_size ({cfg.population_size}), got {cfg.learners_per_generation}",
            )

    def generation(self, oracle: Oracle) -> GenerationReport:
        if not self.population:
            return self._bootstrap(oracle)
        # 1-2. play the hyperedges touching the last learners that have no match yet
        known = [tuple(m["team"]) for m in self.matches]
        missing = hg.missing_hyperedges(self.population, self.learners, oracle.num_ctrl, oracle.num_partners, known)
        played = oracle.evaluate([self._slot_order(team, oracle.num_ctrl) for team in missing])
        self.matches += [{"team": list(r.team), **r.metrics} for r in played]
        # 3. hyperedge weights: each team's success rate
        weights = self._weights()
        # 4. eta: in-degree in the preference hypergraph / degree in the hypergraph
        self.eta = hg.preference_centrality(weights, nodes=self.population)
        # 5. rho over the partners: the members nobody prefers are drawn most
        candidates = list(self.population)
        rho = hg.uniform_distribution(candidates) if self.uniform else hg.partner_distribution(self.eta, candidates)
        # 6. best responses against partners drawn from rho, per environment and episode
        parent = self.learners[-1]
        learners, training = [], []
        for _ in range(self.config.learners_per_generation):
            trained = oracle.train(parent, weighted(rho, candidates))
            member = oracle.register(trained, [parent])
            learners.append(member)
            training.append(record(member, trained))
        # 7. population update
        eta_all = {m: self.eta.get(m, 0.0) for m in self.population}
        self.population, removed = hg.update_population(self.population, eta_all, learners, self.config.population_size)
        oracle.retire(removed)
        self.learners = learners
        self.matches = [m for m in self.matches if set(m["team"]) <= set(self.population)]
        drawn: dict[str, int] = {}
        for t in training:
            for profile, n in t.drawn.items():
                drawn[profile] = drawn.get(profile, 0) + n
        metrics = {"pop/rho_entropy": hg.distribution_entropy(rho), "eval/matches": float(len(played))}
        metrics.update({f"pop/eta/{m}": v for m, v in self.eta.items()})
        metrics.update({f"pop/rho/{m}": v for m, v in rho.items()})
        graph = {
            "weights": {"|".join(k): v for k, v in weights.items()},
            "preference": {n: list(e) for n, e in hg.preference_hypergraph(weights).items()},
            "eta": dict(self.eta),
            "rho": rho,
            "drawn_profiles": drawn,
            "removed": removed,
        }
        return GenerationReport(
            oracle.generation,
            self.name,
            learners,
            list(self.population),
            training=training,
            matches=played,
            removed=removed,
            metrics=metrics,
            documents={"hypergraph.json": graph},
        )

    def _bootstrap(self, oracle: Oracle) -> GenerationReport:
        """Pi_0: one self-play learner."""
        trained = oracle.train(None, partners=None)
        member = oracle.register(trained, [])
        self.population, self.learners = [member], [member]
        return GenerationReport(oracle.generation, self.name, [member], [member], training=[record(member, trained)])

    def _weights(self) -> dict[Team, float]:
        table = pd.DataFrame(self.matches)  # pruned to the population's teams at every population update
        if not len(table):
            return {}
        table["score"] = table["SUC"] / 100.0
        return hg.hyperedge_weights(table)

    def _slot_order(self, key: Team, num_ctrl: int) -> Team:
        """A team_key as slots: the learner (filling num_ctrl slots) first, then its partners."""
        for m in self.learners:
            if key.count(m) >= num_ctrl:
                rest = list(key)
                for _ in range(num_ctrl):
                    rest.remove(m)
                return (m,) * num_ctrl + tuple(rest)
        raise ValueError(f"team {key} has no learner filling {num_ctrl} slots")

    def state(self) -> dict[str, Any]:
        return {**super().state(), "learners": self.learners, "eta": self.eta, "matches": self.matches}

    def load_state(self, state: Mapping[str, Any]) -> None:
        super().load_state(state)
        self.learners = list(state.get("learners", []))
        self.eta = dict(state.get("eta", {}))
        self.matches = [dict(m) for m in state.get("matches", [])]

    @classmethod
    def figures(cls, report: GenerationReport, out_dir: Path) -> list[Path]:
        graph = report.documents.get("hypergraph.json")
        if not graph or not graph["weights"]:
            return []
        from atdrone.population.plots import draw_hypergraph

        path = out_dir / "hypergraph.png"
        draw_hypergraph(graph["weights"], graph["preference"], graph["eta"], path)
        return [path]


class HolaNoG(Hola):
    """The ablation: partners drawn uniformly from the population instead of from rho."""

    name = "hola_no_g"
    uniform = True
