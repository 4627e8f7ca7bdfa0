"""The driver of a population training run: Ray, the registry actor, the coordinator, MLflow.

``run_experiment`` starts (or joins, with ``address``) a Ray cluster, serves the run's
registry (``<out_dir>/<name>/registry.db``, or under ``$ATDRONE_REGISTRY_DIR``) from a
named actor in namespace ``atdrone`` on the driver's node, creates the coordinator and
asks it for one generation after another. After each generation it logs the generation
to MLflow as a nested run under the job's parent run, with a nested run per learner,
then writes ``service_state.json`` (atomically). ``resume=True`` continues from the
last completed generation.

Faults. A kill at any point (SIGKILL of the driver, a node lost) is resumed exactly:
the registry's writes are idempotent and a resume discards the rows of the generation
it repeats; checkpoints are renamed into place; what a dead attempt logged to MLflow
of a generation it never saved is deleted (its nested runs carry the attempt's id and
the generation; ``"logged"`` in the state says how far MLflow is complete) and the
parent's curves get one point per step; the best member's model version is found
before one is made; a finished run's parent left RUNNING is ended. SIGTERM is handled
as Ctrl-C: the MLflow runs end KILLED.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import signal
import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from atdrone.fileio import atomic_write_bytes
from atdrone.learn.ppo import saved_ppo_document
from atdrone.population.base import GenerationReport
from atdrone.rundir import RunError, check_resume, read_json, refuse_existing
from atdrone.service.experiment import ExperimentConfig, registry_name
from atdrone.teams.partners import slot_counts

log = logging.getLogger(__name__)
STATE_FILE = "service_state.json"


def _write_json(path: Path, data: Any) -> None:
    atomic_write_bytes(path, json.dumps(data, indent=2, default=_jsonable).encode())


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"  # "0": Ray's node address is 127.0.0.1 (Ray reads it at import)
# what a resume may change; anything else in config.json must match (atdrone.rundir.check_resume)
RESUME_MAY_CHANGE = (
    "generations",
    "final_zoo",
    "final_episodes",
    "select_zoo",
    "gif",
    "learner_gpus",
    "learner_threads",
    "out_dir",
)


def init_ray(address: str | None, num_cpus: int | None = None) -> None:
    """Join the cluster at ``address`` (or RAY_ADDRESS), else start a local one listening on loopback only.

    A local Ray binds its servers (GCS, raylet, workers, agents) to the node address,
    which Ray takes from the route to the internet unless told that the node is a
    single machine; :data:`LOOPBACK_ENV` says so, for this process and every Ray
    process it starts, so nothing of a local run listens beyond 127.0.0.1.
    """
    import ray

    if ray.is_initialized():
        return
    address = address or os.environ.get("RAY_ADDRESS")
    kwargs: dict[str, Any] = {"namespace": "atdrone", "log_to_driver": False}
    if address:
        ray.init(address=address, **kwargs)
        return
    os.environ[LOOPBACK_ENV] = "0"
    from ray._private import ray_constants

    ray_constants.ENABLE_RAY_CLUSTER = False  # read at import: ray may have been imported before this call
    # address "local": a new Ray of this process's own, never one a `ray start` left on this machine
    ray.init(address="local", num_cpus=num_cpus or min(os.cpu_count() or 2, 8), include_dashboard=False, **kwargs)


def check_schedulable(cfg: ExperimentConfig, wait_s: float = 0.0) -> None:
    """Refuse a run whose actors the cluster cannot place (it would wait forever in Ray's queue).

    The rollout workers take one CPU each; a learner ``learner_gpus`` GPUs. ``wait_s``:
    how long to wait for an autoscaling cluster to grow before refusing.
    """
    import ray

    deadline = time.monotonic() + wait_s
    while True:
        total = ray.cluster_resources()
        cpus, gpus = float(total.get("CPU", 0.0)), float(total.get("GPU", 0.0))
        problems = []
        if cfg.num_workers > cpus:
            problems.append(f"num_workers {cfg.num_workers}: one CPU per rollout worker, the cluster has {cpus:g}")
        if cfg.learner_gpus > gpus:
            problems.append(f"learner_gpus {cfg.learner_gpus:g} per learner, the cluster has {gpus:g} GPUs")
        if not problems or time.monotonic() >= deadline:
            break
        time.sleep(2.0)
    if problems:
        raise RunError("cannot schedule the run: " + "; ".join(problems))


def run_experiment(
    cfg: ExperimentConfig,
    address: str | None = None,
    resume: bool = False,
    tracking_uri: str | None = None,
    progress: bool = True,
    num_cpus: int | None = None,
    stop_after: int | None = None,
) -> dict[str, Any]:
    """Run (or resume) an experiment to ``cfg.generations``; returns the final summary.

    A generation is all or nothing: ``service_state.json`` is written before the first
    generation and after each completed one, and a resume discards the registry rows of
    the generation it repeats (checkpoints are rewritten under the same ids) and ends the
    MLflow runs the dead attempt left RUNNING as KILLED. A run directory already holding
    a run is refused without ``resume``, and a resume with a different experiment
    (:data:`RESUME_MAY_CHANGE` aside) is refused. ``stop_after``: stop once this many
    generations are complete (for tests of resume).
    """
    with _sigterm_as_interrupt():
        return _run(cfg, address, resume, tracking_uri, progress, num_cpus, stop_after)


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM (``ray job stop``, a scheduler's stop) raises KeyboardInterrupt, as Ctrl-C does, so the run's
    MLflow records end KILLED and its actors are released; the previous handler comes back afterwards."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt(f"signal {signal.Signals(signum).name}")

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run(
    cfg: ExperimentConfig,
    address: str | None,
    resume: bool,
    tracking_uri: str | None,
    progress: bool,
    num_cpus: int | None,
    stop_after: int | None,
) -> dict[str, Any]:
    import ray

    from atdrone.population import ALGORITHMS
    from atdrone.registry import registry_actor
    from atdrone.service.coordinator import reserve_cpus
    from atdrone.service.pool import COORDINATORS

    run_dir = Path(cfg.out_dir).resolve() / cfg.name
    state_path = run_dir / STATE_FILE
    saved: dict[str, Any] = {}
    if state_path.exists():
        if not resume:
            refuse_existing(run_dir)
        saved = read_json(state_path, "service state")
        check_resume(run_dir, cfg.to_dict(), RESUME_MAY_CHANGE, saved_ppo_document)
        done = _completed(run_dir, saved, cfg, tracking_uri)
        if done is not None:
            return done
    elif resume and (run_dir / "config.json").exists():
        check_resume(run_dir, cfg.to_dict(), RESUME_MAY_CHANGE, saved_ppo_document)
    db = registry_path(cfg, run_dir)
    if saved.get("registry", registry_record(cfg, run_dir)) != registry_record(cfg, run_dir):
        raise RunError(
            f"{run_dir} keeps its registry at {saved['registry']}, not {db}: resume with the same "
            f"{REGISTRY_DIR_ENV} (or --registry-dir)"
        )
    run_dir.mkdir(parents=True, exist_ok=True)
    _write_json(run_dir / "config.json", cfg.to_dict())
    init_ray(address, num_cpus)
    check_schedulable(cfg, wait_s=60.0 if (address or os.environ.get("RAY_ADDRESS")) else 0.0)
    # on the driver's node: the sqlite file (WAL) needs a local disk, which network file systems are not
    registry = registry_actor(db, name=registry_name(cfg.name), node=ray.get_runtime_context().get_node_id())
    start = saved.get("coordinator", {}).get("generation", 0)
    ray.get(registry.discard_generations.remote(cfg.name, start))  # what an interrupted generation left
    # the run's coordinator (with the learners and rollout workers it made) comes from this process's pool and
    # goes back to it: the next run starts none of those processes again. The run's CPUs are reserved here, so
    # they are freed whatever becomes of the coordinator.
    coordinator = COORDINATORS.take()
    cpus = reserve_cpus(cfg.num_workers)
    ended = False
    try:
        run = (cfg, ALGORITHMS[cfg.algorithm], str(run_dir), saved.get("coordinator"), registry, cpus)
        ray.get(coordinator.start.remote(*run))
        summary = _generations(cfg, coordinator, registry, run_dir, saved, tracking_uri, progress, stop_after)
        ended = True
    finally:  # a run that failed ends its coordinator (and its workers); the registry's name is free for the next run
        _release(coordinator, registry, registry_name(cfg.name), ended, cpus)
    COORDINATORS.give_back([coordinator])  # its rollout workers emptied, kept (they hold no CPU)
    return summary


SUMMARY_FILE = "summary.json"
REGISTRY_DIR_ENV = "ATDRONE_REGISTRY_DIR"


def registry_record(cfg: ExperimentConfig, run_dir: Path) -> str:
    """The registry's place as the state file keeps it: relative to the run directory when inside it
    (``./registry.db``: a moved or copied run directory resumes with its own), else the absolute path."""
    db = registry_path(cfg, run_dir)
    try:
        return "./" + db.relative_to(run_dir).as_posix()
    except ValueError:
        return str(db)


def registry_path(cfg: ExperimentConfig, run_dir: Path) -> Path:
    """The run's registry file: ``$ATDRONE_REGISTRY_DIR/<name>/registry.db`` when set (a cluster: a local disk
    of the driver's node, as sqlite's WAL needs), else ``<run_dir>/registry.db``."""
    folder = os.environ.get(REGISTRY_DIR_ENV)
    return (Path(folder).resolve() / cfg.name if folder else run_dir) / "registry.db"


def _completed(
    run_dir: Path, saved: dict[str, Any], cfg: ExperimentConfig, tracking_uri: str | None
) -> dict[str, Any] | None:
    """The summary of a run that already finished all ``cfg.generations`` (resumed again: nothing to do but
    end its MLflow parent run, when a kill came after the summary and before the run's end)."""
    if saved.get("coordinator", {}).get("generation", 0) < cfg.generations or not (run_dir / SUMMARY_FILE).exists():
        return None
    if saved.get("mlflow_run_id"):
        from atdrone.tracking import Tracker

        if Tracker(tracking_uri).end_run_if_running(saved["mlflow_run_id"]):
            log.info("ended the finished run's MLflow run %s, left RUNNING by a kill", saved["mlflow_run_id"])
    summary = read_json(run_dir / SUMMARY_FILE, "run summary")
    summary["population"] = pd.read_csv(run_dir / "population.csv")
    summary.update({"run_dir": str(run_dir), "mlflow_run_id": saved.get("mlflow_run_id"), "reports": []})
    summary["complete"] = True
    return summary


def _generations(
    cfg: ExperimentConfig,
    coordinator: Any,
    registry: Any,
    run_dir: Path,
    saved: dict[str, Any],
    tracking_uri: str | None,
    progress: bool,
    stop_after: int | None,
) -> dict[str, Any]:
    """Ask the coordinator for the remaining generations, logging each; then the final evaluation."""
    import ray

    from atdrone.policies.manifest import task_version
    from atdrone.population import ALGORITHMS
    from atdrone.tracking import Tracker

    state_path = run_dir / STATE_FILE
    tracker = Tracker(tracking_uri)
    reports: list[GenerationReport] = []
    experiment = cfg.experiment or cfg.name
    start = saved.get("coordinator", {}).get("generation", 0)
    tags = run_tags(cfg, run_dir)
    attempt = {**tags, "atdrone.attempt": uuid.uuid4().hex}  # this driver's nested runs
    name = f"{cfg.name}-{cfg.algorithm}"
    with tracker.run(experiment, name, run_id=saved.get("mlflow_run_id"), tags=tags) as run_id:
        # what a dead attempt logged of generations it never saved: they are trained and logged again
        forgotten = tracker.forget_runs(experiment, tags, "atdrone.generation", saved.get("logged", start), run_id)
        killed = tracker.end_stale_runs(experiment, tags, keep=run_id)  # nested runs of an older layout
        if forgotten or killed:
            log.info("removed %d, ended %d MLflow runs of an interrupted attempt", len(forgotten), len(killed))
        if "mlflow_run_id" not in saved:  # from now on a rerun without --resume is refused
            state = {"coordinator": ray.get(coordinator.state.remote()), "mlflow_run_id": run_id, "logged": start}
            _write_json(state_path, {**state, "registry": registry_record(cfg, run_dir)})
        tracker.log_params({"experiment": cfg.to_dict()})
        labels = ALGORITHMS[cfg.algorithm].result_tags(cfg.algorithm_config())  # e.g. a best response
        tracker.set_tags(
            {
                "atdrone.algorithm": cfg.algorithm,
                "atdrone.task": cfg.task,
                "atdrone.zoo_version": task_version(cfg.task),  # the partners every score of the run was measured with
                **{f"atdrone.{k}": v for k, v in labels.items()},
            }
        )
        tracker.log_artifact(run_dir / "config.json")
        for g in range(start, cfg.generations):
            t0 = time.perf_counter()
            report = _await_generation(coordinator, cfg.name, g, progress)
            reports.append(report)
            _log_generation(tracker, report, run_dir, registry, cfg, run_id, attempt)
            # the generation is saved and logged ("logged": MLflow holds generations 0 .. logged - 1)
            state = {"coordinator": ray.get(coordinator.state.remote()), "mlflow_run_id": run_id, "logged": g + 1}
            _write_json(state_path, {**state, "registry": registry_record(cfg, run_dir)})
            if progress:
                learners = ", ".join(report.learners)
                print(
                    f"[{cfg.name}] generation {g} done in {time.perf_counter() - t0:.0f}s: learners {learners}; "
                    f"population {len(report.population)}; env steps {report.budget.get('env_steps', 0):,}, "
                    f"learner samples {report.budget.get('learner_samples', 0):,}",
                    flush=True,
                )
            if stop_after is not None and g + 1 >= stop_after:
                return {"run_dir": str(run_dir), "mlflow_run_id": run_id, "reports": reports, "stopped": True}
        zoos = " and ".join(
            f"{z} ({role})" for z, role in ((cfg.select_zoo, "selects the best"), (cfg.final_zoo, "test")) if z
        )
        if progress and zoos:
            print(f"[{cfg.name}] final evaluation on {zoos}, {cfg.final_episodes} episodes per member", flush=True)
        summary = _finish(tracker, coordinator, registry, cfg, run_dir)
        summary.update({"run_dir": str(run_dir), "mlflow_run_id": run_id, "reports": reports})
    return summary


def _await_generation(coordinator: Any, name: str, g: int, progress: bool, every_s: float = 10.0) -> GenerationReport:
    """Wait for the coordinator's generation ``g``, printing what it is doing (updates, matches) as it goes."""
    import ray

    ref = coordinator.run_generation.remote()
    last, shown = "", time.monotonic()
    while True:
        done, _ = ray.wait([ref], timeout=1.0)
        if done:
            report: GenerationReport = ray.get(ref)
            return report
        if not progress:
            continue
        line = ray.get(coordinator.progress.remote())
        new_kind = line.split(":")[0] != last.split(":")[0]  # training, evaluating, the zoo: said at once
        if line and line != last and (new_kind or time.monotonic() - shown >= every_s):  # never a line twice
            print(f"[{name}] generation {g}: {line}", flush=True)
            last, shown = line, time.monotonic()


def _release(coordinator: Any, registry: Any, name: str, keep: bool, cpus: Any, timeout_s: float = 30.0) -> None:
    """Free the run's CPUs (``cpus``, a placement group); kill the run's registry actor, and its coordinator (with
    it its workers) unless ``keep`` (a run that ended well: the pool takes it back); wait for the registry's name
    to be free."""
    import ray
    from ray.util.placement_group import remove_placement_group

    from atdrone.registry import REGISTRY_NAMESPACE

    if not keep:
        ray.kill(coordinator)
    remove_placement_group(cpus)
    ray.kill(registry, no_restart=True)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            ray.get_actor(name, namespace=REGISTRY_NAMESPACE)
        except ValueError:
            return
        time.sleep(0.1)


def run_tags(cfg: ExperimentConfig, run_dir: Path) -> dict[str, str]:
    """The MLflow tags of a run's records: its name, and a key of its run directory (two runs of one name in two
    out dirs are two runs)."""
    key = hashlib.sha256(str(run_dir.resolve()).encode()).hexdigest()[:16]
    return {"atdrone.run": cfg.name, "atdrone.run_dir": key}


def _log_generation(
    tracker: Any,
    report: GenerationReport,
    run_dir: Path,
    registry: Any,
    cfg: ExperimentConfig,
    parent: str,
    tags: dict[str, str],
) -> None:
    """A generation as a nested MLflow run (metrics, documents, figures, a nested run per learner) and a
    point on the parent run's curves (:func:`_generation_curves`; once: a resumed generation does not add a
    second point). The nested runs carry ``tags`` (the attempt's) and the generation index."""
    import ray

    from atdrone.population import ALGORITHMS

    g = report.generation
    gen_dir = run_dir / "generations" / f"{g:03d}"
    tags = {**tags, "atdrone.generation": str(g)}
    tracker.log_metrics(_generation_curves(report, registry, cfg), step=g, run_id=parent, once=True)
    with tracker.run(cfg.name, f"generation-{g}", nested=True, tags=tags):
        metrics = {"pop/size": len(report.population), "perf/generation_s": report.wall_s, **report.metrics}
        metrics.update({f"budget/{k}": float(v) for k, v in report.budget.items()})
        if report.matches:
            metrics["eval/matches"] = len(report.matches)
            metrics["eval/SUC"] = float(np.mean([m.metrics["SUC"] for m in report.matches]))
            metrics["eval/COL"] = float(np.mean([m.metrics["COL"] for m in report.matches]))
        for t in report.training:  # partner slots each member filled in the learner's training episodes
            metrics.update({f"pop/drawn/{t.member}/{m}": n for m, n in slot_counts(t.drawn).items()})
        from atdrone.tracking import member_series

        scalars, series = member_series(metrics, report.population)  # per-member values: one chart per name
        tracker.log_metrics(scalars, step=g)
        tracker.log_series(series)
        tracker.describe(
            "Members, in the order of the `pop/...` series' steps: "
            + ", ".join(f"{i} {m}" for i, m in enumerate(report.population))
        )
        for name, document in report.documents.items():
            _write_json(gen_dir / name, document)
            tracker.log_artifact(gen_dir / name)
        for figure in ALGORITHMS[cfg.algorithm].figures(report, gen_dir):
            tracker.log_artifact(figure)
        table = ray.get(registry.crossplay.remote(task=None))
        if len(table) > 1:
            from atdrone.population.plots import crossplay_heatmap

            crossplay_heatmap(table, gen_dir / "crossplay.png", title=f"{cfg.name} cross-play SUC, generation {g}")
            tracker.log_artifact(gen_dir / "crossplay.png")
        for t in report.training:
            with tracker.run(cfg.name, f"learner-{t.member}", nested=True, tags={**tags, "atdrone.member": t.member}):
                tracker.log_dict(
                    {"parent": t.parent, "seed": t.seed, "partners": t.partners, "drawn": t.drawn}, "training.json"
                )
                for i, row in enumerate(t.history):
                    tracker.log_metrics(row, step=i)
                tracker.log_artifact(run_dir / "members" / f"{t.member}.pt", "checkpoints")
                ray.get(registry.update_member.remote(t.member, mlflow_run_id=tracker.mlflow.active_run().info.run_id))


def _generation_curves(report: GenerationReport, registry: Any, cfg: ExperimentConfig) -> dict[str, float]:
    """The parent run's per-generation curves: population size, rho entropy, best and mean zoo SUC.

    The coordinator evaluates each generation's new members on the final zoo
    (``eval_episodes`` episodes each, registry metrics ``<zoo>/SUC``); best and mean are
    over the members of the population now.
    """
    import ray

    curves = {"gen/population_size": float(len(report.population))}
    if "pop/rho_entropy" in report.metrics:
        curves["gen/rho_entropy"] = float(report.metrics["pop/rho_entropy"])
    if not cfg.final_zoo:
        return curves
    members = ray.get(registry.members.remote(run=cfg.name))
    suc = {
        row["id"]: row["metrics"].get(f"{cfg.final_zoo}/SUC")
        for _, row in members.iterrows()
        if row["id"] in report.population
    }
    known = [v for v in suc.values() if v is not None]
    if known:
        noisy = f"{cfg.eval_episodes}ep"  # named for their episode count: the final table's are final_episodes
        curves[f"gen/{cfg.final_zoo}_SUC_best_{noisy}"] = float(max(known))
        curves[f"gen/{cfg.final_zoo}_SUC_mean_{noisy}"] = float(np.mean(known))
    return curves


def select_best(table: pd.DataFrame, select_zoo: str, population: list[str]) -> tuple[str, float | None]:
    """The run's best member and its score on the selection zoo: the highest ``<select_zoo>_SUC``, ties
    broken by the higher ``<select_zoo>_REW`` and then by the later (longer trained) member; the last member
    (no score) without a selection zoo. Only the selection zoo's columns are read, so no test-zoo result can
    change the choice."""
    suc, rew = f"{select_zoo}_SUC", f"{select_zoo}_REW"
    if not select_zoo or suc not in table or not np.isfinite(table[suc].to_numpy(np.float64)).any():
        return population[-1], None
    ranked = table.assign(
        _suc=table[suc].astype(np.float64).fillna(-np.inf),
        _rew=table[rew].astype(np.float64).fillna(-np.inf) if rew in table else 0.0,
        _order=np.arange(len(table)),
    ).sort_values(["_suc", "_rew", "_order"])
    best = ranked.iloc[-1]
    return str(best["member"]), float(best["_suc"])


def _evaluate_population(coordinator: Any, zoo: str, episodes: int) -> dict[str, dict[str, float]]:
    """Every member's metrics with partners from ``zoo`` (the coordinator's evaluation)."""
    import ray

    return ray.get(coordinator.evaluate_population.remote(zoo, episodes))


def _finish(tracker: Any, coordinator: Any, registry: Any, cfg: ExperimentConfig, run_dir: Path) -> dict[str, Any]:
    """Evaluate the population on the selection zoo and the final (test) zoo, choose the best member on the
    selection zoo alone, print and log the population table."""
    import ray

    zoos = [z for z in dict.fromkeys((cfg.select_zoo, cfg.final_zoo)) if z]
    results = {z: _evaluate_population(coordinator, z, cfg.final_episodes) for z in zoos}
    state = ray.get(coordinator.state.remote())["algorithm"]
    eta, rho, drawn = state.get("eta", {}), state.get("rho", {}), state.get("drawn", {})
    rows = []
    for m in state["population"]:
        row: dict[str, Any] = {"member": m, "eta": eta.get(m, float("nan"))}
        if rho:  # the last generation's partner distribution and the partner slots drawn from it
            row.update({"rho": rho.get(m, float("nan")), "drawn": int(drawn.get(m, 0))})
        for zoo in zoos:
            for k, v in results[zoo].get(m, {}).items():
                row[f"{zoo}_{k}"] = v
        rows.append(row)
    table = pd.DataFrame(rows)
    graph = {m: {k: float(v[m]) for k, v in (("eta", eta), ("rho", rho)) if m in v} for m in state["population"]}
    ray.get([registry.update_member.remote(m, metrics=g) for m, g in graph.items() if g])  # for registry list
    atomic_write_bytes(run_dir / "population.csv", table.to_csv(index=False).encode())
    tracker.log_artifact(run_dir / "population.csv")
    best, score = select_best(table, cfg.select_zoo, state["population"])
    selected = {}
    if score is not None:
        selected[f"eval/{cfg.select_zoo}/best_SUC"] = score
    if cfg.final_zoo and f"{cfg.final_zoo}_SUC" in table:  # the chosen member on the test zoo: reported only
        selected[f"eval/{cfg.final_zoo}/selected_SUC"] = float(
            table.loc[table["member"] == best, f"{cfg.final_zoo}_SUC"].iloc[0]
        )
    from atdrone.tracking import population_columns, population_markdown

    rows = table.to_dict("records")
    selected.update(population_columns(rows, cfg.select_zoo, cfg.final_zoo, best))  # the runs table's columns
    if selected:
        tracker.log_metrics(selected, step=cfg.generations, once=True)
    title = (
        f"{cfg.algorithm} on {cfg.task}, {cfg.generations} generations: best member **{best}** (chosen on "
        f"{cfg.select_zoo or 'the last generation'}; {cfg.final_zoo or 'no'} test zoo), {cfg.final_episodes} "
        "episodes per member and zoo"
    )
    tracker.describe(population_markdown(rows, title))
    model = _log_best(tracker, best, score, run_dir, cfg)
    budget = ray.get(coordinator.state.remote())["budget"]
    _write_json(run_dir / SUMMARY_FILE, {"best": best, "selected_on": cfg.select_zoo, "budget": budget, "model": model})
    return {"population": table, "best": best, "budget": budget, "model": model}


def model_name(cfg: ExperimentConfig) -> str:
    """The registered model of an experiment config: one per config, a version per run."""
    return f"atdrone-{cfg.experiment or cfg.name}"


def _log_best(tracker: Any, best: str, score: float | None, run_dir: Path, cfg: ExperimentConfig) -> str:
    """Register the best member's checkpoint as a version of the config's model (the alias "champion" goes to
    the best-scoring version of all its runs) and a GIF of it playing; returns ``models:/NAME/VERSION``."""
    from atdrone.models.checkpoint import load_checkpoint

    path = run_dir / "members" / f"{best}.pt"
    model, header = load_checkpoint(path)
    tags = {"member": best, "run": cfg.name, "score_metric": f"{cfg.select_zoo}_SUC" if score is not None else ""}
    version = tracker.register_checkpoint(path, model_name(cfg), score, tags)
    if cfg.gif:
        from atdrone.envs.render import save_gif
        from atdrone.policies.neural import NeuralPolicy
        from atdrone.policies.zoo import load_zoo
        from atdrone.teams.replay import showcase

        policy = NeuralPolicy(model, name=best, num_p=header["num_p"], num_e=header["num_e"], task=cfg.task)
        zoo = load_zoo(cfg.final_zoo) if cfg.final_zoo else None
        frames, episode = showcase(cfg.task, policy, zoo, seed=cfg.seed)
        gif = save_gif(frames, run_dir / "best.gif", fps=10)
        tracker.log_artifact(gif)
        tracker.set_tags({"atdrone.best_gif": episode["caption"]})
    tracker.log_dict(header, "best_member_header.json")
    return f"models:/{model_name(cfg)}/{version}"


def format_summary(cfg: ExperimentConfig, summary: dict[str, Any], tracking_uri: str) -> str:
    """The end-of-run text: the population table and where to look (run dir, registry, MLflow)."""
    from atdrone.tracking import champion_version, ui_model_link

    with pd.option_context("display.float_format", "{:.2f}".format, "display.width", 120):
        table = summary["population"].to_string(index=False)
    done = (
        f"\n{cfg.name} had already finished its {cfg.generations} generations (nothing to resume)"
        if summary.get("complete")
        else ""
    )
    return "\n".join(
        [
            f"{done}\npopulation of {cfg.name} ({cfg.algorithm}, {cfg.task}):",
            table,
            f"best member: {summary['best']}"
            + (f" (chosen on the {cfg.select_zoo} zoo; {cfg.final_zoo} is a test zoo)" if cfg.select_zoo else "")
            + f"; run directory: {summary['run_dir']}",
            "budget: " + ", ".join(f"{k.replace('_', ' ')} {v:,}" for k, v in summary.get("budget", {}).items()),
            f"registry: atdrone registry --db {registry_path(cfg, Path(summary['run_dir']))} list",
            f"model: {summary.get('model', '')} (champion: models:/{model_name(cfg)}@champion = version "
            f"{champion_version(model_name(cfg), tracking_uri) or 'none'}; {ui_model_link(model_name(cfg))})",
            f"MLflow: experiment {cfg.experiment or cfg.name!r}, run {summary['mlflow_run_id']} at {tracking_uri}; "
            f"browse with: mlflow ui --backend-store-uri {tracking_uri}",
        ]
    )
