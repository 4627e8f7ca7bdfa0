"""The cells of a benchmark: what each trains and evaluates, as an ordinary service experiment.

Three kinds:

- ``method``: a (method, task, seed) run of the method's experiment at the benchmark's
  budget; its final learner is evaluated on every test zoo and on the selection zoo;
- ``br``: the best response to one test zoo (the ``br`` algorithm, partners drawn
  uniformly from that zoo) per (task, zoo, seed), the upper bound, evaluated on its zoo;
- ``floor``: a random learner (uniform turns) with a zoo's partners per (task, zoo), no
  training: the bottom of the normalised scores.

:func:`run_cell` does one cell where it is called (a Ray task of the benchmark job, on
any node) and returns its record, a JSON object: the final member, its checkpoint and
digest, the budget spent and the metrics per zoo. A cell whose run was interrupted is
resumed by the service (``resume=True``), so calling it again after a kill continues it.
Every final learner with the same seed is evaluated on the same episodes (evaluation
seed ``EVAL_SEED + seed``), so differences between methods are paired.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from atdrone.benchmark.budget import plan
from atdrone.benchmark.config import BenchmarkConfig, check_hola_generations, method_document, parse_benchmark
from atdrone.config import ConfigError, load_task
from atdrone.envs.streams import fold, unit
from atdrone.learn.ppo import ppo_config
from atdrone.policies.base import DroneBatch, StatelessPolicy
from atdrone.service.experiment import ExperimentConfig, load_experiment

EVAL_SEED = 10_000  # evaluation episodes of seed s come from EVAL_SEED + s: apart from training's seeds
FLOOR_SEED = 0
MAX_CELLS = 10_000
CellKind = Literal["method", "br", "floor"]


@dataclass(frozen=True)
class Cell:
    """One unit of the grid: kind, method label ("br" / "floor" for the bounds), task, seed, zoo (bounds)."""

    kind: CellKind
    method: str
    task: str
    seed: int
    zoo: str = ""

    @property
    def name(self) -> str:
        """The cell's name in the benchmark (its record ``cells/<name>.json``)."""
        if self.kind == "method":
            return f"{self.method}-{self.task}-s{self.seed}"
        if self.kind == "br":
            return f"br-{self.zoo}-{self.task}-s{self.seed}"
        return f"floor-{self.zoo}-{self.task}"

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def cells(cfg: BenchmarkConfig) -> list[Cell]:
    """Every cell of the grid, in a fixed order: methods, then best responses, then floors."""
    grid = [Cell("method", m, t, s) for m in cfg.methods for t in cfg.tasks for s in cfg.seeds_of(m, t)]
    if cfg.best_response:
        grid += [Cell("br", "br", t, s, z) for t in cfg.tasks for z in cfg.zoos for s in cfg.seeds]
    grid += [Cell("floor", "floor", t, FLOOR_SEED, z) for t in cfg.tasks for z in cfg.zoos]
    return grid


def run_name(cfg: BenchmarkConfig, cell: Cell) -> str:
    """The service run of a cell: its folder under ``<folder>/runs/``, MLflow experiment and registry actor,
    named after the benchmark too (two benchmarks on one cluster never share a registry actor's name)."""
    return f"{cfg.name}-{cell.name}"


def experiment_document(cfg: BenchmarkConfig, cell: Cell) -> dict[str, Any]:
    """The cell's experiment document: the method's config (or a best response to the cell's zoo) at the
    benchmark's budget, with no final evaluation of the service's own (the benchmark evaluates)."""
    if cell.kind == "floor":
        raise ValueError("a floor cell trains nothing")
    if cell.kind == "method":
        spec = cfg.methods[cell.method]
        doc = method_document(spec)
        pool = spec.pool or cfg.pool
        algorithm = doc.get("algorithm")
        if pool and isinstance(algorithm, str) and _has_pool(algorithm):
            doc[algorithm] = {**doc.get(algorithm, {}), "pool": pool}
    else:
        first = method_document(next(iter(cfg.methods.values())))  # the shared settings of the first method
        doc = {k: v for k, v in first.items() if k in ("ppo", "preset", "num_workers", "eval_episodes")}
        doc.update(algorithm="br", br={"zoo": cell.zoo})
    doc.update(cfg.experiment)
    doc.update(
        name=run_name(cfg, cell),
        experiment=cfg.name,  # the benchmark's experiment: the cell's run nests under the benchmark's run
        register=False,  # the benchmark registers only the weights it publishes
        task=cell.task,
        seed=cell.seed,
        out_dir=str(cfg.folder / "runs"),
        updates_per_generation=cfg.updates_per_generation,
        final_zoo="",
        select_zoo="",
        gif=False,
    )
    algorithm = str(doc["algorithm"])
    ppo = ppo_config(doc.get("ppo", {}), doc.get("preset", "default"))
    doc.update(
        plan(
            algorithm,
            doc.get(algorithm, {}),
            cfg.env_steps,
            cfg.updates_per_generation,
            ppo.num_envs * ppo.rollout_steps,
        )
    )
    return doc


def _has_pool(algorithm: str) -> bool:
    import dataclasses

    from atdrone.population import ALGORITHMS

    config = ALGORITHMS[algorithm].Config
    return dataclasses.is_dataclass(config) and any(f.name == "pool" for f in dataclasses.fields(config))


def experiment(cfg: BenchmarkConfig, cell: Cell) -> ExperimentConfig:
    """The cell's validated experiment; a ConfigError names the method (``methods.<label>...``)."""
    where = f"methods.{cell.method}" if cell.kind == "method" else "best_response"
    try:
        return load_experiment(experiment_document(cfg, cell))
    except ConfigError as exc:
        raise ConfigError(where, str(exc)) from None


def load_benchmark(path_or_doc: str | Path | Mapping[str, Any], **overrides: Any) -> BenchmarkConfig:
    """A validated BenchmarkConfig (:func:`atdrone.benchmark.config.parse_benchmark`) whose every cell's
    experiment is built and validated too, so a bad method, task or zoo is refused before anything trains."""
    cfg = parse_benchmark(path_or_doc, **overrides)
    grid = cells(cfg)
    if len(grid) > MAX_CELLS:
        raise ConfigError("methods", f"{len(grid):,} cells: at most {MAX_CELLS:,}")
    seen: set[str] = set()
    for cell in grid:  # one per method (and one best response): the rest differ only in task, seed and zoo
        if cell.kind != "floor" and cell.method not in seen:
            seen.add(cell.method)
            exp = experiment(cfg, cell)
            if cell.kind == "method":  # a HOLA run too short to play its hypergraph: refused (smoke test: marked)
                check_hola_generations(cfg, cell.method, exp.algorithm, exp.generations)
    return cfg


def final_member(run_dir: Path, algorithm: str) -> str:
    """The run's final learner: HOLA's last learner, PBT's fittest final member, else the last member."""
    state = json.loads((run_dir / "service_state.json").read_text())["coordinator"]["algorithm"]
    if algorithm == "pbt":
        last = sorted((run_dir / "generations").iterdir())[-1] / "pbt.json"
        fitness = json.loads(last.read_text())["fitness"]
        return str(max(state["population"], key=lambda m: (fitness.get(m, -1.0), m)))
    if algorithm in ("hola", "hola_no_g"):
        return str(state["learners"][-1])
    return str(state["population"][-1])


RANDOM_DRAW = 5  # the counter a random drone folds into its key (a neural drone's draws use 0 and 1, VICSEK's 7)


class RandomPolicy(StatelessPolicy):
    """Uniform turns in [-1, 1]: the floor of the normalised scores. Each turn is drawn from the drone's key for
    its episode, step and slot, so an episode plays the same however the evaluation batches it (its own seeded
    generator only where a batch carries no keys)."""

    def __init__(self, seed: int) -> None:
        self.name = "random"
        self.rng = np.random.default_rng(seed)

    def act(self, batch: DroneBatch) -> np.ndarray:
        u = self.rng.random(len(batch)) if batch.keys is None else unit(fold(batch.keys, RANDOM_DRAW))
        return (2.0 * u - 1.0).astype(np.float32)


def cell_zoos(cfg: BenchmarkConfig, kind: str, zoo: str | None) -> list[str]:
    """The zoos a cell's learner is evaluated with: a bound's own zoo; a method's test zoos, then the selection zoo."""
    if kind != "method":
        return [str(zoo)]
    return cfg.played_zoos


def sha256_file(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def run_cell(
    cfg: BenchmarkConfig, cell: Cell, tracking_uri: str | None, parent_run: str | None = None
) -> dict[str, Any]:
    """Train (or resume) and evaluate one cell here; its record (JSON-ready)."""
    import torch

    from atdrone.benchmark.episodes import episode_summary
    from atdrone.hostinfo import float_kernels
    from atdrone.teams.evaluation import evaluate

    torch.set_num_threads(1)
    t0, cpu0 = time.perf_counter(), time.process_time()
    record: dict[str, Any] = {"cell": cell.to_dict(), "name": cell.name, "benchmark": cfg.digest()}
    record["zoo_version"] = cfg.zoo_versions()[cell.task]
    budget = {"env_steps": 0, "learner_samples": 0, "eval_env_steps": 0}
    workers = 0
    if cell.kind == "floor":
        policy: Any = RandomPolicy(EVAL_SEED + cell.seed)
    else:
        from atdrone.policies.neural import load_policy
        from atdrone.service.driver import run_experiment

        exp = experiment(cfg, cell)
        run_experiment(exp, resume=True, tracking_uri=tracking_uri, progress=False, parent_run=parent_run)
        run_dir = Path(exp.out_dir) / exp.name
        saved = json.loads((run_dir / "service_state.json").read_text())
        state = saved["coordinator"]
        budget.update({k: int(v) for k, v in state.get("budget", {}).items()})
        train_wall = training_wall(run_dir, str(saved.get("registry", "./registry.db")))
        member = final_member(run_dir, exp.algorithm)
        checkpoint = run_dir / "members" / f"{member}.pt"
        record.update(
            algorithm=exp.algorithm,
            member=member,
            checkpoint=str(checkpoint.relative_to(cfg.folder)),
            sha256=sha256_file(checkpoint),
            generations=exp.generations,
        )
        policy = load_policy(checkpoint)
        workers = exp.num_workers
    zoos = cell_zoos(cfg, cell.kind, cell.zoo)
    metrics: dict[str, dict[str, float]] = {}
    episodes: dict[str, dict[str, float]] = {}
    bench_eval = 0
    t_eval = time.perf_counter()
    task = load_task(cell.task)
    for zoo in zoos:
        result = evaluate(policy, task, zoo, episodes=cfg.eval_episodes, seeds=[EVAL_SEED + cell.seed])
        metrics[zoo] = result.mean
        episodes[zoo] = episode_summary(result.records, task)
        bench_eval += int(result.records["length"].sum())
    if cell.kind == "method" and cfg.protocols:  # the team-change protocols: reported apart, no bounds
        from atdrone.teams.protocols import load_protocol

        record["protocols"] = {}
        for name in cfg.protocols:
            protocol = load_protocol(name)
            result = evaluate(
                policy,
                cell.task,
                protocol.zoo,
                episodes=cfg.eval_episodes,
                seeds=[EVAL_SEED + cell.seed],
                protocol=protocol,
            )
            record["protocols"][name] = result.mean
            bench_eval += int(result.records["length"].sum())
    wall = time.perf_counter() - t0
    budget["benchmark_eval_env_steps"] = bench_eval
    timing: dict[str, Any] = {
        # wall_s, cpu_s: this attempt's (a resumed cell: its last attempt only); never compared across runs
        "wall_s": round(wall, 1),
        "cpu_s": round(wall * workers + time.process_time() - cpu0, 1),
        # the training's generations over every attempt (from the registry), and this evaluation
        "eval_wall_s": round(time.perf_counter() - t_eval, 1),
        "workers": workers,
        "node": _node_id(),
        "pid": os.getpid(),
        "machine": float_kernels(),  # where the metrics replay bit for bit (atdrone.hostinfo)
    }
    if cell.kind != "floor":
        timing["train_wall_s"] = round(train_wall, 1)
    record.update(metrics=metrics, episodes=episodes, budget=budget, timing=timing)
    return record


def training_wall(run_dir: Path, registry: str) -> float:
    """Seconds from the start to the end of every finished generation of a service run, summed over all its
    attempts (the registry keeps each generation's times; the gaps between attempts are not counted)."""
    import pandas as pd

    from atdrone.registry import Registry

    path = Path(registry)
    with Registry(path if path.is_absolute() else run_dir / path, create=False) as reg:
        done = reg.generations().dropna(subset=["finished"])
    spans = pd.to_datetime(done["finished"]) - pd.to_datetime(done["started"])
    return float(spans.dt.total_seconds().sum())


def _node_id() -> str:
    try:
        import ray

        return str(ray.get_runtime_context().get_node_id()) if ray.is_initialized() else ""
    except Exception:  # pragma: no cover - outside Ray
        return ""


STALL_FACTOR = 2.0
"""A cell whose wall time is over this many times its method's median cell wall time counts as stalled."""


def cell_wall(timing: dict[str, Any]) -> float:
    """A cell's wall seconds: its training's generations over every attempt plus its evaluation where the record
    has them, else the last attempt's wall time (a record made before they were kept)."""
    if "eval_wall_s" in timing:
        return float(timing.get("train_wall_s", 0.0)) + float(timing["eval_wall_s"])
    return float(timing.get("wall_s", float("nan")))


def cell_cpu(cfg: BenchmarkConfig, record: Mapping[str, Any]) -> float:
    """A cell's CPU-seconds: its last attempt's (the rollout workers' reserved CPU-seconds plus the driver's and
    evaluation's CPU time) and, for a resumed cell, its earlier attempts' generations at one reserved CPU per rollout
    worker (their drivers' CPU time is not kept). The workers come from the record, else from the cell's experiment."""
    timing = record.get("timing", {})
    cpu = float(timing.get("cpu_s", float("nan")))
    earlier = cell_wall(timing) - float(timing.get("wall_s", float("nan")))
    if not earlier > 0:  # one attempt: its generations and evaluation lie within its wall time
        return cpu
    workers = timing.get("workers")
    if workers is None:  # a record made before the workers were kept
        workers = experiment(cfg, Cell(**record["cell"])).num_workers
    return cpu + int(workers) * earlier
