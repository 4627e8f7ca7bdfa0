"""The driver of a population training run: Ray, the registry actor, the coordinator, MLflow.

``run_experiment`` starts (or joins, with ``address``) a Ray cluster, serves the run's
registry (``<out_dir>/<name>/registry.db``) from a named actor in namespace
``atdrone``, creates the coordinator and asks it for one generation after another.
After each generation it writes ``service_state.json`` (atomically) and logs the
generation to MLflow as a nested run under the job's parent run, with a nested run
per learner. ``resume=True`` continues from the last completed generation.
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from atdrone.fileio import atomic_write_bytes
from atdrone.population.base import GenerationReport
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


def init_ray(address: str | None, num_cpus: int | None = None) -> None:
    """Join the cluster at ``address`` (or RAY_ADDRESS), else start a local one."""
    import ray

    if ray.is_initialized():
        return
    address = address or os.environ.get("RAY_ADDRESS")
    kwargs: dict[str, Any] = {"namespace": "atdrone", "log_to_driver": False}
    if address:
        ray.init(address=address, **kwargs)
    else:
        ray.init(num_cpus=num_cpus or min(os.cpu_count() or 2, 8), include_dashboard=False, **kwargs)


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

    ``stop_after``: stop once this many generations are complete (for tests of resume).
    """

    import ray

    from atdrone.population import ALGORITHMS
    from atdrone.registry import registry_actor
    from atdrone.service.coordinator import Coordinator

    run_dir = Path(cfg.out_dir).resolve() / cfg.name
    state_path = run_dir / STATE_FILE
    saved: dict[str, Any] = {}
    if state_path.exists():
        if not resume:
            raise FileExistsError(f"{run_dir} holds a run: pass --resume to continue it, or pick another name")
        saved = json.loads(state_path.read_text())
    run_dir.mkdir(parents=True, exist_ok=True)
    _write_json(run_dir / "config.json", cfg.to_dict())
    init_ray(address, num_cpus)
    registry = registry_actor(run_dir / "registry.db", name=registry_name(cfg.name))
    start = saved.get("coordinator", {}).get("generation", 0)
    ray.get(registry.discard_generations.remote(cfg.name, start))  # what an interrupted generation left
    coordinator = Coordinator.remote(cfg, ALGORITHMS[cfg.algorithm], str(run_dir), saved.get("coordinator"), registry)
    try:
        return _generations(cfg, coordinator, registry, run_dir, saved, tracking_uri, progress, stop_after)
    finally:  # the run's actors end with it; the registry's name is free for the next run
        _release(coordinator, registry, registry_name(cfg.name))


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

    from atdrone.tracking import Tracker

    state_path = run_dir / STATE_FILE
    tracker = Tracker(tracking_uri)
    reports: list[GenerationReport] = []
    with tracker.run(
        cfg.experiment or cfg.name, f"{cfg.name}-{cfg.algorithm}", run_id=saved.get("mlflow_run_id")
    ) as run_id:
        tracker.log_params({"experiment": cfg.to_dict()})
        tracker.set_tags({"atdrone.algorithm": cfg.algorithm, "atdrone.task": cfg.task})
        tracker.log_artifact(run_dir / "config.json")
        start = saved.get("coordinator", {}).get("generation", 0)
        for g in range(start, cfg.generations):
            t0 = time.perf_counter()
            report: GenerationReport = ray.get(coordinator.run_generation.remote())
            reports.append(report)
            _log_generation(tracker, report, run_dir, registry, cfg)
            state = {"coordinator": ray.get(coordinator.state.remote()), "mlflow_run_id": run_id}
            _write_json(state_path, state)
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
        summary = _finish(tracker, coordinator, registry, cfg, run_dir)
        summary.update({"run_dir": str(run_dir), "mlflow_run_id": run_id, "reports": reports})
    return summary


def _release(coordinator: Any, registry: Any, name: str, timeout_s: float = 30.0) -> None:
    """Kill the run's coordinator (and with it its workers) and registry actor; wait for the name to be free."""
    import ray

    from atdrone.registry import REGISTRY_NAMESPACE

    ray.kill(coordinator)
    ray.kill(registry, no_restart=True)
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            ray.get_actor(name, namespace=REGISTRY_NAMESPACE)
        except ValueError:
            return
        time.sleep(0.1)


def _log_generation(
    tracker: Any, report: GenerationReport, run_dir: Path, registry: Any, cfg: ExperimentConfig
) -> None:
    """A generation as a nested MLflow run: its metrics, documents, figures, and a nested run per learner."""
    import ray

    from atdrone.population import ALGORITHMS

    g = report.generation
    gen_dir = run_dir / "generations" / f"{g:03d}"
    with tracker.run(cfg.name, f"generation-{g}", nested=True):
        metrics = {"pop/size": len(report.population), "perf/generation_s": report.wall_s, **report.metrics}
        metrics.update({f"budget/{k}": float(v) for k, v in report.budget.items()})
        if report.matches:
            metrics["eval/matches"] = len(report.matches)
            metrics["eval/SUC"] = float(np.mean([m.metrics["SUC"] for m in report.matches]))
            metrics["eval/COL"] = float(np.mean([m.metrics["COL"] for m in report.matches]))
        for t in report.training:  # partner slots each member filled in the learner's training episodes
            metrics.update({f"pop/drawn/{t.member}/{m}": n for m, n in slot_counts(t.drawn).items()})
        tracker.log_metrics(metrics, step=g)
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
            with tracker.run(cfg.name, f"learner-{t.member}", nested=True):
                tracker.set_tags({"atdrone.member": t.member, "atdrone.generation": str(g)})
                tracker.log_dict(
                    {"parent": t.parent, "seed": t.seed, "partners": t.partners, "drawn": t.drawn}, "training.json"
                )
                for i, row in enumerate(t.history):
                    tracker.log_metrics(row, step=i)
                tracker.log_artifact(run_dir / "members" / f"{t.member}.pt", "checkpoints")
                ray.get(registry.update_member.remote(t.member, mlflow_run_id=tracker.mlflow.active_run().info.run_id))


def _finish(tracker: Any, coordinator: Any, registry: Any, cfg: ExperimentConfig, run_dir: Path) -> dict[str, Any]:
    """Evaluate the population on the final zoo, print and log the population table."""
    import ray

    results = (
        ray.get(coordinator.evaluate_population.remote(cfg.final_zoo, cfg.final_episodes)) if cfg.final_zoo else {}
    )
    state = ray.get(coordinator.state.remote())["algorithm"]
    eta, rho, drawn = state.get("eta", {}), state.get("rho", {}), state.get("drawn", {})
    rows = []
    for m in state["population"]:
        row: dict[str, Any] = {"member": m, "eta": eta.get(m, float("nan"))}
        if rho:  # the last generation's partner distribution and the partner slots drawn from it
            row.update({"rho": rho.get(m, float("nan")), "drawn": int(drawn.get(m, 0))})
        for k, v in results.get(m, {}).items():
            row[f"{cfg.final_zoo}_{k}"] = v
        rows.append(row)
    table = pd.DataFrame(rows)
    atomic_write_bytes(run_dir / "population.csv", table.to_csv(index=False).encode())
    tracker.log_artifact(run_dir / "population.csv")
    suc = f"{cfg.final_zoo}_SUC"
    if results:
        tracker.log_metrics({f"eval/{cfg.final_zoo}/best_SUC": float(table[suc].max())}, step=cfg.generations)
        best = str(table.loc[table[suc].idxmax(), "member"])
    else:
        best = state["population"][-1]
    _log_best(tracker, best, run_dir, cfg)
    return {"population": table, "best": best, "budget": ray.get(coordinator.state.remote())["budget"]}


def _log_best(tracker: Any, best: str, run_dir: Path, cfg: ExperimentConfig) -> None:
    """Log the best member as an MLflow model with alias "champion", and a GIF of it playing."""
    from atdrone.models.checkpoint import load_checkpoint

    path = run_dir / "members" / f"{best}.pt"
    model, header = load_checkpoint(path)
    tracker.log_model(
        model, name=f"atdrone-{cfg.name}", alias="champion", tags={"member": best, "checkpoint": str(path.resolve())}
    )
    if cfg.gif:
        from atdrone.envs.render import save_gif
        from atdrone.policies.neural import NeuralPolicy
        from atdrone.teams.replay import record_episode

        policy = NeuralPolicy(model, name=best, num_p=header["num_p"], num_e=header["num_e"])
        frames, _ = record_episode(cfg.task, seed=cfg.seed, policy=policy, frame_every=4, max_steps=400)
        gif = run_dir / "best.gif"
        save_gif(frames, gif, fps=10)
        tracker.log_artifact(gif)
    tracker.log_dict(header, "best_member_header.json")


def format_summary(cfg: ExperimentConfig, summary: dict[str, Any], tracking_uri: str) -> str:
    """The end-of-run text: the population table and where to look (run dir, registry, MLflow)."""
    with pd.option_context("display.float_format", "{:.2f}".format, "display.width", 120):
        table = summary["population"].to_string(index=False)
    return "\n".join(
        [
            f"\npopulation of {cfg.name} ({cfg.algorithm}, {cfg.task}):",
            table,
            f"best member: {summary['best']}; run directory: {summary['run_dir']}",
            "budget: " + ", ".join(f"{k.replace('_', ' ')} {v:,}" for k, v in summary.get("budget", {}).items()),
            f"registry: atdrone registry --db {summary['run_dir']}/registry.db list",
            f"MLflow: experiment {cfg.experiment or cfg.name!r}, run {summary['mlflow_run_id']} at {tracking_uri}; "
            f"browse with: mlflow ui --backend-store-uri {tracking_uri}",
        ]
    )
