"""``atdrone registry``: query population registries (runs, members, matches, cross-play, lineage, export).

Also the options every command that names a member shares (:func:`add_member_location`):
``--db FILE``, ``--run RUN`` and ``--runs-dir DIR``, so ``render``, ``evaluate`` and every
registry query find ``hola-g3-0`` (or ``hola_quick/hola-g3-0``) the same way.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

DB_HELP = "registry file (default: $ATDRONE_REGISTRY, else those found under --runs-dir)"
RUN_HELP = "the run whose registry holds the member (its name, e.g. hola_quick): picks one among several runs"
RUNS_HELP = "where to look for runs/*/registry.db without --db (default runs)"
MEMBER_HELP = "a member id (hola-g3-0), a run-qualified id (hola_quick/hola-g3-0), a models:/ URI or a checkpoint file"
FORMATS = ("table", "csv", "json")


def add_member_location(p: argparse.ArgumentParser, db: Any = None, run: Any = None, runs_dir: Any = None) -> None:
    """``--db``, ``--run`` and ``--runs-dir``: where a member id is looked up (defaults: any registry under runs/)."""
    p.add_argument("--db", type=Path, default=db, help=DB_HELP)
    p.add_argument("--run", default=run, help=RUN_HELP)
    p.add_argument("--runs-dir", type=Path, default=Path("runs") if runs_dir is None else runs_dir, help=RUNS_HELP)


def add_registry(subparsers: Any) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "registry",
        help="query the population registry (runs, members, matches, cross-play, lineage, export)",
        description="Read population registries (sqlite files) read-only, whether or not Ray is running. "
        "The file is --db, else $ATDRONE_REGISTRY, else the registries under --runs-dir (runs/*/registry.db), "
        "else ./registry.db. `runs` and `list` read every registry found; the other queries read one: --run "
        "picks a run's. A member is named by its id where one run has it, else as RUN/ID (hola_quick/hola-g3-0).",
    )
    add_member_location(p)
    sub = p.add_subparsers(dest="registry_command", metavar="QUERY", required=True)

    def query(name: str, help: str) -> argparse.ArgumentParser:
        q = sub.add_parser(name, help=help, description=help)
        add_member_location(q, argparse.SUPPRESS, argparse.SUPPRESS, argparse.SUPPRESS)  # also accepted after QUERY
        return q

    def sorting(q: argparse.ArgumentParser, example: str) -> None:
        q.add_argument("--sort", metavar="KEY", default=None, help=f"order the rows by this column, e.g. {example}")
        q.add_argument("--desc", action="store_true", help="with --sort: highest first (missing values stay last)")

    q = query("runs", "the registries found: run, algorithm, task, generations, members, best member")
    q.add_argument("--format", choices=FORMATS, default="table", help="table (default), csv or json")
    q = query("list", "the members, optionally filtered and sorted: a compact table fitted to the terminal")
    q.add_argument("--task", default=None, help="only this task")
    q.add_argument("--status", default=None, help="only this status (active, retired, missing)")
    q.add_argument("--columns", default=None, help="comma-separated member fields or metric keys, e.g. id,zoo1/SUC")
    sorting(q, "zoo3/SUC")
    q.add_argument(
        "--format",
        choices=FORMATS,
        default="table",
        help="table (default), csv or json: every field, a column per metric",
    )
    query("show", "every field of one member, what it trained against and the budget it spent").add_argument(
        "id", metavar="MEMBER", help=MEMBER_HELP
    )
    q = query("matches", "the evaluated teams: run, generation, task, team, episodes, seeds, SUC/COL/AST/REW")
    q.add_argument("--member", default=None, help="only the matches with this member in the team")
    q.add_argument("--task", default=None, help="only matches on this task")
    sorting(q, "SUC")
    q.add_argument("--format", choices=FORMATS, default="table", help="table (default), csv or json")
    q = query("crossplay", "the member x member matrix of a metric, averaged over matches")
    q.add_argument("--task", default=None, help="only matches on this task")
    q.add_argument("--metric", default="SUC", help="SUC (default), COL, AST or REW")
    query("lineage", "a member and all its ancestors").add_argument("id", metavar="MEMBER", help=MEMBER_HELP)
    q = query("export", "write a table to CSV (members: one column per metric) or Parquet")
    q.add_argument("--format", choices=("csv", "parquet"), default="csv", help="file format (default csv)")
    tables = ("members", "matches", "generations")
    q.add_argument("--table", choices=tables, default="members", help="which table (default members)")
    q.add_argument("--out", type=Path, required=True, help="output file")
    return p


def run_registry(args: argparse.Namespace) -> int:
    """Answer one registry query; a refused one (RegistryError, a missing file) reaches the CLI's main as one line."""
    from atdrone.fileio import output_file
    from atdrone.registry_view import answer

    if args.registry_command == "export":
        output_file(args.out, (f".{args.format}",))
    print(answer(args, warn=lambda message: print(f"atdrone registry: warning: {message}", file=sys.stderr)))
    return 0
