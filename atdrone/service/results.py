"""What a service run records of itself: each generation in MLflow, and at the end the population table, the
best member (chosen on the selection zoo alone) as a model version, and the summary."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from atdrone.fileio import atomic_write_bytes
from atdrone.population.base import GenerationReport
from atdrone.service.experiment import ExperimentConfig
from atdrone.service.runstate import SUMMARY_FILE, write_json
from atdrone.teams.partners import slot_counts


def log_generation(
    tracker: Any,
    report: GenerationReport,
    run_dir: Path,
    registry: Any,
    cfg: ExperimentConfig,
    parent: str,
    tags: dict[str, str],
) -> None:
    """A generation as a nested MLflow run (metrics, documents, figures, a nested run per learner) and a
    point on the parent run's curves (:func:`generation_curves`; once: a resumed generation does not add a
    second point). The nested runs carry ``tags`` (the attempt's) and the generation index."""
    import ray

    from atdrone.population import ALGORITHMS

    g = report.generation
    gen_dir = run_dir / "generations" / f"{g:03d}"
    tags = {**tags, "atdrone.generation": str(g)}
    tracker.log_metrics(generation_curves(report, registry, cfg), step=g, run_id=parent, once=True)
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
            write_json(gen_dir / name, document)
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


def generation_curves(report: GenerationReport, registry: Any, cfg: ExperimentConfig) -> dict[str, float]:
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


def finish(tracker: Any, coordinator: Any, registry: Any, cfg: ExperimentConfig, run_dir: Path) -> dict[str, Any]:
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
    model = _log_best(tracker, best, score, run_dir, cfg) if cfg.register else ""
    budget = ray.get(coordinator.state.remote())["budget"]
    write_json(run_dir / SUMMARY_FILE, {"best": best, "selected_on": cfg.select_zoo, "budget": budget, "model": model})
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
        zoo = load_zoo(cfg.final_zoo, cfg.task) if cfg.final_zoo else None
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
            f"registry: atdrone registry --db {summary['registry']} list",
            (
                f"model: {summary.get('model', '')} (champion: models:/{model_name(cfg)}@champion = version "
                f"{champion_version(model_name(cfg), tracking_uri) or 'none'}; {ui_model_link(model_name(cfg))})"
                if cfg.register
                else "model: none registered (register: false)"
            ),
            f"MLflow: experiment {cfg.experiment or cfg.name!r}, run {summary['mlflow_run_id']} at {tracking_uri}; "
            f"browse with: mlflow ui --backend-store-uri {tracking_uri}",
        ]
    )
