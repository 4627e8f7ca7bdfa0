"""Benchmark configs (configs/benchmarks/*.json): methods x tasks x seeds, zoos, budgets.

A benchmark is the product of its methods, tasks and seeds; each (method, task, seed) is
one ordinary service experiment (a *cell*), plus, with ``best_response``, a best response
per (task, test zoo, seed): the upper bound. Example::

    {"name": "quick", "tasks": ["4p2e1o"], "seeds": [0, 1, 2], "env_steps": 262144,
     "methods": {"sp": {"experiment": "sp_quick"}, "hola": {"experiment": "hola_quick"}},
     "zoos": ["zoo1", "zoo2", "zoo3"], "eval_episodes": 200}

name: the benchmark (a folder ``<out_dir>/<name>/`` and the MLflow experiment).
methods: label -> :class:`MethodSpec` (an experiment config of configs/experiments and
overrides of its keys); the label names the method in every table.
tasks, seeds: the grid. zoos: the test zoos every final learner is evaluated on;
select_zoo: the zoo every choice is made on (which seed's weights to keep), evaluated too,
never a test zoo. env_steps: the training budget of every run (generations are planned
per algorithm by :func:`atdrone.benchmark.budget.plan`); updates_per_generation: PPO
updates per learner per generation. eval_episodes: episodes per final learner and zoo.
pool: the training pool of the methods that train against one (their section's ``pool``;
"": each method's own); a method's ``pool`` overrides it. experiment: keys set in every
cell's experiment (e.g. ``num_workers``, ``ppo``). best_response: train the upper bound.
references: the methods the others are compared with in paired differences (default the
first method). bootstrap_reps / bootstrap_seed: the stratified bootstrap of the aggregates.
results_dir: the report's folder (default ``<out_dir>/<name>/results/<name>``). max_parallel: at
most this many cells at once (0: as many as the cluster's CPUs hold).
extra_seeds: more seeds for some (method, task) runs, e.g. where a comparison needs them:
``[{"methods": ["hola", "sp"], "tasks": ["4p2e5o"], "seeds": [3, 4]}]`` (:class:`ExtraSeeds`);
the aggregates use ``seeds`` only, the per-cell tables and paired differences every seed.
smoke_test: the benchmark only checks that the grid runs end to end; its report says it ranks
nothing, and a HOLA method planned for fewer than :data:`MIN_HOLA_GENERATIONS` hypergraph
generations is marked there instead of refused (:func:`check_hola_generations`).
protocols: protocols of team events (configs/protocols, e.g. ``zoo3+swap``) every method's
final learner is also played on (its record's ``protocols``; the report's team-change table);
they have no bounds and take no part in the other tables.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from atdrone.config import (
    OPTIONAL,
    ConfigError,
    check_run_name,
    check_seed,
    check_task_field,
    load_config,
    read_document,
    read_object,
)
from atdrone.policies.zoo import PolicyError, load_zoo

PLACEMENT = ("out_dir", "results_dir", "max_parallel")  # where and how fast, not what: a resume may change them
RESOURCES = ("learner_threads", "learner_gpus")  # experiment keys outside the digest (how fast, not what)
LABELS = ("smoke_test",)  # what a report says about the grid, not what runs: outside the digest too
# HOLA's generation 0 trains Pi_0 alone; every later generation builds and plays the hypergraph G'_t. A run planned
# for fewer hypergraph generations than this measures little of the method (at one planned generation, none).
MIN_HOLA_GENERATIONS = 3
HOLA_ALGORITHMS = ("hola", "hola_no_g")


@dataclass(frozen=True)
class MethodSpec:
    """One method: an experiment config (a configs/experiments name or a path) and overrides of its keys.

    pool: the training pool of a method that trains against one ("": the benchmark's ``pool``)."""

    experiment: str
    overrides: dict[str, Any] = field(default_factory=dict)
    pool: str = field(default="", metadata=OPTIONAL)


@dataclass(frozen=True)
class ExtraSeeds:
    """More seeds for the runs of ``methods`` x ``tasks`` (beside the benchmark's ``seeds``)."""

    methods: tuple[str, ...]
    tasks: tuple[str, ...]
    seeds: tuple[int, ...]


@dataclass(frozen=True)
class BenchmarkConfig:
    """A benchmark grid; see the module docstring for every key."""

    name: str
    methods: dict[str, MethodSpec]
    tasks: tuple[str, ...]
    seeds: tuple[int, ...] = (0, 1, 2)
    zoos: tuple[str, ...] = ("zoo1", "zoo2", "zoo3")
    select_zoo: str = "validation"
    env_steps: int = 1_048_576
    updates_per_generation: int = 16
    eval_episodes: int = 500
    pool: str = field(default="", metadata=OPTIONAL)
    experiment: dict[str, Any] = field(default_factory=dict)
    best_response: bool = True
    references: tuple[str, ...] = ()
    bootstrap_reps: int = 2000
    bootstrap_seed: int = 0
    max_parallel: int = 0
    out_dir: str = "runs/benchmarks"
    results_dir: str = field(default="", metadata=OPTIONAL)
    extra_seeds: tuple[ExtraSeeds, ...] = ()
    smoke_test: bool = False
    protocols: tuple[str, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """The document form (what ``config.json`` of the benchmark folder keeps)."""
        return json.loads(json.dumps(asdict(self)))

    def digest(self) -> str:
        """What makes two configs the same benchmark: every key but where its files go, and the partners:
        the zoo manifest's version of each task (a drone retrained is another benchmark, never mixed in)."""
        doc = {k: v for k, v in self.to_dict().items() if k not in PLACEMENT + LABELS}
        # the learner's resources, which a resumed run may change too: where its update runs, not what it computes
        doc["experiment"] = {k: v for k, v in doc["experiment"].items() if k not in RESOURCES}
        for key in ("extra_seeds", "protocols"):  # a config without them keeps the digest it had before them
            if not doc[key]:
                del doc[key]
        doc["zoo_versions"] = self.zoo_versions()
        return hashlib.sha256(json.dumps(doc, sort_keys=True).encode()).hexdigest()[:16]

    def zoo_versions(self) -> dict[str, str]:
        """Task -> the version of its zoos in the zoo manifest."""
        from atdrone.policies.manifest import task_version

        return {task: task_version(task) for task in self.tasks}

    @property
    def played_zoos(self) -> list[str]:
        """The zoos every method's learner is evaluated with: the test zoos, then the selection zoo."""
        return [*self.zoos, self.select_zoo] if self.select_zoo else list(self.zoos)

    @property
    def folder(self) -> Path:
        """The benchmark's working folder: cells' runs and records."""
        return Path(self.out_dir).resolve() / self.name

    @property
    def results(self) -> Path:
        """The report's folder: ``results_dir``, by default ``<out_dir>/<name>/results/<name>`` (beside the cells; the
        committed ``benchmarks/results/`` folders are written only when named)."""
        return Path(self.results_dir).resolve() if self.results_dir else self.folder / "results" / self.name

    @property
    def reference_methods(self) -> tuple[str, ...]:
        return self.references or (next(iter(self.methods)),)

    def seeds_of(self, method: str, task: str) -> tuple[int, ...]:
        """The seeds of a method's runs on a task: ``seeds`` and its :class:`ExtraSeeds`, in that order."""
        extra = [s for e in self.extra_seeds if method in e.methods and task in e.tasks for s in e.seeds]
        return self.seeds + tuple(s for s in dict.fromkeys(extra) if s not in self.seeds)


def check_hola_generations(cfg: BenchmarkConfig, label: str, algorithm: str, generations: int) -> str:
    """A HOLA method (``hola``, ``hola_no_g``) planned for fewer than :data:`MIN_HOLA_GENERATIONS` hypergraph
    generations (``generations`` - 1: generation 0 trains Pi_0 alone) is refused, naming ``methods.<label>``;
    in a smoke test it is allowed and the mark for its report returned. '' for every other method."""
    hypergraph = generations - 1
    if algorithm not in HOLA_ALGORITHMS or hypergraph >= MIN_HOLA_GENERATIONS:
        return ""
    why = (
        f"{label} is planned for {generations} generation(s) at {cfg.env_steps:,} env steps: "
        f"{hypergraph} hypergraph generation(s) after Pi_0, fewer than {MIN_HOLA_GENERATIONS}"
    )
    if cfg.smoke_test:
        return why
    raise ConfigError(
        f"methods.{label}",
        f"{why}; raise env_steps or lower updates_per_generation (or mark the benchmark smoke_test: it then ranks "
        "nothing)",
    )


def method_document(spec: MethodSpec) -> dict[str, Any]:
    """The method's experiment document (its config file) with its overrides applied."""
    doc: dict[str, Any] = dict(read_object(spec.experiment, "experiments", _experiment_names()))
    for key, value in spec.overrides.items():
        if isinstance(value, Mapping) and isinstance(doc.get(key), Mapping):
            doc[key] = {**doc[key], **value}
        else:
            doc[key] = value
    return doc


def _experiment_names() -> tuple[str, ...]:
    from atdrone.config import CONFIG_DIR

    return tuple(sorted(p.stem for p in (CONFIG_DIR / "experiments").glob("*.json")))


def parse_benchmark(path_or_doc: str | Path | Mapping[str, Any], **overrides: Any) -> BenchmarkConfig:
    """A BenchmarkConfig from a JSON file (a configs/benchmarks name or a path) or a mapping, its own keys
    checked; :func:`atdrone.benchmark.cells.load_benchmark` also builds every cell's experiment."""
    if isinstance(path_or_doc, Mapping):
        doc = dict(path_or_doc)
    else:
        names = tuple(sorted(p.stem for p in _benchmark_dir().glob("*.json")))
        found = read_document(path_or_doc, "benchmarks", names)
        if not isinstance(found, dict):
            raise ConfigError(None, f"{path_or_doc} must hold one JSON object (a benchmark config)")
        doc = found
    cfg: BenchmarkConfig = load_config(BenchmarkConfig, doc, "benchmarks", **overrides)
    _check(cfg)
    return cfg


def _benchmark_dir() -> Path:
    from atdrone.config import CONFIG_DIR

    return CONFIG_DIR / "benchmarks"


def _check(cfg: BenchmarkConfig) -> None:
    check_run_name(cfg.name)
    if not cfg.methods:
        raise ConfigError("methods", "name at least one method")
    for label in cfg.methods:
        check_run_name(label, f"methods.{label}")
        if label in ("br", "floor"):
            raise ConfigError(f"methods.{label}", "'br' and 'floor' name the bounds; call the method otherwise")
    if not cfg.tasks:
        raise ConfigError("tasks", "name at least one task")
    for i, task in enumerate(cfg.tasks):
        check_task_field(task, f"tasks[{i}]")
    if not cfg.seeds or len(set(cfg.seeds)) != len(cfg.seeds):
        raise ConfigError("seeds", f"name distinct seeds, got {list(cfg.seeds)}")
    for i, seed in enumerate(cfg.seeds):
        check_seed(seed, f"seeds[{i}]")
    if not cfg.zoos:
        raise ConfigError("zoos", "name at least one test zoo")
    for i, zoo in enumerate(cfg.zoos):
        _check_zoo(zoo, f"zoos[{i}]", cfg.tasks)
    if cfg.select_zoo:
        _check_zoo(cfg.select_zoo, "select_zoo", cfg.tasks)
        if cfg.select_zoo in cfg.zoos:
            raise ConfigError("select_zoo", f"{cfg.select_zoo!r} is a test zoo: choose on the validation zoo")
    if cfg.max_parallel < 0:
        raise ConfigError("max_parallel", f"must be >= 0 (0: as many as the CPUs hold), got {cfg.max_parallel}")
    for key in ("env_steps", "updates_per_generation", "eval_episodes", "bootstrap_reps"):
        if getattr(cfg, key) < 1:
            raise ConfigError(key, f"must be >= 1, got {getattr(cfg, key)}")
    for ref in cfg.references:
        if ref not in cfg.methods:
            raise ConfigError("references", f"{ref!r} is not a method (methods: {', '.join(cfg.methods)})")
    for i, extra in enumerate(cfg.extra_seeds):
        where = f"extra_seeds[{i}]"
        for j, method in enumerate(extra.methods):
            if method not in cfg.methods:
                raise ConfigError(f"{where}.methods[{j}]", f"{method!r} is not a method of the benchmark")
        for j, task in enumerate(extra.tasks):
            if task not in cfg.tasks:
                raise ConfigError(f"{where}.tasks[{j}]", f"{task!r} is not a task of the benchmark")
        if not extra.seeds or not extra.methods or not extra.tasks:
            raise ConfigError(where, "name at least one method, task and seed")
        for j, seed in enumerate(extra.seeds):
            check_seed(seed, f"{where}.seeds[{j}]")
    for i, name in enumerate(cfg.protocols):
        _check_protocol(name, f"protocols[{i}]", cfg.tasks)
    for key in ("name", "task", "seed", "algorithm", "out_dir", "generations"):
        if key in cfg.experiment:
            raise ConfigError(f"experiment.{key}", "set by the benchmark for every cell")


def _check_protocol(name: str, path: str, tasks: Sequence[str]) -> None:
    """ConfigError at ``path`` unless ``name`` is a protocol whose zoo every task can play."""
    from atdrone.teams.protocols import evaluation_protocol, is_protocol

    if not is_protocol(name):
        raise ConfigError(path, f"{name!r} is not a protocol of team events (configs/protocols, or a JSON path)")
    try:
        protocol = evaluation_protocol(name)
    except ConfigError as exc:
        raise ConfigError(path, str(exc)) from None
    _check_zoo(protocol.zoo, path, tasks)


def _check_zoo(zoo: str, path: str, tasks: Sequence[str]) -> None:
    try:
        for task in tasks:
            load_zoo(zoo, task).check()
    except (ConfigError, PolicyError) as exc:
        raise ConfigError(path, str(exc)) from None
