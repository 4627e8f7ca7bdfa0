"""The ``atdrone`` command line.

Each subcommand is a pair: ``add_<name>(subparsers)`` declares its arguments and
``run_<name>(args) -> int`` does the work; :data:`COMMANDS` wires them together, so a
new subcommand is one more pair and one more table row.

    atdrone render --task 4p2e5o --out run.gif [--seed 0] [--frame-every 2] [--png frame.png]
                   [--policy greedy|vicsek|PATH] [--zoo zoo1]
    atdrone gallery [--out-dir gallery]

``--out`` is always an output file (a GIF, an export) and ``--out-dir`` an output folder.
    atdrone evaluate --policy greedy|vicsek|PATH --task 4p2e1o|all --zoo zoo1|all [--episodes 500]
                     [--seeds 0 1 2] [--out-dir eval_out]
    atdrone deploy CONFIG [--arm] [--backend sim|cflib] [--episodes N] [--compare] [--tracking-uri URI]
    atdrone deploy report LOG
    atdrone benchmark CONFIG [--address ADDR] [--out-dir DIR] [--results-dir DIR] [--tracking-uri URI]
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from atdrone.cli_registry import add_member_location, add_registry, run_registry
from atdrone.cli_zoos import add_zoos, run_zoos
from atdrone.config import TASK_NAMES, ConfigError, read_json
from atdrone.errors import UserError, interrupt_exit_code, interrupt_on_signals, interrupted
from atdrone.fileio import output_file

EXIT_USAGE = 2  # bad arguments or a bad task document
POLICY_HELP = (
    "greedy, vicsek, a member id (hola-g3-0, or hola_quick/hola-g3-0 where several runs have it), models:/NAME@ALIAS, "
    "weights:METHOD/TASK, a checkpoint PATH or ZOO:MEMBER"
)


@dataclass(frozen=True)
class Command:
    """One subcommand: how to declare its arguments and what runs it."""

    add_parser: Callable[[Any], argparse.ArgumentParser]
    run: Callable[[argparse.Namespace], int]


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None


def _positive_int(text: str) -> int:
    value = _integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


MAX_EPISODES = 1_000_000  # episodes of one evaluation cell


def _episodes(text: str) -> int:
    value = _positive_int(text)
    if value > MAX_EPISODES:
        raise argparse.ArgumentTypeError(f"must be <= {MAX_EPISODES:,}, got {value:,}")
    return value


def _seed(text: str) -> int:
    value = _integer(text)
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"must be between 0 and 2**32 - 1, got {value}")
    return value


def _fps(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not 0 < value <= 100:
        raise argparse.ArgumentTypeError(f"must be in (0, 100] frames per second, got {text}")
    return value


_output_file = output_file  # the one check of an output file name (atdrone.fileio)


def _add_episode_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=_seed, default=0, help="seed of the episode (default 0)")
    p.add_argument("--frame-every", type=_positive_int, default=2, help="draw every k-th step into the GIF (default 2)")
    p.add_argument(
        "--max-steps", type=_positive_int, default=None, help="stop after this many steps (default: the task horizon)"
    )
    p.add_argument("--fps", type=_fps, default=10.0, help="GIF frames per second (default 10)")


def _format_summary(summary: dict[str, Any]) -> str:
    text = (
        f"{summary['task']} seed {summary['seed']}: {summary['outcome']} after {summary['steps']} steps, "
        f"return {summary['return']:+.2f}, captured {summary['captured']}/{summary['num_e']}"
    )
    if "team" in summary:
        team = summary["team"]
        partners = ", ".join(f"{n} in {s}" for n, s in zip(team["partners"], team["partner_slots"], strict=True))
        text += f"\nteam: learners in slots {', '.join(map(str, team['learner_slots']))}; partners {partners}"
    return text


def _error(args: argparse.Namespace, message: object) -> None:
    print(f"atdrone {args.command}: error: {message}", file=sys.stderr)


# ---------------------------------------------------------------- render
def add_render(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "render",
        help="render one episode to a GIF",
        description="Run one episode and save it as a GIF. Every pursuer follows --policy (default: the built-in "
        "chase-the-nearest-evader policy); with --zoo the policy drives the task's learner slots and partners drawn "
        "from the zoo (drawn green) the others.",
    )
    p.add_argument(
        "--task",
        default=None,
        help=f"task name ({', '.join(TASK_NAMES)}) or JSON path (default: the policy's task, else 4p2e5o)",
    )
    p.add_argument("--policy", default=None, help=f"{POLICY_HELP} (default: built-in chase)")
    p.add_argument("--zoo", default=None, help="fill the partner slots from this zoo (zoo1-zoo4, validation, a path)")
    p.add_argument("--out", type=Path, default=None, help="GIF path, *.gif (default: <task>.gif)")
    p.add_argument("--png", type=Path, default=None, help="also save the first frame as this PNG, *.png")
    _add_episode_args(p)
    add_member_location(p)
    return p


def run_render(args: argparse.Namespace) -> int:
    from atdrone.config import load_task
    from atdrone.envs.render import save_gif, save_png
    from atdrone.policies.zoo import load_zoo
    from atdrone.resolve import resolve
    from atdrone.teams.replay import record_episode

    if args.out is not None:
        _output_file(args.out, (".gif",))
    if args.png is not None:
        _output_file(args.png, (".png",), "--png")
    found = resolve(args.policy, db=args.db, run=args.run, runs_dir=args.runs_dir) if args.policy else None
    cfg = load_task(args.task or (found.task if found is not None and found.task else "4p2e5o"))
    zoo = load_zoo(args.zoo, cfg) if args.zoo is not None else None
    policy = found.policy() if found is not None else None
    partners = zoo.policies() if zoo is not None else None
    frames, summary = record_episode(
        cfg, args.seed, policy=policy, partners=partners, max_steps=args.max_steps, frame_every=args.frame_every
    )
    out = save_gif(frames, args.out if args.out is not None else Path(f"{cfg.name}.gif"), fps=args.fps)
    print(f"wrote {out} ({len(frames)} frames)")
    if args.png is not None:
        print(f"wrote {save_png(frames[0], args.png)}")
    print(_format_summary(summary))
    return 0


# --------------------------------------------------------------- gallery
DEMO_TASKS = ("4p2e1o", "4p2e3o", "4p2e5o", "4p3e5o")


def add_gallery(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "gallery",
        help="render an episode of each of the four tasks (the built-in chase policy)",
        description="Render one episode of each paper task to <out-dir>/<task>.gif and print a summary table. "
        "(`make demo` is something else: it trains a population.)",
    )
    p.add_argument("--out-dir", type=Path, default=Path("gallery"), help="output folder (default gallery)")
    _add_episode_args(p)
    return p


def run_gallery(args: argparse.Namespace) -> int:
    from atdrone.envs.render import save_gif
    from atdrone.teams.replay import record_episode

    rows = []
    for n, task in enumerate(DEMO_TASKS, 1):
        print(f"[{n}/{len(DEMO_TASKS)}] {task}: running and drawing an episode ...", flush=True)
        frames, summary = record_episode(task, args.seed, max_steps=args.max_steps, frame_every=args.frame_every)
        out = save_gif(frames, args.out_dir / f"{task}.gif", fps=args.fps)
        print(f"[{n}/{len(DEMO_TASKS)}] {task}: {summary['outcome']} after {summary['steps']} steps -> {out}")
        rows.append(summary)
    print()
    print(f"{'task':<8} {'outcome':<10} {'steps':>6} {'return':>8} {'captured':>9}")
    for s in rows:
        captured = f"{s['captured']}/{s['num_e']}"
        print(f"{s['task']:<8} {s['outcome']:<10} {s['steps']:>6} {s['return']:>8.2f} {captured:>9}")
    print(f"\nGIFs in {args.out_dir}/ (seed {args.seed}, built-in chase policy)")
    return 0


# ----------------------------------------------------------------- train
def add_train(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "train",
        help="train: one policy locally (configs/train) or a population on Ray (configs/experiments)",
        description="A config with 'mode' (configs/train/*.json) trains one policy in this process; a config "
        "with 'algorithm' (configs/experiments/*.json: sp, pbt, hola, hola_no_g, br, mappo, naht_d, "
        "naht_d_no_dec, fcp) runs the Ray population service, on a local Ray by default or on the cluster "
        "at --address. Tracked in MLflow "
        "(MLFLOW_TRACKING_URI, default sqlite:///mlflow.db). Runs live in <out_dir>/<name>/.",
    )
    p.add_argument("config", help="config JSON (configs/train/*.json or configs/experiments/*.json)")
    p.add_argument("--resume", action="store_true", help="continue the run from its last checkpoint / generation")
    p.add_argument("--seed", type=int, default=None, help="override the config's seed")
    p.add_argument("--name", default=None, help="override the run name")
    p.add_argument("--out-dir", default=None, help="override where runs are written (default runs/)")
    p.add_argument("--no-progress", action="store_true", help="no progress output")
    p.add_argument(
        "--tracking-uri", default=None, help="MLflow tracking URI (default MLFLOW_TRACKING_URI or ./mlflow.db)"
    )
    local = p.add_argument_group("local training (configs/train)")
    local.add_argument("--task", default=None, help="override the config's task (a task name or JSON path)")
    local.add_argument("--total-env-steps", type=_positive_int, default=None, help="override the step budget")
    local.add_argument("--max-minutes", type=float, default=None, help="stop after this much wall time")
    local.add_argument("--device", default=None, help="auto (default), cpu or cuda for the PPO update")
    service = p.add_argument_group("population service (configs/experiments)")
    service.add_argument("--address", default=None, help="Ray cluster address (default: RAY_ADDRESS or a local Ray)")
    service.add_argument("--generations", type=_positive_int, default=None, help="override the generations")
    return p


# Ray's "token authentication is enabled ... Set RAY_AUTH_MODE=disabled to opt out" on every local start: the
# local Ray listens on 127.0.0.1 with the token on, and the advice to turn it off is not one to give a new user
QUIET_LOGGERS = ("ray._private.authentication.authentication_token_setup",)


def run_train(args: argparse.Namespace) -> int:
    import logging

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for name in QUIET_LOGGERS:  # notices about the libraries' defaults, not about this run
        logging.getLogger(name).setLevel(logging.ERROR)
    try:
        document = read_json(args.config)
    except ValueError as exc:  # a number of more digits than Python converts (4300): not a config either
        if isinstance(exc, UserError):
            raise
        raise ConfigError(None, f"{args.config} is not a config: {str(exc).split(';')[0]}") from None
    if not isinstance(document, dict):
        raise ConfigError(None, f"{args.config} must hold a JSON object (a train or experiment config)")
    if args.tracking_uri:  # the trainer, the service's driver and the summary all read the one in force
        import os

        from atdrone.tracking import tracking_uri

        os.environ["MLFLOW_TRACKING_URI"] = tracking_uri(args.tracking_uri)
    service = "algorithm" in document
    interrupt_on_signals()  # SIGTERM as Ctrl-C (a service run installs it again once Ray has started)
    try:
        return _train_service(args) if service else _train_local(args)
    except BaseException as exc:  # a Ctrl-C or SIGTERM, or an error that carries one
        if not interrupted(exc):
            raise
        return _say_what_was_kept(args, service, exc)


def _say_what_was_kept(args: argparse.Namespace, service: bool, exc: BaseException, what: str = "interrupted") -> int:
    """The interrupted (or failed: ``what``) run's one line: what was kept and the command that resumes; the exit
    code of the signal (143 SIGTERM, 130 SIGINT). Re-raises an interrupt that came before a run."""
    where = getattr(args, "run_dir", None)
    if where is None:
        raise exc
    kept = _kept_service(where) if service else _kept_local(where)
    again = f"atdrone train {args.config}" + "".join(f" {a}" for a in _same_run_flags(args))
    if kept is None:
        born = service and (where / "service_state.json").exists()  # a born run is resumed, never started again
        print(
            f"atdrone train: {what} before the first checkpoint: nothing was kept in {where}; "
            f"start again with: {again}" + (" --resume" if born else ""),
            file=sys.stderr,
        )
    else:
        print(f"atdrone train: {what}; kept {kept} in {where}; resume with: {again} --resume", file=sys.stderr)
    return interrupt_exit_code(exc)


def _same_run_flags(args: argparse.Namespace) -> list[str]:
    """The flags that pick the same run again (name, seed, out folder), for the resume hint."""
    flags = []
    task = getattr(args, "task", None)
    pairs = (("--name", args.name), ("--seed", args.seed), ("--out-dir", args.out_dir), ("--task", task))
    for flag, value in pairs:
        if value is not None:
            flags.append(f"{flag} {value}")
    return flags


def _kept_local(run_dir: Path) -> str | None:
    """What an interrupted local run left: its last checkpoint (env steps), or None when nothing was saved."""
    if not (run_dir / "learner_state.safetensors").is_file() or not (run_dir / "last.pt").is_file():
        return None
    try:
        from atdrone.models.checkpoint import read_header

        steps = int(read_header(run_dir / "last.pt").get("step", 0))
    except (UserError, OSError, ValueError):
        return "the last checkpoint (last.pt)"
    return f"the checkpoint at {steps:,} env steps (last.pt; the updates after it are played again)"


def _kept_service(run_dir: Path) -> str | None:
    """What an interrupted population run left: its completed generations, or None when none completed."""
    import json

    try:
        done = int(json.loads((run_dir / "service_state.json").read_text())["coordinator"]["generation"])
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if done < 1:
        return None
    return f"{done} completed generation(s) (the registry, member checkpoints; the unfinished one is played again)"


def _train_local(args: argparse.Namespace) -> int:
    from atdrone.learn.trainer import load_train_config, run_training

    cfg = load_train_config(
        args.config,
        seed=args.seed,
        name=args.name,
        task=args.task,
        total_env_steps=args.total_env_steps,
        max_minutes=args.max_minutes,
        out_dir=args.out_dir,
        device=args.device,
    )
    args.run_dir = Path(cfg.out_dir) / cfg.name
    trainer = run_training(cfg, resume=args.resume, progress=not args.no_progress)
    last = trainer.history[-1] if trainer.history else {}
    evals = ", ".join(f"{k[5:]} {last[k]:.1f}" for k in ("eval/SUC", "eval/COL", "eval/AST", "eval/REW") if k in last)
    print(f"{cfg.name}: {trainer.env_steps} env steps; last evaluation: {evals or 'none'}")
    print(f"checkpoint: {trainer.run_dir / 'last.pt'}; curve: {trainer.run_dir / 'curve.png'}")
    from atdrone.tracking import ui_hint

    print(f"MLflow run {trainer.run_id}")
    print(ui_hint(cfg.experiment or cfg.name))
    return 0


def _train_service(args: argparse.Namespace) -> int:
    from atdrone.service.driver import format_summary, run_experiment
    from atdrone.service.experiment import load_experiment

    cfg = load_experiment(
        args.config, seed=args.seed, name=args.name, out_dir=args.out_dir, generations=args.generations
    )
    args.run_dir = Path(cfg.out_dir) / cfg.name
    try:
        summary = run_experiment(cfg, address=args.address, resume=args.resume, progress=not args.no_progress)
    except Exception as exc:
        if interrupted(exc) or args.debug:
            raise
        return _service_failed(args, exc)
    from atdrone.tracking import tracking_uri, ui_hint

    print(format_summary(cfg, summary, tracking_uri()))
    print(ui_hint(cfg.experiment or cfg.name))
    return 0


# -------------------------------------------------------------- evaluate
def add_evaluate(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "evaluate",
        help="SUC / COL / AST / REW of a policy teamed with unseen zoo partners",
        description="Play --episodes episodes per seed of the policy in the task's learner slots with partners drawn "
        "from the zoo; print SUC / COL / AST / REW (each with its 95 % confidence interval over episodes) as a table "
        "(rows tasks, columns zoos) and "
        "write <out>/<policy>_<task>_<zoo>.json (summary and per-seed metrics) and .csv (every episode).",
    )
    p.add_argument("--policy", required=True, help=f"the learner: {POLICY_HELP}")
    p.add_argument(
        "--task",
        default=None,
        help=f"task name ({', '.join(TASK_NAMES)}), JSON path, or all (default: the policy's task, else 4p2e1o)",
    )
    p.add_argument(
        "--zoo",
        default="zoo1",
        help="zoo name (zoo1-zoo4, validation), a protocol of team events (zoo3+swap, zoo3+drop, zoo3+drop+join), "
        "JSON path, or all (zoo1-zoo4)",
    )
    p.add_argument(
        "--episodes", type=_episodes, default=500, help=f"episodes per seed and cell, <= {MAX_EPISODES:,} (default 500)"
    )
    p.add_argument("--seeds", type=_seed, nargs="+", default=[0], help="distinct evaluation seeds >= 0 (default: 0)")
    p.add_argument(
        "--cross-task",
        action="store_true",
        help="let a policy trained on one task play another (labelled NAME@TASK in the report)",
    )
    p.add_argument("--out-dir", type=Path, default=Path("eval_out"), help="output folder (default eval_out)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument(
        "--tracking-uri",
        default=None,
        help="also record the result as a run of the MLflow experiment 'evaluate' in this store (e.g. "
        "sqlite:///mlflow.db)",
    )
    add_member_location(p)
    return p


def run_evaluate(args: argparse.Namespace) -> int:
    from tqdm import tqdm

    from atdrone.config import load_task
    from atdrone.policies.zoo import ZOO_NAMES, load_zoo
    from atdrone.resolve import resolve
    from atdrone.teams.evaluation import evaluate_grid, task_fit
    from atdrone.teams.protocols import is_protocol, load_protocol
    from atdrone.teams.reports import format_table, write_report

    if len(set(args.seeds)) != len(args.seeds):
        raise UserError(f"--seeds: each seed once, got {args.seeds} (a repeated seed replays the same episodes)")
    found = resolve(args.policy, db=args.db, run=args.run, runs_dir=args.runs_dir)
    task_arg = args.task or found.task or "4p2e1o"
    tasks = [load_task(t) for t in (TASK_NAMES if task_arg == "all" else [task_arg])]
    one_task = tasks[0] if len(tasks) == 1 else None  # with --task all, each task's drones are found per cell
    names = ZOO_NAMES if args.zoo == "all" else [args.zoo]
    protocols = [load_protocol(z) if is_protocol(z) else None for z in names]  # a protocol plays its zoo
    zoos = [load_zoo(p.zoo if p else z, one_task) for z, p in zip(names, protocols, strict=True)]
    learner = found.policy()
    notes = task_fit(learner, tasks, cross_task=args.cross_task)
    for note in notes:
        print(f"atdrone evaluate: warning: {note}", file=sys.stderr)
    trained_on = getattr(learner, "task", "")
    if trained_on and any(t.name != trained_on for t in tasks):
        learner.name = f"{learner.name}@{trained_on}"  # every record names the task it was trained on
    playable = [z for z in zoos if not z.missing]
    if not playable:  # nothing to play: the user's zoo is incomplete, one line and status 2
        missing = "; ".join(f"zoo {z.name} is missing {', '.join(z.missing)}" for z in zoos)
        raise UserError(f"no zoo has all its members ({missing}); nothing to evaluate")
    for zoo in zoos:
        if zoo.missing:
            print(
                f"atdrone evaluate: warning: zoo {zoo.name} is missing {', '.join(zoo.missing)}; its cells are skipped",
                file=sys.stderr,
            )
    label = "".join(c if c.isalnum() or c in "._-" else "_" for c in found.label)
    task_part = "all" if task_arg == "all" else tasks[0].name
    zoo_part = "all" if args.zoo == "all" else (protocols[0] or zoos[0]).name
    stem = f"{label}_{task_part}_{zoo_part}"
    total = len(tasks) * len(playable) * args.episodes * len(args.seeds)
    cells: list[Any] = []
    with tqdm(total=total, unit="ep", desc="evaluate", file=sys.stderr, disable=args.no_progress) as bar:
        for task in tasks:  # the report is rewritten after each cell: a long grid keeps what it has played
            for zoo, protocol in zip(zoos, protocols, strict=True):
                cells += evaluate_grid(
                    learner,
                    [task],
                    [zoo],
                    args.episodes,
                    args.seeds,
                    on_progress=bar.update,
                    cross_task=args.cross_task,
                    protocol=protocol,
                )
                json_path, csv_path = write_report(args.out_dir, stem, cells, args.policy, args.episodes, args.seeds)
    print(format_table(cells, args.policy, args.episodes, args.seeds))
    for cell in cells:  # a protocol's team events: before / after the first event, recovery time
        if cell.evaluation is not None and cell.evaluation.protocol:
            print(f"\n{cell.task} {cell.zoo}: " + ", ".join(_event_line(cell.evaluation)))
    print(f"\nwrote {json_path} and {csv_path}")
    if args.tracking_uri:
        from atdrone.teams.reports import report_document
        from atdrone.tracking import record_evaluation

        document = report_document(cells, args.policy, args.episodes, args.seeds)
        run_id, link = record_evaluation(document, [json_path, csv_path], stem, args.tracking_uri)
        print(f"MLflow run {run_id} (experiment 'evaluate'): {link}")
    return 0


def _event_line(evaluation: Any) -> list[str]:
    """Each event metric of an evaluation with its 95 % interval, as text."""
    from atdrone.teams.protocols import EVENT_METRICS

    value, interval = evaluation.pooled, evaluation.interval
    unit = lambda m: " steps" if m == "REC" else " %"
    return [f"{m} {value[m]:.1f}{unit(m)} [{interval[m][0]:.1f}, {interval[m][1]:.1f}]" for m in EVENT_METRICS]


def _service_failed(args: argparse.Namespace, exc: Exception) -> int:
    """A population run that failed, in one line by kind (bad input: exit 2; a fault: what was kept, the resume
    command, exit 1; a bug: an internal error, exit 1), never a Ray traceback."""
    from atdrone.service.faults import EXIT_FAULT, explain, one_line

    fault = explain(exc)
    if fault is None:  # a bug: its own error, not Ray's wrapper (main names it an internal error)
        root = getattr(exc, "cause", None)
        raise RuntimeError(f"{type(root or exc).__name__}: {one_line(root or exc)}") from exc
    if fault.code != EXIT_FAULT:
        _error(args, fault.line)
        return fault.code
    _say_what_was_kept(args, True, exc, what=f"error: {fault.line}")
    return fault.code


# ------------------------------------------------------------- benchmark
def add_benchmark(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "benchmark",
        help="train and evaluate every method x task x seed of a benchmark config, then report (resumable)",
        description="Run a benchmark (configs/benchmarks/*.json): every (method, task, seed) cell and the best "
        "responses on a Ray cluster (a local Ray by default), each final learner evaluated on every zoo; then the "
        "report (Markdown, CSV, PNG) and the kept weights in the results folder and on an MLflow run. Run it again "
        "after an interruption: finished cells are skipped, an interrupted one resumes.",
    )
    p.add_argument("config", help="benchmark config: a configs/benchmarks name (quick, paper) or a JSON path")
    p.add_argument("--address", default=None, help="Ray cluster address (default: RAY_ADDRESS or a local Ray)")
    p.add_argument("--out-dir", default=None, help="override out_dir (the cells' runs and records)")
    p.add_argument("--results-dir", default=None, help="override results_dir (the report and weights)")
    p.add_argument(
        "--tracking-uri", default=None, help="MLflow tracking URI (default MLFLOW_TRACKING_URI or ./mlflow.db)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress output")
    return p


def run_benchmark(args: argparse.Namespace) -> int:
    from atdrone.benchmark.cells import cells, load_benchmark
    from atdrone.benchmark.job import run_benchmark as run

    cfg = load_benchmark(args.config, out_dir=args.out_dir, results_dir=args.results_dir)
    interrupt_on_signals()  # SIGTERM as Ctrl-C (installed again once Ray has started)
    try:
        summary = run(cfg, address=args.address, tracking_uri=args.tracking_uri, progress=not args.no_progress)
    except BaseException as exc:
        if not interrupted(exc) or args.debug:
            raise
        from atdrone.benchmark.job import finished

        flags = (
            ("--out-dir", args.out_dir),
            ("--results-dir", args.results_dir),
            ("--tracking-uri", args.tracking_uri),
            ("--address", args.address),
        )
        again = f"atdrone benchmark {args.config}" + "".join(f" {f} {v}" for f, v in flags if v is not None)
        print(
            f"atdrone benchmark: interrupted; kept {len(finished(cfg))} finished cell(s) of {len(cells(cfg))} (an "
            f"unfinished one resumes from its last generation) in {cfg.folder}; resume with: {again}",
            file=sys.stderr,
        )
        return interrupt_exit_code(exc)
    print(f"{cfg.name}: {len(summary['records'])} cells; report {cfg.results / 'report.md'}")
    for m in summary["weights"]:
        print(f"  weights:{m['method']}/{m['task']} (seed {m['seed']}, chosen on {m['selected_on']['zoo'] or '-'})")
    return 0


# ---------------------------------------------------------------- deploy
def add_deploy(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "deploy",
        help="fly a population member on Crazyflie drones (or the simulated fleet); 'deploy report LOG' summarises",
        description="Connect the backend of a deploy config (configs/deploy/*.json), run the preflight checks and "
        "print the plan. Nothing arms without --arm (a dry run). With --arm: fly the episodes, write the flight log "
        "(Parquet, trajectories plot, GIF) under out_dir and log a deploy run to MLflow. --compare (sim backend) puts "
        "the flown SUC/COL/AST beside the training simulator's. 'atdrone deploy report LOG' prints a log's summary.",
    )
    p.add_argument("config", help="deploy config: a configs/deploy name or a JSON path; or 'report'")
    p.add_argument("log", nargs="?", help="with 'report': the flight log directory")
    p.add_argument("--arm", action="store_true", help="arm the drones and fly (without it: a dry run)")
    p.add_argument("--backend", choices=["sim", "cflib"], default=None, help="override the config's backend")
    p.add_argument("--episodes", type=_positive_int, default=None, help="override the config's episodes")
    p.add_argument("--compare", action="store_true", help="sim backend: the gap to the training simulator")
    p.add_argument(
        "--tracking-uri", default=None, help="MLflow tracking URI (default MLFLOW_TRACKING_URI or ./mlflow.db)"
    )
    p.add_argument("--out-dir", default=None, help="override the config's out_dir (flight logs)")
    return p


def run_deploy(args: argparse.Namespace) -> int:
    import json

    if args.config == "report":
        from atdrone.deploy.flightlog import format_summary, summarize

        if not args.log or not Path(args.log).is_dir():
            _error(args, f"no flight log directory {args.log!r} (usage: atdrone deploy report LOG)")
            return EXIT_USAGE
        print(format_summary(summarize(Path(args.log))))
        return 0
    if args.log:
        _error(args, f"unexpected argument {args.log!r}")
        return EXIT_USAGE
    from atdrone.deploy.bridge import BridgeError
    from atdrone.deploy.config import load_deploy
    from atdrone.deploy.job import DeployError, format_gap
    from atdrone.deploy.job import run_deploy as deploy
    from atdrone.deploy.mocap import MocapError

    cfg = load_deploy(args.config, backend=args.backend, episodes=args.episodes, out_dir=args.out_dir)
    if args.compare and cfg.backend != "sim":
        _error(args, "--compare needs the sim backend")
        return EXIT_USAGE
    try:
        result = deploy(cfg, arm=args.arm, tracking_uri=args.tracking_uri, compare=args.compare)
    except (DeployError, BridgeError, MocapError) as exc:  # a KeyError here is a bug (the deploy names its own)
        _error(args, exc.args[0] if exc.args else exc)
        return 1
    if not result.preflight.ok:
        return 1
    if result.summary is not None:
        from atdrone.deploy.flightlog import format_summary

        print(format_summary(result.summary))
    if result.ended_early:  # an armed flight that did not fly its episodes: every drone landed first
        flown = f"{result.episodes_flown}/{cfg.episodes}"
        _error(args, f"flight ended early after {flown} episode(s): {result.ended_early}")
        return 1
    if result.gap is not None:
        print(format_gap(result.gap))
        assert result.log_dir is not None
        from atdrone.fileio import atomic_write_bytes

        atomic_write_bytes(result.log_dir / "gap.json", json.dumps(result.gap, indent=2).encode())
    return 0


COMMANDS: dict[str, Command] = {
    "render": Command(add_render, run_render),
    "gallery": Command(add_gallery, run_gallery),
    "train": Command(add_train, run_train),
    "registry": Command(add_registry, run_registry),
    "evaluate": Command(add_evaluate, run_evaluate),
    "deploy": Command(add_deploy, run_deploy),
    "benchmark": Command(add_benchmark, run_benchmark),
    "zoos": Command(add_zoos, run_zoos),
}


def build_parser() -> argparse.ArgumentParser:
    from atdrone import __version__

    parser = argparse.ArgumentParser(prog="atdrone", description="AT-Drone multi-drone pursuit benchmark.")
    parser.add_argument("--version", action="version", version=f"atdrone {__version__}")
    parser.add_argument("--debug", action="store_true", help="show the traceback of an error")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for command in COMMANDS.values():
        command.add_parser(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv`` (default: sys.argv[1:]), run the subcommand, return its exit code.

    An error the user caused (:class:`atdrone.errors.UserError`: a bad config, a damaged
    checkpoint, a refused run) or a file that cannot be read or written is one line on
    stderr and exit code 2; anything else is a bug, one line and exit code 1. ``--debug``
    lets either raise with its traceback.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return COMMANDS[args.command].run(args)
    except KeyboardInterrupt as exc:
        _error(args, "interrupted")
        return interrupt_exit_code(exc)
    except Exception as exc:
        if interrupted(exc):  # a Ctrl-C that another error carries (one during a module's initialisation)
            _error(args, "interrupted")
            return interrupt_exit_code(exc)
        if args.debug:
            raise
        if isinstance(exc, (UserError, OSError)):
            _error(args, _one_line(exc))
            return EXIT_USAGE
        # a bug: say what and where to look, not a page of traceback
        _error(args, f"internal error: {type(exc).__name__}: {_one_line(exc)} (run with --debug for the traceback)")
        return 1


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line (KeyError's quoted argument unquoted)."""
    text = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
    return " ".join(text.split()) or type(exc).__name__


if __name__ == "__main__":
    sys.exit(main())
