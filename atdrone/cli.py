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

from atdrone.cli_args import EXIT_USAGE, Command, say_error
from atdrone.cli_evaluate import add_evaluate, run_evaluate
from atdrone.cli_jobs import add_benchmark, add_deploy, run_benchmark, run_deploy
from atdrone.cli_registry import add_registry, run_registry
from atdrone.cli_render import add_gallery, add_render, run_gallery, run_render
from atdrone.cli_train import add_train, run_train
from atdrone.cli_zoos import add_zoos, run_zoos
from atdrone.errors import UserError, interrupt_exit_code, interrupted

__all__ = ["COMMANDS", "Command", "build_parser", "main"]

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


def main(argv: list[str] | None = None, prog: str | None = None) -> int:
    """Parse ``argv`` (default: sys.argv[1:]), run the subcommand, return its exit code; ``prog``: the job script
    that runs the subcommand (``jobs/deploy.py``), named in its lines instead of ``atdrone COMMAND``.

    An error the user caused (:class:`atdrone.errors.UserError`: a bad config, a damaged
    checkpoint, a refused run) or a file that cannot be read or written is one line on
    stderr and exit code 2; anything else is a bug, one line and exit code 1. ``--debug``
    lets either raise with its traceback.
    """
    parser = build_parser()
    args = parser.parse_args(argv)
    args.prog = prog
    try:
        return COMMANDS[args.command].run(args)
    except KeyboardInterrupt as exc:
        say_error(args, "interrupted")
        return interrupt_exit_code(exc)
    except Exception as exc:
        if interrupted(exc):  # a Ctrl-C that another error carries (one during a module's initialisation)
            say_error(args, "interrupted")
            return interrupt_exit_code(exc)
        if args.debug:
            raise
        if isinstance(exc, (UserError, OSError)):
            say_error(args, _one_line(exc))
            return EXIT_USAGE
        # a bug: say what and where to look, not a page of traceback
        say_error(args, f"internal error: {type(exc).__name__}: {_one_line(exc)} (run with --debug for the traceback)")
        return 1


def _one_line(exc: BaseException) -> str:
    """An exception's message on one line (KeyError's quoted argument unquoted)."""
    text = str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc)
    return " ".join(text.split()) or type(exc).__name__


if __name__ == "__main__":
    sys.exit(main())
