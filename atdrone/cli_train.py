"""``atdrone train``: one policy locally or a population on Ray; what an interrupted or failed run kept."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from atdrone.cli_args import positive_int, say_error
from atdrone.config import ConfigError, read_json
from atdrone.errors import UserError, interrupt_exit_code, interrupt_on_signals, interrupted


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
    local.add_argument("--total-env-steps", type=positive_int, default=None, help="override the step budget")
    local.add_argument("--max-minutes", type=float, default=None, help="stop after this much wall time")
    local.add_argument("--device", default=None, help="auto (default), cpu or cuda for the PPO update")
    service = p.add_argument_group("population service (configs/experiments)")
    service.add_argument("--address", default=None, help="Ray cluster address (default: RAY_ADDRESS or a local Ray)")
    service.add_argument("--generations", type=positive_int, default=None, help="override the generations")
    return p


# Ray's "token authentication is enabled ... Set RAY_AUTH_MODE=disabled to opt out" on every local start: the
# local Ray listens on 127.0.0.1 with the token on, and the advice to turn it off is not one to give a new user
QUIET_LOGGERS = ("ray._private.authentication.authentication_token_setup",)


def run_train(args: argparse.Namespace) -> int:
    import logging

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    for name in QUIET_LOGGERS:  # notices about the libraries' defaults, not about this run
        logging.getLogger(name).setLevel(logging.ERROR)
    document = read_json(args.config)
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


def _service_failed(args: argparse.Namespace, exc: Exception) -> int:
    """A population run that failed, in one line by kind (bad input: exit 2; a fault: what was kept, the resume
    command, exit 1; a bug: an internal error, exit 1), never a Ray traceback."""
    from atdrone.service.faults import EXIT_FAULT, bug_line, explain

    fault = explain(exc)
    if fault is None:  # a bug: its own error, not Ray's wrapper (main names it an internal error)
        raise RuntimeError(bug_line(exc)) from exc
    if fault.code != EXIT_FAULT:
        say_error(args, fault.line)
        return fault.code
    _say_what_was_kept(args, True, exc, what=f"error: {fault.line}")
    return fault.code
