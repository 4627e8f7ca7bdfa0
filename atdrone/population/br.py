"""Best response to a fixed zoo: each generation continues the last member against uniform zoo partners."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from atdrone.config import ConfigError
from atdrone.population.base import Algorithm, GenerationReport, Oracle, record
from atdrone.teams.partners import Uniform


@dataclass(frozen=True)
class BestResponseConfig:
    """zoo: the partners to respond to (zoo1-zoo4 or a zoo JSON path)."""

    zoo: str


class BestResponse(Algorithm):
    name = "br"
    Config = BestResponseConfig

    @classmethod
    def check_config(cls, cfg: Any, path: str) -> None:
        from atdrone.policies.zoo import load_zoo

        try:
            load_zoo(cfg.zoo)
        except ConfigError as exc:
            raise ConfigError(f"{path}.zoo", str(exc)) from None

    def generation(self, oracle: Oracle) -> GenerationReport:
        parent = self.population[-1] if self.population else None
        trained = oracle.train(parent, partners=Uniform(tuple(oracle.zoo_members(self.config.zoo))))
        member = oracle.register(trained, [parent] if parent else [])
        self.population.append(member)
        return GenerationReport(
            oracle.generation, self.name, [member], list(self.population), training=[record(member, trained)]
        )
