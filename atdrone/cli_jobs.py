"""``atdrone benchmark`` and ``atdrone deploy``: the benchmark grid and the flights."""

from __future__ import annotations

import argparse
import shlex
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

from atdrone.cli_args import EXIT_USAGE, invocation, positive_int, program, say_error
from atdrone.errors import interrupt_exit_code, interrupt_on_signals, interrupted

if TYPE_CHECKING:
    from atdrone.deploy.job import DeployResult


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
    p.add_argument(
        "--first",
        nargs="+",
        default=(),
        metavar="GLOB",
        help="run the cells whose names match these patterns first, in the order given (e.g. 'sp-4p2e1o-*' "
        "'floor-*'); the others follow in grid order. Results do not depend on the order",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress output")
    p.add_argument(
        "--report-so-far",
        metavar="DIR",
        default=None,
        help="run nothing: write the report of the cells finished so far to DIR (a folder other than the results "
        "folder; seconds, no Ray), its report.md naming the cells still missing",
    )
    return p


def run_benchmark(args: argparse.Namespace) -> int:
    from atdrone.benchmark.cells import load_benchmark
    from atdrone.benchmark.job import ended
    from atdrone.benchmark.job import run_benchmark as run

    if args.report_so_far is not None:
        return _report_so_far(args)
    cfg = load_benchmark(args.config, out_dir=args.out_dir, results_dir=args.results_dir)
    interrupt_on_signals()  # SIGTERM as Ctrl-C (installed again once Ray has started)
    try:
        summary = run(
            cfg,
            address=args.address,
            tracking_uri=args.tracking_uri,
            progress=not args.no_progress,
            first=args.first,
        )
    except BaseException as exc:  # one line by kind (an interrupt, a fault, bad input), never a Ray traceback
        end = None if args.debug else ended(cfg, exc, _benchmark_again(args))
        if end is None:  # a bug: main names it an internal error
            raise
        code, line = end
        print(f"{program(args)}: {line}", file=sys.stderr)
        return code
    print(f"{cfg.name}: {len(summary['records'])} cells; report {cfg.results / 'report.md'}")
    for m in summary["weights"]:
        print(f"  weights:{m['method']}/{m['task']} (seed {m['seed']}, chosen on {m['selected_on']['zoo'] or '-'})")
    return 0


def _report_so_far(args: argparse.Namespace) -> int:
    """``--report-so-far DIR``: the report of the finished cells in DIR; the job's results folder is refused."""
    from atdrone.benchmark.cells import cells, load_benchmark
    from atdrone.benchmark.job import report_so_far
    from atdrone.errors import UserError

    final = load_benchmark(args.config, out_dir=args.out_dir, results_dir=args.results_dir).results
    cfg = load_benchmark(args.config, out_dir=args.out_dir, results_dir=args.report_so_far)
    if cfg.results == final:
        raise UserError(f"--report-so-far {args.report_so_far}: that is the benchmark's results folder; name another")
    files, missing = report_so_far(cfg)
    done = len(cells(cfg)) - len(missing)
    print(f"{cfg.name}: a report of {done} finished cell(s), {len(missing)} missing: {files['report.md']}")
    return 0


def _benchmark_again(args: argparse.Namespace) -> str:
    """The command that resumes the same benchmark."""
    flags = (
        ("--out-dir", args.out_dir),
        ("--results-dir", args.results_dir),
        ("--tracking-uri", args.tracking_uri),
        ("--address", args.address),
    )
    again = f"atdrone benchmark {args.config}" + "".join(f" {f} {v}" for f, v in flags if v is not None)
    return again + "".join(f" --first '{g}'" if i == 0 else f" '{g}'" for i, g in enumerate(args.first))


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
    p.add_argument("--episodes", type=positive_int, default=None, help="override the config's episodes")
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
            say_error(args, f"no flight log directory {args.log!r} (usage: atdrone deploy report LOG)")
            return EXIT_USAGE
        print(format_summary(summarize(Path(args.log))))
        return 0
    if args.log:
        say_error(args, f"unexpected argument {args.log!r}")
        return EXIT_USAGE
    interrupt_on_signals()  # SIGTERM as Ctrl-C until the job takes both over (from then on every drone lands)
    try:
        from atdrone.deploy.bridge import BridgeError
        from atdrone.deploy.config import load_deploy
        from atdrone.deploy.job import DeployError
        from atdrone.deploy.job import run_deploy as deploy
        from atdrone.deploy.mocap import MocapError

        cfg = load_deploy(args.config, backend=args.backend, episodes=args.episodes, out_dir=args.out_dir)
        if args.compare and cfg.backend != "sim":
            say_error(args, "--compare needs the sim backend")
            return EXIT_USAGE
        try:
            result = deploy(cfg, arm=args.arm, tracking_uri=args.tracking_uri, compare=args.compare)
        except (DeployError, BridgeError, MocapError) as exc:  # a KeyError here is a bug (the deploy names its own)
            say_error(args, exc.args[0] if exc.args else exc)
            return 1
    except BaseException as exc:  # a stop signal before the job took them over: nothing was armed
        if not interrupted(exc) or args.debug:
            raise
        print(f"{program(args)}: interrupted; nothing armed; {_deploy_again(args)}", file=sys.stderr)
        return interrupt_exit_code(exc)
    if result.summary is not None:
        from atdrone.deploy.flightlog import format_summary

        print(format_summary(result.summary))
    if result.stopped_by:  # every drone landed first (one that could not is named)
        print(
            f"{program(args)}: interrupted; {_kept_flight(result, cfg.episodes)}; {_deploy_again(args)}",
            file=sys.stderr,
        )
        return 128 + signal.Signals[result.stopped_by]
    if not result.preflight.ok:
        return 1
    if result.ended_early:  # an armed flight that did not fly its episodes: every drone landed first
        flown = f"{result.episodes_flown}/{cfg.episodes}"
        say_error(args, f"flight ended early after {flown} episode(s): {result.ended_early}")
        return 1
    if result.gap is not None:
        from atdrone.deploy.gap import format_gap

        print(format_gap(result.gap))
        assert result.log_dir is not None
        from atdrone.fileio import atomic_write_bytes

        atomic_write_bytes(result.log_dir / "gap.json", json.dumps(result.gap, indent=2).encode())
    return 0


def _kept_flight(result: DeployResult, episodes: int) -> str:
    """How an interrupted deploy job left the drones and what it kept, for its last line."""
    if not result.flown:
        return "nothing armed"
    down = {n: e for n, e in (result.endings or {}).items() if e != "landed"}
    drones = "not landed: " + ", ".join(f"{n} {e}" for n, e in down.items()) if down else "every drone landed"
    return f"{drones} after {result.episodes_flown}/{episodes} episode(s); kept the flight log {result.log_dir}"


def _deploy_again(args: argparse.Namespace) -> str:
    """The command that runs the same deploy job again."""
    flags = [args.config, *(["--arm"] if args.arm else []), *(["--compare"] if args.compare else [])]
    for flag, value in (
        ("--backend", args.backend),
        ("--episodes", args.episodes),
        ("--out-dir", args.out_dir),
        ("--tracking-uri", args.tracking_uri),
    ):
        if value is not None:
            flags += [flag, str(value)]
    return f"{'fly' if args.arm else 'run'} again with: {invocation(args)} {shlex.join(flags)}"
