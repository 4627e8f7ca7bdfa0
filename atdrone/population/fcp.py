"""Fictitious co-play (FCP, Strouse et al. 2021): a learner trained against frozen self-play partners.

Generation 0 builds the frozen pool: ``seeds`` self-play runs, each frozen at
``levels`` evenly spaced skill levels (early, middle, final: seeds x levels partners,
each a registry member whose parent is its run's previous level), the way HOLA-Drone
V2 builds Pi_0 (:func:`~atdrone.population.base.frozen_snapshots`). Every generation
then continues one learner for ``updates_per_generation`` updates against partners
drawn uniformly from that pool, per environment and per episode. The skill spread is
what FCP relies on: partners of every level, not only the finished ones.

The pool is written as a pool document (``generations/000/fcp_pool.json`` in the run
folder); a second FCP experiment names it in ``reuse`` and trains only its learner,
against exactly those checkpoints. The algorithm's population (what the run evaluates
and ranks) is the learner's lineage; the frozen partners stay registry members.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from atdrone.config import ConfigError
from atdrone.population.base import Algorithm, GenerationReport, Oracle, TrainingRecord, frozen_snapshots, record
from atdrone.teams.partners import Uniform
from atdrone.teams.pools import check_pool, pool_document

POOL_DOCUMENT = "fcp_pool.json"


@dataclass(frozen=True)
class FCPConfig:
    """seeds x levels: the frozen pool; reuse: a pool document an earlier FCP run wrote ("": train one)."""

    seeds: int = 3
    levels: int = 3
    reuse: str = ""


class FCP(Algorithm):
    name = "fcp"
    Config = FCPConfig

    def __init__(self, config: FCPConfig, seed: int) -> None:
        super().__init__(config, seed)
        self.pool: list[str] = []  # the frozen partners' ids

    @classmethod
    def check_config(cls, cfg: Any, path: str) -> None:
        for key in ("seeds", "levels"):
            if getattr(cfg, key) < 1:
                raise ConfigError(f"{path}.{key}", f"must be >= 1, got {getattr(cfg, key)}")
        if cfg.reuse:
            check_pool(cfg.reuse, best_response=False, path=f"{path}.reuse")

    @classmethod
    def check_experiment(cls, cfg: Any, experiment: Any, path: str) -> None:
        if cfg.reuse:
            check_pool(cfg.reuse, best_response=False, path=f"{path}.reuse", task=experiment.task)
        if not cfg.reuse and experiment.updates_per_generation < cfg.levels:
            raise ConfigError(
                f"{path}.levels",
                f"{cfg.levels} skill levels need updates_per_generation >= {cfg.levels}, "
                f"got {experiment.updates_per_generation}",
            )

    def state(self) -> dict[str, Any]:
        return {**super().state(), "pool": list(self.pool)}

    def load_state(self, state: Mapping[str, Any]) -> None:
        super().load_state(state)
        self.pool = list(state.get("pool", []))

    def generation(self, oracle: Oracle) -> GenerationReport:
        training: list[TrainingRecord] = []
        documents: dict[str, dict[str, Any]] = {}
        if not self.pool:
            if self.config.reuse:
                self.pool = oracle.zoo_members(self.config.reuse)
            else:
                cfg = self.config
                self.pool, training, splits = frozen_snapshots(oracle, cfg.seeds, cfg.levels, {"role": "fcp partner"})
                paths = [(m, str(oracle.checkpoint_path(m))) for m in self.pool]
                documents[POOL_DOCUMENT] = pool_document(
                    "fcp_pool", paths, f"FCP's frozen pool: {cfg.seeds} self-play runs x levels of {splits} updates"
                )
        parent = self.population[-1] if self.population else None
        trained = oracle.train(parent, partners=Uniform(tuple(self.pool)))
        member = oracle.register(trained, [parent] if parent else [], {"role": "fcp learner"})
        self.population.append(member)
        training.append(record(member, trained))
        return GenerationReport(
            oracle.generation, self.name, [member], list(self.population), training=training, documents=documents
        )
