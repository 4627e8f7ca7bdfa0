"""Ray job entrypoint: run (or continue) a benchmark on the cluster.

    ray job submit --address http://HEAD:8265 --working-dir . -- \\
        python jobs/benchmark.py configs/benchmarks/quick.json [--out-dir /shared/bench] [--results-dir DIR] \\
        [--tracking-uri URI]

Inside a Ray job RAY_ADDRESS is set, so the cells run on the cluster's nodes; outside a
job it starts a local Ray (or joins --address). The cells' runs and records live in
``<out_dir>/<name>/``: on a cluster that must be storage every node sees (--out-dir or
ATDRONE_OUT_DIR). Submitting the same config again after an interruption continues it:
finished cells are skipped. Bad input exits with status 2 and a one-line error; a fault it
cannot survive (the disk full, a store that cannot be written, cells that failed) with status 1,
and SIGTERM (``ray job stop``) and SIGINT stop it cleanly with 143 and 130, each in one line
saying what was kept and how to resume.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:  # `--working-dir .` on nodes that only have the dependencies
    sys.path.insert(0, str(REPO_ROOT))

PROG = "jobs/benchmark.py"
EXIT_USAGE = 2


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("config", help="benchmark config (configs/benchmarks/*.json, or a name: quick, paper)")
    p.add_argument("--out-dir", default=os.environ.get("ATDRONE_OUT_DIR"), help="override out_dir")
    p.add_argument("--results-dir", default=None, help="override results_dir")
    p.add_argument("--tracking-uri", default=None, help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI)")
    p.add_argument("--address", default=None, help="Ray address (default: $RAY_ADDRESS, set inside a Ray job)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from atdrone.benchmark.cells import load_benchmark
    from atdrone.benchmark.job import ended, run_benchmark
    from atdrone.errors import UserError, interrupt_on_signals

    try:
        cfg = load_benchmark(args.config, out_dir=args.out_dir, results_dir=args.results_dir)
    except UserError as exc:
        print(f"{PROG}: error: {exc}".splitlines()[0], file=sys.stderr)
        return EXIT_USAGE
    where = os.environ.get("RAY_ADDRESS") or args.address or "a local Ray"
    print(f"{PROG}: benchmark {cfg.name} on {where}", flush=True)
    interrupt_on_signals()  # SIGTERM as Ctrl-C (installed again once Ray has started)
    try:
        summary = run_benchmark(cfg, address=args.address, tracking_uri=args.tracking_uri)
    except BaseException as exc:  # one line by kind (an interrupt, a fault, bad input), never a Ray traceback
        end = ended(cfg, exc, shlex.join(["python", PROG, *(argv if argv is not None else sys.argv[1:])]))
        if end is None:
            raise
        code, line = end
        print(f"{PROG}: {line}", file=sys.stderr)
        return code
    print(f"{PROG}: done: {len(summary['records'])} cells, report {cfg.results / 'report.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
