"""What ``atdrone registry`` prints, and which registry files it reads.

Discovery. A query reads ``--db``, else ``$ATDRONE_REGISTRY``, else the registries of
the runs under ``--runs-dir`` (``runs/*/registry.db``, where ``atdrone train`` writes
them), else ``./registry.db`` when it exists. ``runs`` summarises every registry found
and ``list`` lists the members of all of them (the run column tells them apart); the
other queries need exactly one and otherwise name the candidates.

A member is named by its id (``hola-g3-0``) where one run has it, else with its run
(``hola_quick/hola-g3-0``); ``--run RUN`` picks the run's registry for the queries that
read one (:func:`atdrone.resolve.registry_of_run`).

Formatting. ``list`` is a compact table (id, run, algorithm, generation, status,
parents, eta and the zoo SUC/COL metrics present) cut to the terminal's width, or CSV
or JSON with every field and one column per metric; ``--columns`` picks member fields
and metric keys, ``--sort KEY [--desc]`` orders the rows by one of them (missing values
last). ``show`` prints every field of a member in full, one ``key: value`` line each,
then what it trained against and the budget it spent (from its checkpoint's header and
the matches it played). ``matches`` lists the evaluated teams with their scores. The printing itself:
:mod:`atdrone.registry_format`.
"""

from __future__ import annotations

import argparse
import re
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pandas as pd

from atdrone.fileio import atomic_write_bytes
from atdrone.registry import METRICS, Registry, RegistryError
from atdrone.registry_format import (
    _cell,
    _is_number,
    _is_numeric_column,
    _missing,
    format_csv,
    format_frame,
    format_member,
)
from atdrone.resolve import (
    MODEL_PREFIX,
    REGISTRY_GLOB,
    _dir,
    _none_found,
    find_member,
    locate,
    locate_one,
    registry_of_run,
    resolve,
)

FIELDS = (
    "id",
    "run",
    "algorithm",
    "generation",
    "task",
    "status",
    "parents",
    "checkpoint",
    "sha256",
    "mlflow_run_id",
    "created",
)
DEFAULT_FIELDS = ("id", "run", "algorithm", "generation", "status", "parents")
MATCH_COLUMNS = ("id", "run", "generation", "task", "team", "episodes", "seeds", *METRICS)
RUN_COLUMNS = ("run", "algorithm", "task", "generations", "members", "best", "best_by", "registry")
_ZOO_METRIC = re.compile(r"^(?!(?:train|eval|pop|perf)/)(?P<zoo>.+)/(?P<metric>SUC|COL)$")

Warn = Callable[[str], None]


@contextmanager
def _open(path: Path) -> Iterator[Registry]:
    with Registry(path, create=False) as registry:
        yield registry


def _each(paths: Sequence[Path], query: Callable[[Registry], Any], warn: Warn) -> list[Any]:
    """``query`` on each registry; with several, one that cannot be read is skipped with a warning."""
    answers = []
    for path in paths:
        try:
            with _open(path) as registry:
                answers.append(query(registry))
        except (RegistryError, OSError) as exc:
            if len(paths) == 1:
                raise
            warn(f"skipped {path}: {exc}")
    return answers


# ------------------------------------------------------------------- members
def zoo_metric_keys(metrics: Sequence[dict[str, Any]]) -> list[str]:
    """The zoo evaluation metric keys present (``zoo1/SUC``, ``zoo1/COL``, ...), by zoo then SUC before COL."""
    keys = {k for m in metrics for k in m if _ZOO_METRIC.match(k)}
    return sorted(keys, key=lambda k: (k.rsplit("/", 1)[0], k.endswith("/COL")))


def default_columns(frame: pd.DataFrame) -> list[str]:
    """``list``'s columns: the short member fields, eta when some member has it, the zoo SUC/COL metrics."""
    metrics = list(frame["metrics"])
    eta = ["eta"] if any("eta" in m for m in metrics) else []
    return [*DEFAULT_FIELDS, *eta, *zoo_metric_keys(metrics)]


def parse_columns(text: str | None) -> list[str] | None:
    """``--columns a,b,c`` as a list (None when not given); an empty list is refused."""
    if text is None:
        return None
    columns = [c.strip() for c in text.split(",") if c.strip()]
    if not columns:
        raise RegistryError("--columns needs at least one column name, e.g. --columns id,zoo1/SUC")
    return columns


def all_columns(frame: pd.DataFrame) -> list[str]:
    """Every member field, then one column per metric key present (sorted): the tidy CSV's and JSON's columns."""
    return [*FIELDS, "tags", *sorted({k for m in frame["metrics"] for k in m})]


def sort_rows(frame: pd.DataFrame, key: str | None, descending: bool = False) -> pd.DataFrame:
    """``frame`` ordered by column ``key`` (stable; missing values last either way); unchanged without a key."""
    if key is None:
        return frame
    if key not in frame.columns:
        raise RegistryError(f"cannot sort by {key!r}: choose a column ({', '.join(map(str, frame.columns))})")
    values = frame[key]
    numeric = _is_numeric_column(list(values))
    order = sorted(
        range(len(frame)),
        key=lambda i: (
            _missing(values.iloc[i]),
            (-values.iloc[i] if descending else values.iloc[i])
            if numeric and not _missing(values.iloc[i])
            else _cell(values.iloc[i]),
        ),
    )
    if descending and not numeric:  # text: reverse the present values, keep the missing ones last
        present = [i for i in order if not _missing(values.iloc[i])]
        order = present[::-1] + [i for i in order if _missing(values.iloc[i])]
    return frame.iloc[order].reset_index(drop=True)


def member_table(frame: pd.DataFrame, columns: Sequence[str] | None = None) -> pd.DataFrame:
    """The members as one row each with ``columns`` (member fields or metric keys; default :func:`default_columns`)."""
    chosen = list(columns) if columns is not None else default_columns(frame)
    known = {k for m in frame["metrics"] for k in m}
    unknown = [c for c in chosen if c not in FIELDS and c != "tags" and c not in known]
    if unknown:
        metric_keys = ", ".join(sorted(known)) or "none"
        raise RegistryError(
            f"unknown column {', '.join(unknown)}: choose member fields ({', '.join(FIELDS)}) "
            f"or metric keys ({metric_keys})"
        )
    data = {c: list(frame[c]) if c in (*FIELDS, "tags") else [m.get(c) for m in frame["metrics"]] for c in chosen}
    return pd.DataFrame(data, columns=chosen)


def best_member(frame: pd.DataFrame) -> tuple[str, str]:
    """The member with the highest zoo SUC metric (and which), else the last registered one."""
    best: tuple[float, str, str] | None = None
    for mid, metrics in zip(frame["id"], frame["metrics"], strict=True):
        for key in zoo_metric_keys([metrics]):
            value = metrics[key]
            if key.endswith("/SUC") and _is_number(value) and (best is None or value > best[0]):
                best = (float(value), mid, f"{key} {_cell(value)}")
    if best is not None:
        return best[1], best[2]
    return (str(frame["id"].iloc[-1]), "last member") if len(frame) else ("-", "")


def run_summaries(registry: Registry) -> list[dict[str, Any]]:
    """One row per run in a registry: algorithm, task, generations completed, members and best member."""
    members, generations = registry.members(), registry.generations()
    runs = list(dict.fromkeys([*members["run"], *generations["run"]])) or [registry.path.parent.name]
    rows = []
    for run in runs:
        mine = members[members["run"] == run]
        done = generations[(generations["run"] == run) & generations["finished"].notna()]
        best, best_by = best_member(mine)
        rows.append(
            {
                "run": run,
                "algorithm": ",".join(dict.fromkeys(mine["algorithm"])) or "-",
                "task": ",".join(dict.fromkeys(mine["task"])) or "-",
                "generations": len(done),
                "members": len(mine),
                "best": best,
                "best_by": best_by,
                "registry": str(registry.path),
            }
        )
    return rows


# ------------------------------------------------------------------ queries
def _members(args: argparse.Namespace, warn: Warn) -> str:
    paths = locate(args.db, args.runs_dir)
    if not paths:
        raise RegistryError(_none_found(args.runs_dir))
    frames = _each(paths, lambda r: r.members(run=args.run, task=args.task, status=args.status), warn)
    frames = [f for f in frames if len(f)]
    columns = parse_columns(args.columns)
    if not frames:
        return format_frame(pd.DataFrame(columns=columns or list(DEFAULT_FIELDS)), args.format, "(no members)")
    frame = pd.concat(frames, ignore_index=True) if len(frames) > 1 else frames[0]
    if columns is None:  # a table: the short columns; csv and json: everything, one column per metric
        columns = default_columns(frame) if args.format == "table" else all_columns(frame)
    sort = getattr(args, "sort", None)
    extra = [sort] if sort is not None and sort not in columns else []
    table = sort_rows(member_table(frame, [*columns, *extra]), sort, getattr(args, "desc", False))
    table = table.drop(columns=extra)
    return format_frame(table, args.format, "(no members)")


def match_table(matches: pd.DataFrame, member: str | None = None) -> pd.DataFrame:
    """The matches as one row each (team comma-joined in slot order), only those with ``member`` when given."""
    if member is not None:
        matches = matches[[member in team for team in matches["team"]]]
    frame = matches.reindex(columns=list(MATCH_COLUMNS)).reset_index(drop=True)
    frame["team"] = [",".join(team) for team in frame["team"]]
    frame["seeds"] = [",".join(map(str, seeds)) for seeds in frame["seeds"]]
    return frame


def _matches(args: argparse.Namespace, warn: Warn) -> str:
    member = None
    if args.member is not None:
        found, path = _find(argparse.Namespace(**{**vars(args), "id": args.member}))
        member, db = found["id"], path
    else:
        db = _one(args)
    with _open(db) as registry:
        table = match_table(registry.matches(run=None, task=args.task), member)
    return format_frame(sort_rows(table, args.sort, args.desc), args.format, "(no matches)")


def _runs(args: argparse.Namespace, warn: Warn) -> str:
    paths = locate(args.db, args.runs_dir)
    rows = [row for rows in _each(paths, run_summaries, warn) for row in rows]
    empty = f"(no registries under {_dir(args.runs_dir)}{REGISTRY_GLOB}; pass --runs-dir DIR or --db FILE)"
    return format_frame(pd.DataFrame(rows, columns=list(RUN_COLUMNS)), args.format, empty)


def _show(args: argparse.Namespace, warn: Warn) -> str:
    member, path = _find(args)
    with _open(path) as registry:
        played = match_table(registry.matches(), member["id"])
    return "\n".join([format_member(member), *training_lines(member, played, warn)])


def training_lines(member: dict[str, Any], played: pd.DataFrame, warn: Warn) -> list[str]:
    """What a member trained against (its checkpoint header's partner distribution) and the budget it spent."""
    header: dict[str, Any] = {}
    if member.get("checkpoint"):
        try:
            from atdrone.models.checkpoint import read_header

            header = read_header(member["checkpoint"])
        except Exception as exc:  # a missing or damaged file: the registry's fields are still worth showing
            warn(f"cannot read {member['checkpoint']}: {exc}")
    lines = ["trained against:"]
    partners = header.get("partners")
    if not isinstance(partners, dict):
        lines.append("  (not recorded)" if header else "  (no checkpoint header)")
    else:
        lines.append(f"  kind: {partners.get('kind', '?')}")
        probs = partners.get("probs") or []
        for key in ("profiles", "members"):
            names = partners.get(key)
            if not names:
                continue
            weighted = (
                probs is not None and len(probs) == len(names) and (key == "profiles" or "profiles" not in partners)
            )
            shown = [f"{n} ({p:.3g})" for n, p in zip(names, probs, strict=True)] if weighted else list(names)
            lines.append(f"  {key}: {', '.join(shown)}")
    lines.append("budget:")
    if "step" in header:
        lines.append(f"  training env steps: {int(header['step']):,} (seed {header.get('seed', '?')})")
    lines.append(f"  evaluation: {len(played)} match(es), {int(played['episodes'].sum()):,} episodes")
    return lines


def _one(args: argparse.Namespace) -> Path:
    """The one registry a query reads: ``--run``'s, else ``--db`` or the one found (:func:`locate_one`)."""
    run = getattr(args, "run", None)
    return registry_of_run(run, args.db, args.runs_dir) if run else locate_one(args.db, args.runs_dir)


def _find(args: argparse.Namespace) -> tuple[dict[str, Any], Path]:
    """The member ``args.id`` names and its registry: an id (``hola-g3-0``, ``hola_quick/hola-g3-0``) in any
    registry found (``--run``'s with ``--run``), or a models:/ URI or a checkpoint file that leads to a member
    (:func:`atdrone.resolve.resolve`)."""
    run = getattr(args, "run", None)
    db = registry_of_run(run, args.db, args.runs_dir) if run else args.db
    if not (args.id.startswith(MODEL_PREFIX) or Path(args.id).is_file()):
        return find_member(args.id, db, args.runs_dir)
    from atdrone.policies.base import PolicyError

    try:
        found = resolve(args.id, db=db, runs_dir=args.runs_dir)
    except PolicyError as exc:
        raise RegistryError(str(exc)) from None
    if found.member is None or found.registry is None:
        where = ", ".join(map(str, locate(args.db, args.runs_dir))) or "no registry found"
        raise RegistryError(f"{args.id!r} is a {found.kind} that no registry lists as a member ({where})")
    return found.member, found.registry


def _crossplay(args: argparse.Namespace, warn: Warn) -> str:
    with _open(_one(args)) as registry:
        matrix = registry.crossplay(task=args.task, metric=args.metric)
    if not len(matrix):
        return "(no matches)"
    with _pandas_display():
        return matrix.to_string(float_format=lambda v: f"{v:.1f}")


def _lineage(args: argparse.Namespace, warn: Warn) -> str:
    member, path = _find(args)
    with _open(path) as registry:
        frame = _known(registry.lineage, member["id"])
    with _pandas_display():
        return frame.to_string(index=False)


def _export(args: argparse.Namespace, warn: Warn) -> str:
    """Parquet as the registry stores it (JSON columns as text); CSV tidy: members with one column per metric."""
    with _open(_one(args)) as registry:
        if args.format != "csv" or args.table != "members":
            out = registry.export(args.out, format=args.format, table=args.table)
            return f"wrote {out} ({args.table}, {args.format})"
        frame = registry.members()
    table = member_table(frame, all_columns(frame)) if len(frame) else pd.DataFrame(columns=[*FIELDS, "tags"])
    out = atomic_write_bytes(Path(args.out), (format_csv(table) + "\n").encode())
    return f"wrote {out} ({args.table}, {args.format}: one column per metric)"


def _known(lookup: Callable[[str], Any], member_id: str) -> Any:
    """``lookup(member_id)``, an unknown id as RegistryError (one line at the command line)."""
    try:
        return lookup(member_id)
    except KeyError as exc:
        raise RegistryError(str(exc.args[0]) if exc.args else f"no member {member_id!r}") from exc


def _pandas_display() -> Any:
    return pd.option_context("display.max_colwidth", None, "display.max_rows", None, "display.max_columns", None)


QUERIES: dict[str, Callable[[argparse.Namespace, Warn], str]] = {
    "runs": _runs,
    "list": _members,
    "show": _show,
    "crossplay": _crossplay,
    "lineage": _lineage,
    "matches": _matches,
    "export": _export,
}


def answer(args: argparse.Namespace, warn: Warn) -> str:
    """The text ``atdrone registry QUERY`` prints; RegistryError or FileNotFoundError for a refused query."""
    return QUERIES[args.registry_command](args, warn)
