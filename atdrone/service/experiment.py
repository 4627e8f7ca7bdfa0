"""Experiment configs for the population training service (configs/experiments/*.json).

One service, several algorithms, chosen by ``algorithm`` from the table
:data:`atdrone.population.ALGORITHMS` (sp, br, pbt, hola, hola_no_g, ...). Settings
every algorithm shares are the fields of :class:`ExperimentConfig`; an algorithm's own
settings are a section named after it, typed by the algorithm's ``Config``, e.g.
``"hola": {"population_size": 4, "learners_per_generation": 1}``. The PPO section means
exactly what it means for local training: ``ppo.num_envs`` environments per update
(split evenly over ``num_workers`` rollout workers) and ``ppo.rollout_steps`` steps each.
Bad documents are refused with a ConfigError naming the field.

Migration from the flat documents of earlier versions: ``population_size``,
``learners_per_generation`` (hola, hola_no_g, pbt), ``pbt_perturb`` (pbt: ``perturb``)
and ``zoo`` (br) moved into the algorithm's section; ``envs_per_worker`` x ``num_workers``
became ``ppo.num_envs`` and ``rollout_steps`` became ``ppo.rollout_steps``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any

from atdrone.config import (
    OPTIONAL,
    ConfigError,
    TaskConfig,
    check_run_name,
    check_seed,
    check_task_field,
    load_config,
    read_object,
    require_at_least,
    require_at_most,
)
from atdrone.learn.ppo import ppo_config, ppo_document
from atdrone.policies.zoo import PolicyError, load_zoo

# integer settings that must be >= 1 (jobs/train.py also offers them as overrides)
POSITIVE_INTS = (
    "generations",
    "updates_per_generation",
    "num_workers",
    "eval_episodes",
    "final_episodes",
    "learner_threads",
)
# upper bounds: evaluation episodes and rollout workers allocate, generations bound a run's length
LIMITS = {
    "generations": 10_000,
    "updates_per_generation": 1_000_000,
    "num_workers": 256,
    "eval_episodes": 100_000,
    "final_episodes": 1_000_000,
    "learner_threads": 256,
}
MAX_LR = 1.0  # a learning rate beyond it only makes NaN weights
MAX_EPISODES = 1_000_000  # any episode count of an algorithm's section

# keys of earlier, flat documents -> where they live now
MOVED = {
    "population_size": 'the algorithm\'s section, e.g. "hola": {"population_size": 4}',
    "learners_per_generation": 'the algorithm\'s section, e.g. "hola": {"learners_per_generation": 1}',
    "pbt_perturb": '"pbt": {"perturb": ...}',
    "zoo": '"br": {"zoo": ...}',
    "envs_per_worker": "ppo.num_envs (every environment of an update, split over num_workers)",
    "rollout_steps": "ppo.rollout_steps",
}


@dataclass(frozen=True)
class ExperimentConfig:
    """A population training experiment.

    name: experiment (and MLflow experiment) name; runs go to ``out_dir/name``.
    algorithm: a name of the algorithms table; its section (``section``, the document's
    key named after the algorithm) holds its own settings. generations: outer
    iterations; updates_per_generation: PPO updates of each learner per generation
    (the length of its learning-rate schedule); num_workers: rollout workers sharing
    ppo.num_envs. eval_episodes: episodes per evaluation match. final_zoo /
    final_episodes: the zoo every member is evaluated on at the end (empty: skip), a test
    zoo: reported, never used to choose; a protocol of team events (``zoo3+swap``) may stand
    wherever a zoo is named, and is played with its zoo. select_zoo: the zoo the run's best member and the
    MLflow champion are chosen on, final_episodes episodes per member (default the
    validation zoo; it must share no drone with Zoos 1-3; empty: the last member).
    ppo: overrides of the PPO preset. learner_gpus: GPUs each learner actor asks Ray
    for (its update then runs on CUDA; 0: CPU); learner_threads: torch threads of a
    learner's update on the CPU (the rollout workers are idle while it runs, as in the
    local trainer's update_threads). experiment: the MLflow experiment
    (default: the config's own name, kept when a run is renamed with an override).
    register: register the best member as a version of the model ``atdrone-<experiment>``
    (a benchmark's cells do not: the benchmark registers only the weights it publishes).
    protocol: train with a protocol's team events and split of the team drawn in every
    rollout episode (configs/protocols/; its zoo is not used: the partners stay the
    algorithm's); recorded in each member's registry tags and the MLflow run.
    """

    name: str
    algorithm: str
    task: str
    seed: int = 0
    generations: int = 3
    updates_per_generation: int = 10
    num_workers: int = 2
    eval_episodes: int = 64
    final_zoo: str = field(default="zoo1", metadata=OPTIONAL)
    final_episodes: int = 200
    select_zoo: str = field(default="validation", metadata=OPTIONAL)
    preset: str = "default"
    ppo: dict[str, Any] = field(default_factory=dict)
    out_dir: str = "runs"
    gif: bool = True
    learner_gpus: float = 0.0
    learner_threads: int = 2
    experiment: str = field(default="", metadata=OPTIONAL)
    register: bool = True
    section: dict[str, Any] = field(default_factory=dict)
    protocol: str = field(default="", metadata=OPTIONAL)

    def algorithm_config(self) -> Any:
        """The algorithm's typed config section."""
        from atdrone.population import ALGORITHMS

        return ALGORITHMS[self.algorithm].parse_config(self.section, self.algorithm)

    def to_dict(self) -> dict[str, Any]:
        """The document form: the section under the algorithm's name."""
        doc = asdict(self)
        doc[self.algorithm] = doc.pop("section")
        if not self.protocol:  # a run without one saves the document runs saved before the key existed
            doc.pop("protocol")
        return doc


def load_experiment(path_or_doc: str | Path | Mapping[str, Any], **overrides: Any) -> ExperimentConfig:
    """A validated ExperimentConfig from a JSON file (or mapping) plus overrides.

    Everything a run would trip over later is checked here, before any training: the
    run name, seed and sizes, the task, the PPO section, the algorithm's section against
    the shared settings, and every zoo named (final_zoo, the algorithm's ``zoo``) down to
    its checkpoint files.
    """
    from atdrone.population import ALGORITHMS

    base = dict(path_or_doc) if isinstance(path_or_doc, Mapping) else read_object(path_or_doc, "experiments")
    for key, where in MOVED.items():
        if key in base:
            raise ConfigError(key, f"moved: set it in {where} (see atdrone/service/experiment.py)")
    algorithm = base.get("algorithm")
    if not isinstance(algorithm, str) or algorithm not in ALGORITHMS:
        raise ConfigError("algorithm", f"must be one of {sorted(ALGORITHMS)}, got {algorithm!r}")
    base["section"] = base.pop(algorithm, {})
    if isinstance(base.get("name"), str) and overrides.get("experiment") is None:  # --name renames the experiment
        overrides["experiment"] = base.get("experiment") or overrides.get("name") or base["name"]
    cfg: ExperimentConfig = load_config(ExperimentConfig, base, "experiments", **overrides)
    _check_settings(cfg)
    task = check_task_field(cfg.task)
    ppo = ppo_config(cfg.ppo, cfg.preset)
    cfg = replace(cfg, ppo=ppo_document(ppo))  # every value, as the run saves it
    if ppo.num_envs % cfg.num_workers:
        raise ConfigError(
            "ppo.num_envs", f"{ppo.num_envs} environments cannot be split evenly over {cfg.num_workers} workers"
        )
    if not 0.0 < ppo.lr <= MAX_LR:
        raise ConfigError("ppo.lr", f"must be in (0, {MAX_LR:g}], got {ppo.lr!r}")
    section = cfg.algorithm_config()
    _check_episode_counts(section, cfg.algorithm)
    ALGORITHMS[cfg.algorithm].check_experiment(section, cfg, cfg.algorithm)  # "<algorithm>.<key>"
    if isinstance(getattr(section, "zoo", None), str) and section.zoo:
        _check_zoo(section.zoo, f"{cfg.algorithm}.zoo", cfg.task)
    if cfg.final_zoo:
        _check_zoo(cfg.final_zoo, "final_zoo", cfg.task)
    if cfg.select_zoo:
        _check_zoo(cfg.select_zoo, "select_zoo", cfg.task)
        _check_disjoint(cfg.select_zoo)
    if cfg.protocol:
        _check_protocol(cfg.protocol, task)
    return cfg


def _check_protocol(name: str, task: TaskConfig) -> None:
    """ConfigError at protocol unless it loads, its split fits the task's pursuer slots (a training call with
    partners caps it at the slots its learner fills, see :meth:`Coordinator.train`) and its team sizes are
    shipped task variants."""
    from atdrone.learn.sizes import check_sizes
    from atdrone.teams.protocols import check_split, load_protocol

    try:
        protocol = load_protocol(name)
    except ConfigError as exc:
        raise ConfigError("protocol", str(exc)) from None
    check_split(protocol.split, task.players.num_p, "protocol")
    check_sizes(protocol.sizes, task, "protocol")


def _check_disjoint(zoo: str) -> None:
    """ConfigError at select_zoo when the selection zoo shares a drone with a test zoo (selection on the test set)."""
    from atdrone.teams.pools import shared_members
    from atdrone.teams.protocols import zoo_of

    shared = shared_members(load_zoo(zoo_of(zoo)[0]))
    if shared:
        raise ConfigError(
            "select_zoo",
            f"{zoo!r} shares drones with the test zoos ({'; '.join(shared)}): choosing on it would look at the "
            "test partners; use the validation zoo or another zoo of unseen drones",
        )


def _check_settings(cfg: ExperimentConfig) -> None:
    """The shared settings that need no file: run name, seed, bounds."""
    check_run_name(cfg.name)
    if cfg.experiment:  # the MLflow experiment and model name: the same rule (no quote reaches a filter string)
        check_run_name(cfg.experiment, "experiment")
    check_seed(cfg.seed)
    require_at_least(cfg, POSITIVE_INTS)
    require_at_most(cfg, LIMITS)
    if cfg.learner_gpus < 0:
        raise ConfigError("learner_gpus", f"must be >= 0, got {cfg.learner_gpus}")


def _check_episode_counts(section: Any, algorithm: str) -> None:
    """ConfigError at ``<algorithm>.<key>`` for an episode count of the algorithm's section over
    :data:`MAX_EPISODES` (each is played, so it bounds a generation's length)."""
    if not is_dataclass(section):
        return
    for f in fields(section):
        value = getattr(section, f.name)
        if f.name.endswith("episodes") and isinstance(value, int) and value > MAX_EPISODES:
            raise ConfigError(f"{algorithm}.{f.name}", f"must be at most {MAX_EPISODES:,}, got {value:,}")


def _check_zoo(zoo: str, path: str, task: str) -> None:
    """ConfigError at ``path`` unless every member of ``zoo`` (or of a protocol's zoo) can be built on ``task``
    (files present and intact)."""
    from atdrone.teams.protocols import zoo_of

    try:
        load_zoo(zoo_of(zoo)[0], task).check()
    except (ConfigError, PolicyError) as exc:
        raise ConfigError(path, str(exc)) from None


def registry_name(run: str) -> str:
    """The name of a run's registry actor in namespace "atdrone" (another driver finds it by this name)."""
    return f"registry-{run}"
