"""What every ``atdrone`` subcommand shares: the subcommand record, argument types, the error line."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

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


def integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number, got {text!r}") from None


def positive_int(text: str) -> int:
    value = integer(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


MAX_EPISODES = 1_000_000  # episodes of one evaluation cell


def episodes_count(text: str) -> int:
    value = positive_int(text)
    if value > MAX_EPISODES:
        raise argparse.ArgumentTypeError(f"must be <= {MAX_EPISODES:,}, got {value:,}")
    return value


def seed_value(text: str) -> int:
    value = integer(text)
    if not 0 <= value < 2**32:
        raise argparse.ArgumentTypeError(f"must be between 0 and 2**32 - 1, got {value}")
    return value


def fps_value(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number, got {text!r}") from None
    if not 0 < value <= 100:
        raise argparse.ArgumentTypeError(f"must be in (0, 100] frames per second, got {text}")
    return value


def add_episode_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--seed", type=seed_value, default=0, help="seed of the episode (default 0)")
    p.add_argument("--frame-every", type=positive_int, default=2, help="draw every k-th step into the GIF (default 2)")
    p.add_argument(
        "--max-steps", type=positive_int, default=None, help="stop after this many steps (default: the task horizon)"
    )
    p.add_argument("--fps", type=fps_value, default=10.0, help="GIF frames per second (default 10)")


def format_summary(summary: dict[str, Any]) -> str:
    text = (
        f"{summary['task']} seed {summary['seed']}: {summary['outcome']} after {summary['steps']} steps, "
        f"return {summary['return']:+.2f}, captured {summary['captured']}/{summary['num_e']}"
    )
    if "team" in summary:
        team = summary["team"]
        partners = ", ".join(f"{n} in {s}" for n, s in zip(team["partners"], team["partner_slots"], strict=True))
        text += f"\nteam: learners in slots {', '.join(map(str, team['learner_slots']))}; partners {partners}"
    return text


def program(args: argparse.Namespace) -> str:
    """The name a subcommand's lines begin with: ``atdrone COMMAND``, or the job script that ran it
    (``jobs/deploy.py``)."""
    return getattr(args, "prog", None) or f"atdrone {args.command}"


def invocation(args: argparse.Namespace) -> str:
    """The command that runs the subcommand again: ``atdrone COMMAND`` or ``python jobs/SCRIPT.py``."""
    name = program(args)
    return f"python {name}" if name.endswith(".py") else name


def say_error(args: argparse.Namespace, message: object) -> None:
    print(f"{program(args)}: error: {message}", file=sys.stderr)
