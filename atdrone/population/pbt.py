"""Population-based training: IPPO learners trained with each other, then exploit and explore.

Every generation each member trains against partners drawn uniformly from the other
members (self-play while it is alone), from its own weights, or from its winner's when
it was exploited; then each new member plays a team of the others, and the worst
quarter copies the best quarter's weights with the winners' learning rate and entropy
coefficient, each multiplied or divided by ``perturb``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from atdrone.config import ConfigError
from atdrone.population.base import Algorithm, GenerationReport, Oracle, record, require_population
from atdrone.teams.partners import Uniform


@dataclass(frozen=True)
class PBTConfig:
    """population_size: members trained side by side; perturb: the explore factor (> 1)."""

    population_size: int = 4
    perturb: float = 1.25


class PBT(Algorithm):
    name = "pbt"
    Config = PBTConfig

    def __init__(self, config: PBTConfig, seed: int) -> None:
        super().__init__(config, seed)
        self.hparams: dict[str, dict[str, float]] = {}
        self.exploit_from: dict[str, str] = {}  # loser -> winner of the last generation

    @classmethod
    def check_config(cls, cfg: Any, path: str) -> None:
        require_population(cfg, path)
        if cfg.perturb <= 1.0:
            raise ConfigError(f"{path}.perturb", f"must be > 1, got {cfg.perturb}")

    def generation(self, oracle: Oracle) -> GenerationReport:
        size, perturb = self.config.population_size, self.config.perturb
        previous: list[str | None] = list(self.population) or [None] * size
        members, training = [], []
        for i, parent in enumerate(previous):
            source = self.exploit_from.get(parent, parent) if parent else None
            if parent is None:  # the first generation spreads the hyperparameters
                f = perturb ** (i - (size - 1) / 2)
                hparams = {"lr": oracle.ppo.lr * f, "ent_coef": oracle.ppo.ent_coef / f}
            else:
                hparams = self.hparams[parent]
            others = tuple(m for m in previous if m is not None and m != parent)
            trained = oracle.train(source, Uniform(others) if others else None, hparams)
            member = oracle.register(trained, [source] if source else [])
            self.hparams[member] = dict(trained.hparams)
            members.append(member)
            training.append(record(member, trained))
        # fitness: each new member with a team of the others
        teams = []
        for m in members:
            pool = [o for o in members if o != m]
            picks = oracle.rng.choice(len(pool), size=oracle.num_partners)
            teams.append((m,) * oracle.num_ctrl + tuple(pool[j] for j in picks))
        matches = oracle.evaluate(teams)
        fitness = {r.team[0]: r.metrics["SUC"] for r in matches}
        order = sorted(members, key=lambda m: fitness[m])
        k = max(1, size // 4)
        exploited: dict[str, str] = {}
        for loser, winner in zip(order[:k], order[::-1][:k], strict=True):
            if loser != winner:
                self.hparams[loser] = {
                    name: value * float(oracle.rng.choice([1 / perturb, perturb]))
                    for name, value in self.hparams[winner].items()
                }
                exploited[loser] = winner
        self.exploit_from = exploited
        self.population = members
        metrics = {f"pop/fitness/{m}": v for m, v in fitness.items()}
        metrics.update({f"pop/lr/{m}": self.hparams[m]["lr"] for m in members})
        return GenerationReport(
            oracle.generation,
            self.name,
            members,
            list(members),
            training=training,
            matches=matches,
            metrics=metrics,
            documents={"pbt.json": {"fitness": fitness, "exploited": exploited, "hparams": self.hparams}},
        )

    def state(self) -> dict[str, Any]:
        return {**super().state(), "hparams": self.hparams, "exploit_from": self.exploit_from}

    def load_state(self, state: Mapping[str, Any]) -> None:
        super().load_state(state)
        self.hparams = {m: dict(h) for m, h in state.get("hparams", {}).items()}
        self.exploit_from = dict(state.get("exploit_from", {}))
