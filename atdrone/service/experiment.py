"""Experiment configs for the population training service (configs/experiments/*.json).

One service, several algorithms, chosen by ``algorithm``:
  sp         IPPO self-play: one learner fills every pursuer slot;
  pbt        a population of IPPO learners, partners drawn from the population, with
             exploit/explore of learning rate and entropy coefficient;
  hola       HOLA-Drone V2: partners drawn from rho (1 / preference centrality);
  hola_no_g  the ablation: partners drawn uniformly from the population;
  br         best response to a fixed zoo.
Every key is documented on :class:`ExperimentConfig`; bad documents are refused with
a ConfigError naming the field.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from atdrone.config import OPTIONAL, ConfigError, check_task_field, load_config, read_document, require_at_least
from atdrone.learn.ppo import ppo_config
from atdrone.policies.zoo import load_zoo

ALGORITHMS = ("sp", "pbt", "hola", "hola_no_g", "br")
# integer settings that must be >= 1 (jobs/train.py also offers them as overrides)
POSITIVE_INTS = (
    "generations",
    "updates_per_generation",
    "num_workers",
    "envs_per_worker",
    "rollout_steps",
    "population_size",
    "learners_per_generation",
    "eval_episodes",
    "final_episodes",
)


@dataclass(frozen=True)
class ExperimentConfig:
    """A population training experiment.

    name: experiment (and MLflow experiment) name; runs go to ``out_dir/name``.
    generations: outer iterations; updates_per_generation: PPO updates per learner
    and generation; num_workers x envs_per_worker environments collect
    rollout_steps steps per update. population_size: HOLA/PBT population capacity.
    learners_per_generation: best-response learners dispatched per generation (HOLA).
    eval_episodes: episodes per hyperedge (evaluation match). final_zoo /
    final_episodes: the zoo every member is evaluated on at the end (empty: skip).
    zoo: the partners of ``br``. ppo: overrides of the PPO preset. learner_gpus: GPUs
    each learner actor asks Ray for (its PPO update then runs on CUDA; 0: CPU).
    experiment: the MLflow experiment (default: the config's own name, kept when a run
    is renamed with an override, so every run of one config lands in one experiment).
    """

    name: str
    algorithm: Literal["sp", "pbt", "hola", "hola_no_g", "br"]
    task: str
    seed: int = 0
    generations: int = 3
    updates_per_generation: int = 10
    num_workers: int = 2
    envs_per_worker: int = 32
    rollout_steps: int = 128
    population_size: int = 4
    learners_per_generation: int = 1
    eval_episodes: int = 64
    zoo: str = field(default="", metadata=OPTIONAL)
    final_zoo: str = field(default="zoo1", metadata=OPTIONAL)
    final_episodes: int = 200
    pbt_perturb: float = 1.25
    preset: str = "default"
    ppo: dict[str, Any] = field(default_factory=dict)
    out_dir: str = "runs"
    gif: bool = True
    learner_gpus: float = 0.0
    experiment: str = field(default="", metadata=OPTIONAL)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def load_experiment(path_or_doc: str | Path | dict[str, Any], **overrides: Any) -> ExperimentConfig:
    """A validated ExperimentConfig from a JSON file (or mapping) plus overrides."""
    base = dict(path_or_doc) if isinstance(path_or_doc, Mapping) else read_document(path_or_doc, "experiments")
    if isinstance(base, dict) and isinstance(base.get("name"), str) and overrides.get("experiment") is None:
        overrides["experiment"] = base.get("experiment") or base["name"]
    cfg: ExperimentConfig = load_config(ExperimentConfig, base, "experiments", **overrides)
    check_task_field(cfg.task)
    ppo_config(cfg.ppo, cfg.preset)
    require_at_least(cfg, POSITIVE_INTS)
    if cfg.algorithm == "br" and not cfg.zoo:
        raise ConfigError("zoo", "the br algorithm needs a zoo to respond to")
    for key in ("zoo", "final_zoo"):
        if getattr(cfg, key):
            try:
                load_zoo(getattr(cfg, key))
            except ConfigError as exc:
                raise ConfigError(key, str(exc)) from None
    if cfg.algorithm in ("pbt", "hola", "hola_no_g") and cfg.population_size < 2:
        raise ConfigError("population_size", f"a population needs at least 2 members, got {cfg.population_size}")
    if cfg.learner_gpus < 0:
        raise ConfigError("learner_gpus", f"must be >= 0, got {cfg.learner_gpus}")
    if cfg.pbt_perturb <= 1.0:
        raise ConfigError("pbt_perturb", f"must be > 1, got {cfg.pbt_perturb}")
    return cfg


def registry_name(run: str) -> str:
    """The name of a run's registry actor in namespace "atdrone" (another driver finds it by this name)."""
    return f"registry-{run}"
