"""What a population algorithm is, and what it may ask of the service.

An algorithm is a class in :data:`atdrone.population.ALGORITHMS` with a typed config
section (``Config``, a dataclass parsed from the experiment document's section named
after the algorithm) and one :meth:`Algorithm.generation` method that reads top to
bottom, calling the :class:`Oracle` the coordinator provides: evaluate these teams;
train a best response from this member against this partner distribution; register
it; retire members. Its state is plain JSON (:meth:`state` / :meth:`load_state`),
saved after every generation; everything random in a generation comes from
``oracle.rng`` and the seeds the oracle derives from (experiment seed, generation), so
a resumed generation repeats exactly.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar, Protocol

import numpy as np

from atdrone.config import ConfigError, TaskConfig, parse_document
from atdrone.learn.ppo import PPOConfig, architecture
from atdrone.teams.partners import PartnerDistribution

Team = tuple[str, ...]


@dataclass(frozen=True)
class MatchResult:
    """An evaluation match: a team in slot order (the learner in its num_ctrl slots first) and its metrics."""

    team: Team
    metrics: dict[str, float]  # SUC, COL, AST, REW
    episodes: int
    seed: int


@dataclass
class Trained:
    """A learner that finished training, before it is registered.

    ``drawn``: the partner profiles ("a|b", ids sorted) of the episodes it trained on, as
    counted by the rollout; ``env_steps``: environment steps its rollouts took;
    ``samples``: the learner samples (learner drone-steps) its updates used; ``handle`` is
    the oracle's own (the learner actor).
    """

    start_from: str | None
    seed: int
    history: list[dict[str, float]]
    drawn: dict[str, int]
    hparams: dict[str, float]
    partners: dict[str, Any]
    env_steps: int = 0
    samples: int = 0
    handle: Any = None


@dataclass
class TrainingRecord:
    """What one learner of a generation trained from, against what, and how it went."""

    member: str
    parent: str | None
    seed: int
    partners: dict[str, Any]
    drawn: dict[str, int]
    history: list[dict[str, float]]
    env_steps: int = 0
    samples: int = 0


@dataclass
class GenerationReport:
    """One generation: its learners, the population after it, training, matches, and the algorithm's numbers.

    ``metrics``: scalars the driver logs to MLflow at the generation's step (e.g.
    ``pop/rho/<member>``); ``documents``: JSON artifacts written to the generation's
    folder (e.g. ``hypergraph.json``); ``budget``: the run's totals so far (``env_steps``
    and ``learner_samples`` of training, ``eval_env_steps`` of evaluation matches),
    filled in by the coordinator.
    """

    generation: int
    algorithm: str
    learners: list[str]
    population: list[str]
    training: list[TrainingRecord] = field(default_factory=list)
    matches: list[MatchResult] = field(default_factory=list)
    removed: list[str] = field(default_factory=list)
    metrics: dict[str, float] = field(default_factory=dict)
    documents: dict[str, dict[str, Any]] = field(default_factory=dict)
    budget: dict[str, int] = field(default_factory=dict)
    wall_s: float = 0.0


class Oracle(Protocol):
    """What the coordinator does for an algorithm (see :class:`atdrone.service.coordinator.Coordinator`)."""

    generation: int
    num_p: int
    num_ctrl: int
    num_partners: int
    updates_per_generation: int
    ppo: PPOConfig
    rng: np.random.Generator  # this generation's, derived from (experiment seed, generation)

    def evaluate(self, teams: Sequence[Team], episodes: int | Sequence[int] | None = None) -> list[MatchResult]:
        """Play each team (learner id in its num_ctrl slots, then partner ids) and record the matches.

        ``episodes``: per team (or one count for all; default the experiment's eval_episodes),
        each call with fresh seeds, so repeated calls add independent episodes.
        """
        ...

    def train(
        self,
        start_from: str | None,
        partners: PartnerDistribution | None,
        hparams: Mapping[str, float] | None = None,
        updates: int | None = None,
    ) -> Trained:
        """A best response: a learner from ``start_from``'s weights (fresh when None) trained ``updates``
        updates (default updates_per_generation) against partners drawn from ``partners`` per
        environment and episode (self-play when None)."""
        ...

    def register(self, trained: Trained, parents: Sequence[str], tags: Mapping[str, Any] | None = None) -> str:
        """Save the trained learner as a population member (checkpoint + registry row, with ``tags``
        and the algorithm's :meth:`Algorithm.member_tags`); returns its id."""
        ...

    def checkpoint_path(self, member: str) -> Path:
        """Where a member's checkpoint file is."""
        ...

    def retire(self, members: Sequence[str]) -> None:
        """Mark members retired in the registry."""
        ...

    def zoo_members(self, zoo: str) -> list[str]:
        """The ids under which a zoo's members can be partners (``zoo1:greedy`` ...)."""
        ...


class Algorithm:
    """Base of the table's algorithms: a config section, a population and one generation method."""

    name: ClassVar[str]
    Config: ClassVar[type]

    def __init__(self, config: Any, seed: int) -> None:
        self.config = config
        self.seed = seed
        self.population: list[str] = []

    @classmethod
    def parse_config(cls, section: Mapping[str, Any], path: str) -> Any:
        """The typed config section; ConfigError naming ``path.key`` when invalid."""
        cfg = parse_document(cls.Config, dict(section), path)
        cls.check_config(cfg, path)
        return cfg

    @classmethod
    def check_config(cls, cfg: Any, path: str) -> None:
        """Further checks of a parsed section (raise ConfigError)."""

    @classmethod
    def check_experiment(cls, cfg: Any, experiment: Any, path: str) -> None:
        """Checks of the section against the experiment's shared settings (raise ConfigError)."""

    def generation(self, oracle: Oracle) -> GenerationReport:
        raise NotImplementedError

    def architecture(self, ppo: PPOConfig, task: TaskConfig) -> dict[str, Any]:
        """The learners' network header (default: the PPO config's actor-critic, decentralised critic)."""
        return architecture(ppo)

    @classmethod
    def result_tags(cls, cfg: Any) -> dict[str, str]:
        """What a run of this section may call its result (e.g. a best response): the parent MLflow
        run's tags (``atdrone.<key>``) and every registered member's registry tags."""
        return {}

    def member_tags(self) -> dict[str, str]:
        """Tags of every member this algorithm registers: :meth:`result_tags` of its section."""
        return self.result_tags(self.config)

    def state(self) -> dict[str, Any]:
        """JSON state to continue after the last completed generation."""
        return {"population": list(self.population)}

    def load_state(self, state: Mapping[str, Any]) -> None:
        self.population = list(state.get("population", []))

    @classmethod
    def figures(cls, report: GenerationReport, out_dir: Path) -> list[Path]:
        """Pictures of a generation (drawn in the driver); none by default."""
        return []


def require_population(cfg: Any, path: str, minimum: int = 2) -> None:
    if cfg.population_size < minimum:
        raise ConfigError(
            f"{path}.population_size", f"a population needs at least {minimum} members, got {cfg.population_size}"
        )


def record(member: str, trained: Trained) -> TrainingRecord:
    """The report's record of a registered learner."""
    return TrainingRecord(
        member,
        trained.start_from,
        trained.seed,
        trained.partners,
        trained.drawn,
        trained.history,
        trained.env_steps,
        trained.samples,
    )


def frozen_snapshots(
    oracle: Oracle, seeds: int, levels: int, tags: Mapping[str, Any] | None = None
) -> tuple[list[str], list[TrainingRecord], list[int]]:
    """``seeds`` self-play runs, each frozen at ``levels`` evenly spaced skill levels of its
    ``updates_per_generation`` updates (each level's member is the next one's parent).

    Returns the members (run by run, early to final), their training records and the
    updates of each level. HOLA-Drone V2's Pi_0 and FCP's partner pool are built this way.
    """
    total = oracle.updates_per_generation
    splits = [total // levels + (i < total % levels) for i in range(levels)]
    members: list[str] = []
    training: list[TrainingRecord] = []
    for _ in range(seeds):
        parent: str | None = None
        for updates in splits:
            trained = oracle.train(parent, None, updates=updates)
            member = oracle.register(trained, [parent] if parent else [], tags)
            training.append(record(member, trained))
            members.append(member)
            parent = member
    return members, training, splits
