"""The driver of a population training run: Ray, the registry actor, the coordinator, MLflow.

``run_experiment`` starts (or joins, with ``address``) a Ray cluster, serves the run's
registry (``<out_dir>/<name>/registry.db``, or under ``$ATDRONE_REGISTRY_DIR``) from a
named actor in namespace ``atdrone`` on the driver's node, creates the coordinator and
asks it for one generation after another. After each generation it logs the generation
to MLflow as a nested run under the job's parent run, with a nested run per learner,
then writes ``service_state.json`` (atomically). ``resume=True`` continues from the
last completed generation. Before Ray starts, the run directory is locked and checked
(:mod:`atdrone.service.runstate`: one driver per run, a resume trusts only what agrees
with its state file); what the run records: :mod:`atdrone.service.results`.

Faults. A kill at any point (SIGKILL of the driver, a node lost) is resumed exactly:
the registry's writes are idempotent and a resume discards the rows of the generation
it repeats; checkpoints are renamed into place; what a dead attempt logged to MLflow
of a generation it never saved is deleted (its nested runs carry the run's identifier,
the attempt's and the generation; ``"logged"`` in the state says how far MLflow is
complete) and the parent's curves get one point per step; the best member's model
version is found before one is made; a finished run's parent left RUNNING is ended. A
learner or the coordinator that dies mid-generation is replaced and the generation
played again from the last saved one (:data:`GENERATION_RETRIES` times at most). The
registry's write-ahead log is folded back into its file after every generation and at
the end. SIGTERM and SIGINT raise :class:`~atdrone.errors.Interrupted` (installed after
``ray.init``, which replaces the handlers before it): the MLflow runs end KILLED.
"""

from __future__ import annotations

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

import pandas as pd

from atdrone.errors import Interrupted, interrupt_on_signals
from atdrone.population.base import GenerationReport
from atdrone.rundir import RunError, read_json
from atdrone.service.experiment import ExperimentConfig, registry_name
from atdrone.service.rayclean import clean_orphans
from atdrone.service.rayenv import STALL_TOLERANCE
from atdrone.service.results import finish, format_summary, log_generation, model_name, select_best
from atdrone.service.runstate import (
    REGISTRY_DIR_ENV,
    RESUME_MAY_CHANGE,
    STATE_FILE,
    SUMMARY_FILE,
    OpenRun,
    open_run,
    registry_path,
    run_tags,
)

__all__ = [
    "REGISTRY_DIR_ENV",
    "RESUME_MAY_CHANGE",
    "STATE_FILE",
    "SUMMARY_FILE",
    "check_schedulable",
    "format_summary",
    "init_ray",
    "model_name",
    "registry_path",
    "run_experiment",
    "run_tags",
    "select_best",
]
log = logging.getLogger(__name__)
GENERATION_RETRIES = 3  # a generation played again after a learner's or the coordinator's death, at most

LOOPBACK_ENV = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"  # "0": Ray's node address is 127.0.0.1 (Ray reads it at import)


def init_ray(address: str | None, num_cpus: int | None = None) -> None:
    """Join the cluster at ``address`` (or RAY_ADDRESS), else start a local one listening on loopback only.

    A local Ray binds its servers (GCS, raylet, workers, agents) to the node address,
    which Ray takes from the route to the internet unless told that the node is a
    single machine; :data:`LOOPBACK_ENV` says so, for this process and every Ray
    process it starts, so nothing of a local run listens beyond 127.0.0.1. A local Ray outlives a minute or
    more without CPU (:data:`STALL_TOLERANCE`). Before it starts, the
    processes a killed run's local Ray left behind are ended (:func:`~atdrone.service.rayclean.clean_orphans`).
    """
    import ray

    if ray.is_initialized():
        return
    address = address or os.environ.get("RAY_ADDRESS")
    kwargs: dict[str, Any] = {"namespace": "atdrone", "log_to_driver": False}
    if address:
        ray.init(address=address, **kwargs)
    else:
        os.environ[LOOPBACK_ENV] = "0"
        for name, value in STALL_TOLERANCE.items():  # read by the GCS and raylet this start spawns
            os.environ.setdefault(name, value)
        from ray._private import ray_constants

        ray_constants.ENABLE_RAY_CLUSTER = False  # read at import: ray may have been imported before this call
        _private_token()
        clean_orphans()  # what a killed run's local Ray left behind: ended before this one starts
        # address "local": a new Ray of this process's own, never one a `ray start` left on this machine
        ray.init(address="local", num_cpus=num_cpus or min(os.cpu_count() or 2, 8), include_dashboard=False, **kwargs)
        _private_token()
    interrupt_on_signals()  # ray.init replaced the handlers: a stop signal would abort the process


def _private_token() -> None:
    """Ray's authentication token file (``~/.ray/auth_token``) readable by its owner only (Ray writes it 0644);
    made here, 0600, when missing, so it is never readable by others even for a moment."""
    import secrets

    path = Path.home() / ".ray" / "auth_token"
    try:
        if not path.exists():
            path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
            fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
            with os.fdopen(fd, "w") as f:
                f.write(secrets.token_hex(32))  # 256 bits, as Ray's own
        elif path.stat().st_uid == os.getuid() and path.stat().st_mode & 0o077:
            path.chmod(0o600)
    except OSError as exc:  # another user's home, a read-only one: Ray reports what it cannot use
        log.debug("could not make %s private: %s", path, exc)


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
    parent_run: str | None = None,
) -> dict[str, Any]:
    """Run (or resume) an experiment to ``cfg.generations``; returns the final summary.

    A generation is all or nothing: ``service_state.json`` is written at the run's birth
    and after each completed generation, and a resume discards the registry rows of the
    generation it repeats (checkpoints are rewritten under the same ids) and ends the
    MLflow runs the dead attempt left RUNNING as KILLED. A run directory already holding
    a run is refused without ``resume``; a resume with a different experiment
    (:data:`RESUME_MAY_CHANGE` aside), beside a live driver, or whose registry or
    checkpoints disagree with its state file is refused before Ray starts. ``stop_after``:
    stop once this many generations are complete (for tests of resume). ``parent_run``: the
    MLflow run the run's own is nested under (a benchmark's), in the same experiment.
    """
    with _sigterm_as_interrupt():
        run = open_run(cfg, resume)
        try:
            done = _completed(run, cfg, tracking_uri)
            if done is not None:
                return done
            return _run(cfg, run, address, tracking_uri, progress, num_cpus, stop_after, parent_run)
        finally:
            run.close()


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM (``ray job stop``, a scheduler's stop) raises :class:`~atdrone.errors.Interrupted`, as Ctrl-C does,
    so the run's MLflow records end KILLED and its actors are released; the previous handler comes back
    afterwards. (A Ray started inside replaces it: :func:`init_ray` installs it again.)"""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def interrupt(signum: int, frame: Any) -> None:
        raise Interrupted(signum)

    previous = signal.signal(signal.SIGTERM, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


class _Crew:
    """The run's actors on Ray: its registry actor, its reserved CPUs and its coordinator (replaced when it, or a
    learner of it, dies)."""

    def __init__(self, cfg: ExperimentConfig, run: OpenRun, registry: Any, cpus: Any) -> None:
        from atdrone.service.pool import COORDINATORS

        self.cfg, self.run, self.registry, self.cpus = cfg, run, registry, cpus
        self.coordinator = COORDINATORS.take()

    def start(self, state: dict[str, Any] | None) -> None:
        import ray

        from atdrone.population import ALGORITHMS

        args = (self.cfg, ALGORITHMS[self.cfg.algorithm], str(self.run.run_dir), state, self.registry, self.cpus)
        ray.get(self.coordinator.start.remote(*args))

    def replace(self, generation: int, why: BaseException) -> None:
        """A new coordinator (with new learners and workers) at the last saved state; the rows the dead one wrote
        of ``generation`` discarded."""
        import ray

        from atdrone.service.pool import COORDINATORS

        log.warning("generation %d: %s; playing it again with new actors", generation, _first_line(why))
        ray.kill(self.coordinator, no_restart=True)  # its workers and learners go with it
        ray.get(self.registry.discard_generations.remote(self.cfg.name, generation))
        self.coordinator = COORDINATORS.take()
        # the state as a resume reads it (JSON), not the objects it was written from: they may differ in type
        self.start(read_json(self.run.run_dir / STATE_FILE, "service state").get("coordinator"))

    def fold_registry(self) -> None:
        """The registry's write-ahead log folded back into its file (best effort: a reader may hold part of it)."""
        import ray

        try:
            ray.get(self.registry.checkpoint.remote(), timeout=60)
        except ray.exceptions.RayError as exc:
            log.warning("could not fold the registry's log into %s: %s", self.run.registry, _first_line(exc))


def _first_line(exc: BaseException) -> str:
    lines = str(getattr(exc, "cause", None) or exc).strip().splitlines()
    return lines[0] if lines else type(exc).__name__


def _run(
    cfg: ExperimentConfig,
    run: OpenRun,
    address: str | None,
    tracking_uri: str | None,
    progress: bool,
    num_cpus: int | None,
    stop_after: int | None,
    parent_run: str | None = None,
) -> dict[str, Any]:
    import ray

    from atdrone.registry_ray import registry_actor
    from atdrone.service.coordinator import reserve_cpus
    from atdrone.service.pool import COORDINATORS

    init_ray(address, num_cpus)
    check_schedulable(cfg, wait_s=60.0 if (address or os.environ.get("RAY_ADDRESS")) else 0.0)
    # on the driver's node: the sqlite file (WAL) needs a local disk, which network file systems are not
    registry = registry_actor(run.registry, name=registry_name(cfg.name), node=ray.get_runtime_context().get_node_id())
    ended = False
    # the run's coordinator (with the learners and rollout workers it made) comes from this process's pool and
    # goes back to it: the next run starts none of those processes again. The run's CPUs are reserved here, so
    # they are freed whatever becomes of the coordinator.
    crew = _Crew(cfg, run, registry, reserve_cpus(cfg.num_workers))
    cpus = crew.cpus
    try:
        ray.get(registry.claim.remote(run.run_id, cfg.name))
        ray.get(registry.discard_generations.remote(cfg.name, run.start))  # what an interrupted generation left
        crew.start(run.saved.get("coordinator"))
        summary = _generations(cfg, crew, tracking_uri, progress, stop_after, parent_run)
        ended = True
    finally:  # a run that failed ends its coordinator (and its workers); the registry's name is free for the next run
        _release(crew, registry, registry_name(cfg.name), ended, cpus)
    COORDINATORS.give_back([crew.coordinator])  # its rollout workers emptied, kept (they hold no CPU)
    summary["registry"] = str(run.registry)
    return summary


def _completed(run: OpenRun, cfg: ExperimentConfig, tracking_uri: str | None) -> dict[str, Any] | None:
    """The summary of a run that already finished all ``cfg.generations`` (resumed again: nothing to do but fold
    its registry's log into the file and end its MLflow parent run, when a kill came after the summary and before
    the run's end)."""
    run_dir, saved = run.run_dir, run.saved
    if run.start < cfg.generations or not (run_dir / SUMMARY_FILE).exists():
        return None
    from atdrone.registry import Registry

    with Registry(run.registry) as registry:  # what a killed driver left in the write-ahead log, folded back
        registry.checkpoint()
    if saved.get("mlflow_run_id"):
        from atdrone.tracking import Tracker

        if Tracker(tracking_uri).end_run_if_running(saved["mlflow_run_id"]):
            log.info("ended the finished run's MLflow run %s, left RUNNING by a kill", saved["mlflow_run_id"])
    summary = read_json(run_dir / SUMMARY_FILE, "run summary")
    summary["population"] = pd.read_csv(run_dir / "population.csv")
    summary.update({"run_dir": str(run_dir), "mlflow_run_id": saved.get("mlflow_run_id"), "reports": []})
    summary.update({"complete": True, "registry": str(run.registry)})
    return summary


def _generations(
    cfg: ExperimentConfig,
    crew: _Crew,
    tracking_uri: str | None,
    progress: bool,
    stop_after: int | None,
    parent_run: str | None = None,
) -> dict[str, Any]:
    """Ask the coordinator for the remaining generations, logging each; then the final evaluation."""
    import ray

    from atdrone.policies.manifest import task_version
    from atdrone.population import ALGORITHMS
    from atdrone.tracking import Tracker

    run, registry, run_dir = crew.run, crew.registry, crew.run.run_dir
    tracker = Tracker(tracking_uri)
    reports: list[GenerationReport] = []
    experiment = cfg.experiment or cfg.name
    start = run.start
    tags = run.tags(cfg.name)
    attempt = {**tags, "atdrone.attempt": uuid.uuid4().hex}  # this driver's nested runs
    name = f"{cfg.name}-{cfg.algorithm}"
    nest = {"mlflow.parentRunId": parent_run} if parent_run else {}  # MLflow's own tag of a nested run
    with tracker.run(experiment, name, run_id=run.saved.get("mlflow_run_id"), tags={**tags, **nest}) as run_id:
        # what a dead attempt logged of generations it never saved: they are trained and logged again
        forgotten = tracker.forget_runs(experiment, tags, "atdrone.generation", run.saved.get("logged", start), run_id)
        killed = tracker.end_stale_runs(experiment, tags, keep=run_id)  # nested runs of an older layout
        if forgotten or killed:
            log.info("removed %d, ended %d MLflow runs of an interrupted attempt", len(forgotten), len(killed))
        if "mlflow_run_id" not in run.saved:
            run.save(
                {"coordinator": ray.get(crew.coordinator.state.remote()), "mlflow_run_id": run_id, "logged": start}
            )
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
        if cfg.protocol:  # the team events and split its training drew, as the document stood
            from atdrone.teams.protocols import load_protocol

            protocol = load_protocol(cfg.protocol)
            tracker.set_tags({"atdrone.protocol": protocol.name})
            tracker.log_dict(protocol.to_dict(), "protocol.json")
        tracker.log_artifact(run_dir / "config.json")
        for g in range(start, cfg.generations):
            t0 = time.perf_counter()
            report, state = _generation(crew, g, progress)
            reports.append(report)
            log_generation(tracker, report, run_dir, registry, cfg, run_id, attempt)
            crew.fold_registry()
            # the generation is saved and logged ("logged": MLflow holds generations 0 .. logged - 1)
            run.save({"coordinator": state, "mlflow_run_id": run_id, "logged": g + 1})
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
        summary = _finish(crew, tracker)
        summary.update({"run_dir": str(run_dir), "mlflow_run_id": run_id, "reports": reports})
    return summary


def _generation(crew: _Crew, g: int, progress: bool) -> tuple[GenerationReport, dict[str, Any]]:
    """Generation ``g`` from the coordinator, and the coordinator's state after it; played again by a new
    coordinator when it or a learner of it dies."""
    import ray

    for attempt in range(GENERATION_RETRIES + 1):
        try:
            report = _await_generation(crew.coordinator, crew.cfg.name, g, progress)
            return report, ray.get(crew.coordinator.state.remote())
        except Exception as exc:
            if attempt == GENERATION_RETRIES or not _actor_died(exc):
                raise
            crew.replace(g, exc)
    raise AssertionError("unreachable")


def _finish(crew: _Crew, tracker: Any) -> dict[str, Any]:
    """The final evaluation and records (:func:`~atdrone.service.results.finish`, whose writes are idempotent):
    again with a new coordinator when it or a learner of it dies."""
    for attempt in range(GENERATION_RETRIES + 1):
        try:
            return finish(tracker, crew.coordinator, crew.registry, crew.cfg, crew.run.run_dir)
        except Exception as exc:
            if attempt == GENERATION_RETRIES or not _actor_died(exc):
                raise
            crew.replace(crew.cfg.generations, exc)
    raise AssertionError("unreachable")


def _actor_died(exc: BaseException) -> bool:
    """Whether ``exc`` is (or was raised by a task because of) an actor's death; a rollout worker dead past its
    restarts (WorkerFailed) is not one to play again."""
    import ray

    from atdrone.service.actors import WorkerFailed

    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        if isinstance(cause, WorkerFailed):
            return False
        if isinstance(cause, ray.exceptions.RayActorError):
            return True
        cause = getattr(cause, "cause", None) or cause.__cause__
    return False


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


def _release(crew: _Crew, registry: Any, name: str, keep: bool, cpus: Any, timeout_s: float = 30.0) -> None:
    """Fold the registry's log into its file; free the run's CPUs (``cpus``, a placement group); close and kill the
    run's registry actor, and its coordinator (with it its workers) unless ``keep`` (a run that ended well: the pool
    takes it back); wait for the registry's name to be free."""
    import ray
    from ray.util.placement_group import remove_placement_group

    from atdrone.registry import REGISTRY_NAMESPACE

    crew.fold_registry()
    if not keep:
        ray.kill(crew.coordinator)
    remove_placement_group(cpus)
    try:  # closed before the kill: the actor's exit, which Ray finishes after the name is free, writes nothing
        ray.get(registry.close.remote(), timeout=timeout_s)
    except ray.exceptions.RayError as exc:
        log.warning("could not close the registry actor of %s: %s", name, _first_line(exc))
    ray.kill(registry, no_restart=True)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            ray.get_actor(name, namespace=REGISTRY_NAMESPACE)
        except ValueError:
            return
        time.sleep(0.1)
