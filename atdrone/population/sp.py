"""Self-play (IPPO): one lineage; each generation trains the last member in every slot and registers it."""

from __future__ import annotations

from dataclasses import dataclass

from atdrone.population.base import Algorithm, GenerationReport, Oracle, record


@dataclass(frozen=True)
class SelfPlayConfig:
    """Self-play has no settings of its own."""


class SelfPlay(Algorithm):
    name = "sp"
    Config = SelfPlayConfig

    def generation(self, oracle: Oracle) -> GenerationReport:
        parent = self.population[-1] if self.population else None
        trained = oracle.train(parent, partners=None)
        member = oracle.register(trained, [parent] if parent else [])
        self.population.append(member)
        return GenerationReport(
            oracle.generation, self.name, [member], list(self.population), training=[record(member, trained)]
        )
