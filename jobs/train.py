"""Ray job entrypoint: run (or resume) a population training experiment on the cluster.

    ray job submit --address http://HEAD:8265 --working-dir . -- \
        python jobs/train.py configs/experiments/hola_quick.json [--resume] [--generations N] [--name X] \
        [--out-dir /shared/runs] [--tracking-uri URI] [--updates-per-generation N] [--ppo '{"num_envs": 64}'] ...

Inside a Ray job RAY_ADDRESS is set, so ``atdrone.service.driver.run_experiment`` joins
the cluster instead of starting a local Ray; run outside a job it starts a local Ray
(or joins --address). The run lives in ``<out_dir>/<name>/`` (member checkpoints,
service_state.json, ...): on a cluster that must be storage every node sees, so pass
--out-dir (or set ATDRONE_OUT_DIR) to a shared path; its registry.db (sqlite in WAL
mode, which network file systems do not support) goes under --registry-dir (or
ATDRONE_REGISTRY_DIR), a folder on the local disk of the node the driver runs on (the
registry actor runs there too). MLflow goes to --tracking-uri, else
MLFLOW_TRACKING_URI, else ./mlflow.db (on a cluster: a tracking server). The overrides are named
like the config keys (--updates-per-generation and --updates_per_generation alike).
Bad input exits with status 2 and a one-line error; a fault the run cannot survive (the disk
full, a store that cannot be written) with status 1 and a line saying what was kept and
how to resume; SIGTERM (``ray job stop``) and SIGINT end the run cleanly (its MLflow runs
KILLED, what was kept and the resume command in one line) with status 143 and 130.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:  # `--working-dir .` on nodes that only have the dependencies
    sys.path.insert(0, str(REPO_ROOT))

PROG = "jobs/train.py"
EXIT_USAGE = 2
# integer config keys that can be overridden from the command line
from atdrone.service.experiment import POSITIVE_INTS  # noqa: E402 - after the sys.path set-up

INT_OVERRIDES = ("seed", *POSITIVE_INTS)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("config", help="experiment config JSON (configs/experiments/*.json)")
    p.add_argument("--resume", action="store_true", help="continue the run from its last completed generation")
    p.add_argument("--name", default=None, help="override the run (and MLflow experiment) name")
    p.add_argument(
        "--out-dir",
        "--out_dir",
        dest="out_dir",
        default=os.environ.get("ATDRONE_OUT_DIR"),
        help="where runs are written (default: $ATDRONE_OUT_DIR, else the config's out_dir)",
    )
    p.add_argument(
        "--registry-dir",
        default=None,
        help="a folder on the driver node's local disk for the run's registry.db (default: $ATDRONE_REGISTRY_DIR, "
        "else the run directory); sqlite's WAL does not work on NFS/EFS",
    )
    p.add_argument("--tracking-uri", default=None, help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI)")
    p.add_argument("--address", default=None, help="Ray address (default: $RAY_ADDRESS, set inside a Ray job)")
    p.add_argument("--final-zoo", "--final_zoo", dest="final_zoo", default=None, help="override the final zoo")
    p.add_argument("--no-gif", action="store_true", help="skip the GIF of the best member")
    p.add_argument(
        "--learner-gpus",
        "--learner_gpus",
        dest="learner_gpus",
        type=float,
        default=None,
        metavar="G",
        help="override learner_gpus: GPUs each learner asks Ray for (its update then runs on CUDA)",
    )
    p.add_argument("--ppo", default=None, help="PPO overrides as JSON, merged over the config's ppo section")
    for key in INT_OVERRIDES:
        flag = key.replace("_", "-")
        names = [f"--{flag}"] + ([f"--{key}"] if flag != key else [])
        p.add_argument(*names, dest=key, type=int, default=None, metavar="N", help=f"override {key}")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from atdrone.config import ConfigError, read_document
    from atdrone.errors import interrupt_exit_code, interrupt_on_signals, interrupted
    from atdrone.service.driver import format_summary, run_experiment
    from atdrone.service.experiment import load_experiment
    from atdrone.service.faults import EXIT_FAULT, explain
    from atdrone.service.runstate import kept

    overrides = {key: getattr(args, key) for key in INT_OVERRIDES}
    overrides.update(name=args.name, out_dir=args.out_dir, final_zoo=args.final_zoo, learner_gpus=args.learner_gpus)
    if args.no_gif:
        overrides["gif"] = False
    try:
        if args.ppo is not None:
            try:
                extra = json.loads(args.ppo)
            except json.JSONDecodeError as exc:
                raise ConfigError("ppo", f"--ppo is not JSON: {exc}") from None
            if not isinstance(extra, dict):
                raise ConfigError("ppo", "--ppo must be a JSON object")
            overrides["ppo"] = {**read_document(args.config, "experiments").get("ppo", {}), **extra}
        cfg = load_experiment(args.config, **overrides)
    except ConfigError as exc:
        print(f"{PROG}: error: {exc}".splitlines()[0], file=sys.stderr)
        return EXIT_USAGE
    if args.registry_dir:
        from atdrone.service.driver import REGISTRY_DIR_ENV

        os.environ[REGISTRY_DIR_ENV] = args.registry_dir
    where = os.environ.get("RAY_ADDRESS") or args.address or "a local Ray"
    print(f"{PROG}: {cfg.name} ({cfg.algorithm} on {cfg.task}, {cfg.generations} generations) on {where}", flush=True)
    interrupt_on_signals()  # SIGTERM as Ctrl-C (installed again once Ray has started)
    try:
        summary = run_experiment(cfg, address=args.address, resume=args.resume, tracking_uri=args.tracking_uri)
    except BaseException as exc:  # one line by kind, never a Ray traceback
        run_dir = Path(cfg.out_dir) / cfg.name
        again = " ".join(["python", PROG, *(argv if argv is not None else sys.argv[1:])])
        again += "" if args.resume else " --resume"
        if interrupted(exc):
            print(f"{PROG}: interrupted; kept {kept(run_dir)} in {run_dir}; resume with: {again}", file=sys.stderr)
            return interrupt_exit_code(exc)
        fault = explain(exc) if isinstance(exc, Exception) else None
        if fault is None:
            raise
        if fault.code == EXIT_FAULT:
            print(
                f"{PROG}: error: {fault.line}; kept {kept(run_dir)} in {run_dir}; resume with: {again}", file=sys.stderr
            )
        else:  # a run that exists, a damaged state file, a cluster that cannot place it, ...
            print(f"{PROG}: error: {fault.line}", file=sys.stderr)
        return fault.code
    from atdrone.tracking import tracking_uri, ui_hint

    print(format_summary(cfg, summary, tracking_uri(args.tracking_uri)))
    print(ui_hint(cfg.experiment or cfg.name, args.tracking_uri))  # an absolute store: a job's folder is temporary
    print(f"{PROG}: done")
    return 0


if __name__ == "__main__":
    sys.exit(main())
