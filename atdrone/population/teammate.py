"""Adaptive teaming with teammate modelling (the paper's Fig. 4): MAPPO, NAHT-D and NAHT-D w/o Dec.

Each is one lineage of learners trained against a training pool
(:mod:`atdrone.teams.pools`: partners drawn per environment and per episode, slots
shuffled, and by default the number of partners drawn too: ``min_partners``; the other
slots are flown by a copy of the learner), never the evaluation zoos unless the section
says ``"best_response": true``, and then every member is tagged a best response. Each generation continues the last
learner for ``updates_per_generation`` updates.

- ``mappo``: PPO with MAPPO's centralised critic over the global state; the learners'
  drones share parameters and the actor reads only its own observation. The local
  trainer's ``mode: "mappo"`` builds the same network (:func:`atdrone.learn.ppo.architecture`
  with a centralised critic).
- ``naht_d``: MAPPO plus the teammate model of :mod:`atdrone.models.teammate`
  (encoder of the last ``history`` steps, 16-wide embedding, decoder of the teammates'
  actions with its loss weighted by ``ppo.teammate_coef``).
- ``naht_d_no_dec``: the ablation without the decoder and its loss.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from atdrone.config import ConfigError, TaskConfig, load_task
from atdrone.learn.ppo import PPOConfig, architecture
from atdrone.models.teammate import TeammateActorCritic, TeammateConfig
from atdrone.population.base import Algorithm, GenerationReport, Oracle, record
from atdrone.teams.partners import LEARNER_COPY, Uniform, VariableCount
from atdrone.teams.pools import check_pool, pool_path, result_label


@dataclass(frozen=True)
class PoolConfig:
    """pool: the training pool (a name of configs/pools/ or a path); best_response: the pool may
    share partners with the evaluation zoos (the result is then labelled a best response);
    min_partners: each episode draws its number of partners uniformly from min_partners to the
    task's partner slots, the other slots flown by a copy of the learner (not trained on);
    equal to the partner slots: always a full set of partners."""

    pool: str = "train_pool"
    best_response: bool = False
    min_partners: int = 1


@dataclass(frozen=True)
class NahtConfig(PoolConfig):
    """The pool, plus the teammate model: past steps read (k), embedding and decoder widths, and the
    choices the paper leaves open (see atdrone.models.teammate and the algorithms docs)."""

    history: int = 1
    embed_dim: int = 16
    decoder_hidden: int = 64
    critic_embedding: bool = True
    detach_embedding: bool = False


class PoolLearner(Algorithm):
    """One lineage of learners trained against a training pool (the table's mappo, naht_d, naht_d_no_dec)."""

    name = "mappo"
    Config = PoolConfig

    @classmethod
    def check_config(cls, cfg: Any, path: str) -> None:
        check_pool(cfg.pool, cfg.best_response, f"{path}.pool")

    @classmethod
    def check_experiment(cls, cfg: Any, experiment: Any, path: str) -> None:
        check_pool(cfg.pool, cfg.best_response, f"{path}.pool", task=experiment.task)
        slots = load_task(experiment.task).players.num_unctrl
        if not 0 <= cfg.min_partners <= slots:
            raise ConfigError(
                f"{path}.min_partners", f"must be in 0..{slots} (the partner slots), got {cfg.min_partners}"
            )

    def architecture(self, ppo: PPOConfig, task: TaskConfig) -> dict[str, Any]:
        return architecture(ppo, centralised_critic=True)

    @classmethod
    def result_tags(cls, cfg: Any) -> dict[str, str]:
        return {"partners": result_label(cfg.best_response), "pool": cfg.pool}

    def generation(self, oracle: Oracle) -> GenerationReport:
        parent = self.population[-1] if self.population else None
        members = tuple(oracle.zoo_members(pool_path(self.config.pool)))
        count = self.config.min_partners
        partners = Uniform(members) if count >= oracle.num_partners else VariableCount((*members, LEARNER_COPY), count)
        trained = oracle.train(parent, partners=partners)
        member = oracle.register(trained, [parent] if parent else [])
        self.population.append(member)
        return GenerationReport(
            oracle.generation, self.name, [member], list(self.population), training=[record(member, trained)]
        )


class MAPPO(PoolLearner):
    name = "mappo"


class NahtD(PoolLearner):
    name = "naht_d"
    Config = NahtConfig  # type: ignore[assignment]
    decoder = True

    @classmethod
    def check_config(cls, cfg: Any, path: str) -> None:
        super().check_config(cfg, path)
        try:
            TeammateConfig(history=cfg.history, embed_dim=cfg.embed_dim, decoder_hidden=cfg.decoder_hidden)
        except ValueError as exc:
            raise ConfigError(path, str(exc)) from None
        if cfg.detach_embedding and not cls.decoder:
            raise ConfigError(f"{path}.detach_embedding", "needs the decoder: nothing else would train the encoder")

    def architecture(self, ppo: PPOConfig, task: TaskConfig) -> dict[str, Any]:
        cfg = self.config
        return TeammateActorCritic.header(
            TeammateConfig(
                num_p=task.players.num_p,
                num_e=task.players.num_e,
                history=cfg.history,
                embed_dim=cfg.embed_dim,
                decoder_hidden=cfg.decoder_hidden,
                decoder=self.decoder,
                critic_embedding=cfg.critic_embedding,
                detach_embedding=cfg.detach_embedding,
                entity_dim=ppo.entity_dim,
                hidden=ppo.hidden,
                init_log_std=ppo.init_log_std,
                proximity=ppo.proximity,
            )
        )


class NahtDNoDec(NahtD):
    name = "naht_d_no_dec"
    decoder = False
