"""The benchmark as one resumable job: every cell over a Ray cluster, then the report, weights and MLflow.

``run_benchmark`` starts (or joins, with ``address``) a Ray cluster and runs each cell
(:mod:`atdrone.benchmark.cells`) as a Ray task on whichever node has room: a cell's own
driver, taking no CPU itself, starting the service's coordinator, learner and rollout
workers (``num_workers`` CPUs) there; as many cells at once as the cluster's CPUs hold
(one at a time on a 2-core machine with 2 workers per cell). A finished cell's record is
written atomically to ``<folder>/cells/<cell>.json``; that file is what "done" means, so
a benchmark started again (after a kill, a crash, a lost node) runs only the cells
without one, and an interrupted cell resumes its service run from its last generation.
Progress: cells done / running / left and an estimate of the time left.

At the end the report (:mod:`atdrone.benchmark.report`) and the kept weights
(:mod:`atdrone.benchmark.weights`) are written to the results folder and logged, with the
Table 2 numbers as metrics, to a parent MLflow run (experiment ``<name>``, run
``benchmark``), whose id ``benchmark_state.json`` keeps so a resumed benchmark continues
the same run. A folder holding a different benchmark (other methods, tasks, seeds,
budgets) is refused.

While the job runs, :func:`report_so_far` writes the report of the cells finished so far
to another folder (``atdrone benchmark CONFIG --report-so-far DIR``; no Ray, nothing
trained, no weights kept), its ``report.md`` opening with how many cells it holds and
which are missing.
"""

from __future__ import annotations

import fnmatch
import json
import logging
import math
import statistics
import time
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from atdrone.benchmark.cells import Cell, cell_wall, cells, run_cell
from atdrone.benchmark.config import BenchmarkConfig
from atdrone.errors import UserError
from atdrone.fileio import atomic_write_bytes, atomic_write_text
from atdrone.rundir import RunError, read_json

log = logging.getLogger(__name__)
STATE_FILE = "benchmark_state.json"
CONFIG_FILE = "config.json"
CELLS_DIR = "cells"


def _write_json(path: Path, data: Any) -> None:
    atomic_write_bytes(path, json.dumps(data, indent=2, sort_keys=True).encode())


def cell_path(cfg: BenchmarkConfig, cell: Cell) -> Path:
    return cfg.folder / CELLS_DIR / f"{cell.name}.json"


def finished(cfg: BenchmarkConfig) -> dict[str, dict[str, Any]]:
    """The records of the cells already done (by cell name); a record of another benchmark is not one."""
    done = {}
    for cell in cells(cfg):
        path = cell_path(cfg, cell)
        if path.is_file():
            record = read_json(path, "cell record")
            if record.get("benchmark") == cfg.digest() and record.get("cell") == cell.to_dict():
                done[cell.name] = record
    return done


def _check_folder(cfg: BenchmarkConfig) -> None:
    """Refuse a folder that holds another benchmark; write this one's config there."""
    path = cfg.folder / CONFIG_FILE
    if path.is_file():
        saved = read_json(path, "benchmark config")
        if saved.get("digest") != cfg.digest():
            zoos = saved.get("zoo_versions")
            other = (
                f"other partners (zoo versions {zoos} != {cfg.zoo_versions()}): a partner drone changed, so its cells "
                "cannot be mixed with new ones; give this run another name or --out-dir"
                if zoos is not None and zoos != cfg.zoo_versions()
                else f"a different benchmark (config digest {saved.get('digest')} != {cfg.digest()}): run it with its "
                "own config, or give this one another name"
            )
            raise RunError(f"{cfg.folder} holds {other}")
    _write_json(path, {"digest": cfg.digest(), "config": cfg.to_dict(), "zoo_versions": cfg.zoo_versions()})


def cell_cpus(cfg: BenchmarkConfig, cell: Cell) -> int:
    """The CPUs a cell holds while it runs: its rollout workers (a floor cell: its evaluation)."""
    if cell.kind == "floor":
        return 1
    from atdrone.benchmark.cells import experiment

    return experiment(cfg, cell).num_workers


def run_benchmark(
    cfg: BenchmarkConfig,
    address: str | None = None,
    tracking_uri: str | None = None,
    progress: bool = True,
    num_cpus: int | None = None,
    first: Sequence[str] = (),
) -> dict[str, Any]:
    """Run the cells that are not done yet, then write the report; returns a summary (records, files).

    ``first``: cell-name patterns (fnmatch) whose cells run before the others, in the order of the patterns."""
    from atdrone.service.driver import init_ray
    from atdrone.tracking import Tracker, absolute_uri
    from atdrone.tracking import tracking_uri as resolve_uri

    cfg.folder.mkdir(parents=True, exist_ok=True)
    _check_folder(cfg)
    uri = absolute_uri(resolve_uri(tracking_uri))  # the cells' processes may run elsewhere
    state_path = cfg.folder / STATE_FILE
    state = read_json(state_path, "benchmark state") if state_path.is_file() else {}
    run_order(cells(cfg), first)  # a pattern matching no cell refused before Ray starts
    init_ray(address, num_cpus)
    tracker = Tracker(uri)
    tags = {"atdrone.benchmark": cfg.name, "atdrone.benchmark_digest": cfg.digest()}
    with tracker.run(cfg.name, "benchmark", run_id=state.get("mlflow_run_id"), tags=tags) as run_id:
        if state.get("mlflow_run_id") != run_id:
            _write_json(state_path, {"mlflow_run_id": run_id})
        tracker.log_params({"benchmark": cfg.to_dict()})
        records = _run_cells(cfg, uri, progress, run_id, first)
        from atdrone.benchmark.bounds import bounds_from_records, write_bounds
        from atdrone.benchmark.report import table2, write_report
        from atdrone.benchmark.weights import keep_weights

        files = write_report(cfg, records)
        # the bounds of the normalised scores, with the zoo version they were measured with
        files["bounds"] = write_bounds(bounds_from_records(records, cfg.eval_episodes), cfg.results / "bounds.json")
        say = (lambda line: print(f"[{cfg.name}] {line}", flush=True)) if progress else None
        manifests = keep_weights(cfg, records, say)
        _log_results(tracker, cfg, records, table2)
        for path in files.values():
            tracker.log_artifact(path, "report")
        from atdrone.resolve import weights_checkpoint, weights_manifest

        for m in manifests:  # the only models a benchmark registers: models:/atdrone-<name>@<method>-<task>
            tracker.log_artifact(weights_manifest(cfg.results, m["method"], m["task"]), f"weights/{m['method']}")
            alias = f"{m['method']}-{m['task']}".replace(".", "_")
            tags = {"method": m["method"], "task": m["task"], "benchmark": cfg.name, "seed": str(m["seed"])}
            tracker.register_weights(
                weights_checkpoint(cfg.results, m["method"], m["task"]), f"atdrone-{cfg.name}", alias, tags
            )
    if progress:
        print(f"[{cfg.name}] report: {cfg.results / 'report.md'}; MLflow run {run_id}", flush=True)
    return {"records": records, "files": files, "weights": manifests, "mlflow_run_id": run_id}


def report_so_far(cfg: BenchmarkConfig) -> tuple[dict[str, Path], list[str]]:
    """The report of the cells finished so far, in ``cfg.results`` (name a folder other than the job's own: the job
    writes its report and weights there when every cell is done); the files by name, and the cells still missing.

    Reads the cell records only (no Ray; seconds). ``report.md`` opens with how many of the grid's cells it holds
    and which are missing, by method; a comparison that lacks cells has fewer seeds (the tables' ``n``) or is
    absent. UserError when no cell is finished yet."""
    from datetime import UTC, datetime

    from atdrone.benchmark.bounds import bounds_from_records, write_bounds
    from atdrone.benchmark.report import write_report

    grid = cells(cfg)
    done = finished(cfg)
    if not done:
        raise UserError(f"{cfg.name}: no finished cell yet in {cfg.folder / CELLS_DIR}, so no report to write")
    missing = [c.name for c in grid if c.name not in done]
    records = [done[c.name] for c in grid if c.name in done]
    cfg.results.mkdir(parents=True, exist_ok=True)
    files = write_report(cfg, records)
    files["bounds"] = write_bounds(bounds_from_records(records, cfg.eval_episodes), cfg.results / "bounds.json")
    when = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    head = [f"**A report so far** ({when}): {len(records)} of the grid's {len(grid)} cells are finished."]
    if missing:
        by_method: dict[str, list[str]] = {}
        for name in missing:
            by_method.setdefault(name.split("-", 1)[0], []).append(name)
        head.append(
            "Missing: " + "; ".join(f"{m} ({len(v)}: {', '.join(v)})" for m, v in by_method.items()) + ". "
            "Tables hold the seeds finished (`n`); a comparison without both sides is absent. No weights are kept "
            "until the job ends."
        )
    else:
        head.append("Every cell is finished; the job's own end writes the final report and keeps the weights.")
    title, rest = files["report.md"].read_text().split("\n", 1)  # under the report's title
    files["report.md"] = atomic_write_text(files["report.md"], f"{title}\n\n{' '.join(head)}\n{rest}")
    return files, missing


def _log_results(tracker: Any, cfg: BenchmarkConfig, records: Sequence[dict[str, Any]], table2: Any) -> None:
    from atdrone.benchmark.report import evaluations

    table = table2(cfg, evaluations(records))
    metrics = {}
    for _, row in table.iterrows():
        for m in ("SUC", "COL", "AST", "REW"):
            metrics[f"{row['method']}/{row['task']}/{row['zoo']}/{m}"] = row[f"{m}_mean"]
    tracker.log_metrics(metrics, step=0, once=True)


def run_order(grid: Sequence[Cell], first: Sequence[str] = ()) -> list[Cell]:
    """The cells in the order they are started: those matching ``first``'s patterns by pattern, then the rest,
    each group in grid order. A pattern that matches no cell is refused (ConfigError): a typo would reorder
    nothing."""
    from atdrone.config import ConfigError

    for pattern in first:
        if not any(fnmatch.fnmatchcase(c.name, pattern) for c in grid):
            raise ConfigError(
                "--first", f"{pattern!r} matches no cell (cells are named like {', '.join(_examples(grid))})"
            )

    def rank(cell: Cell) -> int:
        return next((i for i, pattern in enumerate(first) if fnmatch.fnmatchcase(cell.name, pattern)), len(first))

    return sorted(grid, key=rank)  # stable: grid order within a rank


def _examples(grid: Sequence[Cell]) -> list[str]:
    """One cell name of each kind."""
    seen: dict[str, str] = {}
    for c in grid:
        seen.setdefault(c.kind, c.name)
    return list(seen.values())


def _run_cells(
    cfg: BenchmarkConfig, tracking_uri: str, progress: bool, parent_run: str, first: Sequence[str] = ()
) -> list[dict[str, Any]]:
    """Run every cell not yet done on the cluster, as many at once as its CPUs hold (``first``'s cells first);
    every record, in grid order. A failed cell does not stop the others; the job then fails naming it (run again
    to retry)."""
    import ray

    grid = cells(cfg)
    done = finished(cfg)
    todo = [c for c in run_order(grid, first) if c.name not in done]
    total_cpus = int(ray.cluster_resources().get("CPU", 1))
    task = ray.remote(run_cell)
    running: dict[Any, tuple[Cell, int, float]] = {}
    failed: list[tuple[str, Exception]] = []
    walls = finished_walls(done.values())  # a resumed job's estimate starts from what it finished before
    if progress:
        print(f"[{cfg.name}] {len(grid)} cells: {len(done)} done, {len(todo)} to run", flush=True)
    shown: tuple[int, int, int] | None = None  # the counts last printed
    needs: dict[str, int] = {}  # CPUs per method (every cell of a method has the same workers)

    def need(cell: Cell) -> int:
        if cell.method not in needs:
            needs[cell.method] = cell_cpus(cfg, cell)
        return needs[cell.method]

    while todo or running:
        held = sum(c for _, c, _ in running.values())
        while todo and (not running or held + need(todo[0]) <= total_cpus):
            if cfg.max_parallel and len(running) >= cfg.max_parallel:
                break
            cell = todo.pop(0)
            options = task.options(
                num_cpus=1 if cell.kind == "floor" else 0, scheduling_strategy="SPREAD", name=cell.name
            )
            running[options.remote(cfg, cell, tracking_uri, parent_run)] = (cell, need(cell), time.monotonic())
            held += need(cell)
        ready, _ = ray.wait(list(running), num_returns=1, timeout=10.0)
        for ref in ready:
            cell, _, started = running.pop(ref)
            try:
                record = ray.get(ref)
            except Exception as exc:  # a cell's error, or its node lost: the others go on
                failed.append((cell.name, exc))
                log.debug("cell %s failed", cell.name, exc_info=exc)  # the traceback, for a bug
                continue
            _write_json(cell_path(cfg, cell), record)
            done[cell.name] = record
            wall = cell_wall(record.get("timing", {}))  # a resumed cell's every attempt, not this one's alone
            walls.setdefault(cell.method, []).append(wall if math.isfinite(wall) else time.monotonic() - started)
        counts = (len(done), len(running), len(todo))
        if progress and counts != shown:  # a line only when a cell started or ended
            pending = [c for c, _, _ in running.values()] + todo
            print(f"[{cfg.name}] {_progress_line(*counts, walls, pending)}", flush=True)
            shown = counts
    if failed:
        raise cells_failed(failed)
    done = finished(cfg)  # as the folder holds them: with what was added beside the job (benchmarks/grid_episodes.py)
    return [done[c.name] for c in grid]


def cells_failed(failed: Sequence[tuple[str, Exception]]) -> Exception:
    """The error a benchmark whose cells failed ends with, naming each cell and its error in one line (the error
    behind Ray's wrapper, without terminal colours): bad input (a RunError) when every cell refused its input, else
    a fault (:class:`~atdrone.service.faults.ServiceFault`: the benchmark resumes, retrying them)."""
    from atdrone.service.faults import EXIT_BAD_INPUT, ServiceFault, bug_line, explain

    faults = [(name, explain(exc), exc) for name, exc in failed]
    lines = [f"{name} ({fault.line if fault else 'internal error: ' + bug_line(exc)})" for name, fault, exc in faults]
    message = f"{len(failed)} cell(s) failed: {'; '.join(lines)}"
    if all(fault is not None and fault.code == EXIT_BAD_INPUT for _, fault, _ in faults):
        return RunError(message)
    return ServiceFault(message)


def ended(cfg: BenchmarkConfig, exc: BaseException, again: str) -> tuple[int, str] | None:
    """How a benchmark job that raised ``exc`` ends: its exit status and last line (after the program's name). An
    interrupt (130 SIGINT, 143 SIGTERM) or a fault (1: the disk full, a store that cannot be written, failed cells)
    says what was kept and ``again``, the command that resumes; bad input (2) what is wrong. None for a bug."""
    from atdrone.errors import interrupt_exit_code, interrupted
    from atdrone.service.faults import EXIT_FAULT, explain

    if interrupted(exc):
        code, line = interrupt_exit_code(exc), "interrupted"
    else:
        fault = explain(exc) if isinstance(exc, Exception) else None
        if fault is None:
            return None
        code, line = fault.code, f"error: {fault.line}"
        if code != EXIT_FAULT:
            return code, line
    kept = (
        f"kept {len(finished(cfg))} finished cell(s) of {len(cells(cfg))} (an unfinished one resumes from its last "
        f"generation) in {cfg.folder}"
    )
    return code, f"{line}; {kept}; resume with: {again}"


def finished_walls(records: Iterable[Mapping[str, Any]]) -> dict[str, list[float]]:
    """Method label -> the wall seconds of its finished cells (each over all its attempts; records without timing
    left out)."""
    walls: dict[str, list[float]] = {}
    for record in records:
        wall = cell_wall(record.get("timing", {}))
        if math.isfinite(wall):
            walls.setdefault(record["cell"]["method"], []).append(wall)
    return walls


def _progress_line(
    done: int, running: int, left: int, walls: Mapping[str, Sequence[float]], pending: Sequence[Cell]
) -> str:
    """``cells: 3 done, 1 running, 6 left; about 4 min left``: each pending cell at the median wall time of its
    method's finished cells (:func:`finished_walls`, then each finished here; a method none finished yet: the median
    of the training methods' medians), as many at once as run now. The median: a cell that ran across a pause or beside
    other work would pull a mean far up."""
    line = f"cells: {done} done, {running} running, {left} left"
    typical = {m: statistics.median(ws) for m, ws in walls.items() if ws}  # a cell that sat out a pause is no guide
    if typical and pending:
        trained = [w for m, w in typical.items() if m != "floor"] or list(typical.values())  # floors train nothing
        overall = statistics.median(trained)  # a method whose only cell sat out a pause pulls a mean far up
        total = sum(typical.get(c.method, overall) for c in pending)
        line += f"; about {total / max(1, running) / 60:.1f} min left"
    return line
