"""The population registry: members, match results and generations in one sqlite file.

Every trained policy that joins a population is a *member* (id, algorithm, generation,
parents, checkpoint path and sha256, task, status, MLflow run id, tags, metrics); every
evaluation of a team is a *match* (the member ids in slot order, task, seeds, episodes,
SUC/COL/AST/REW); every step of a run is a *generation* (started, finished, info). The
pandas views answer the usual questions: the member table, the cross-play matrix and a
member's lineage.

Storage. sqlite in WAL mode, so readers (``atdrone registry ...``, a notebook) never
block the writer and never see half a transaction. A reader (``create=False``) opens the
file read-only (``mode=ro``): it changes nothing in it, refuses a file that is not a
registry, and reads a registry it may not write. Each :class:`Registry` holds one
connection (``check_same_thread=False``) guarded by a lock, so one object may be shared
by threads; every write is one ``BEGIN IMMEDIATE`` transaction, so several Registry
objects (or processes) on one file serialise their writes instead of losing them, and a
read-modify-write such as merging metrics is atomic. JSON columns (parents, tags,
metrics, team, seeds, info) are stored as text and decoded in the views.

On Ray: :mod:`atdrone.registry_ray` (``registry_actor``, ``find_registry_actor``,
``RegistryActor``). The file itself (header checks, the read-only connection, the WAL):
:mod:`atdrone.registry_file`.
"""

from __future__ import annotations

import datetime as dt
import json
import operator
import os
import re
import secrets
import sqlite3
import threading
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pandas as pd

from atdrone.fileio import atomic_write, atomic_write_bytes
from atdrone.registry_file import (
    RegistryError,
    check_header,
    connect_read_only,
    journal_mode,
)

SCHEMA_VERSION = 1
STATUSES = ("active", "retired", "missing")
METRICS = ("SUC", "COL", "AST", "REW")  # the evaluation protocol's metrics, one column each in matches
TABLES = ("members", "matches", "generations")  # every registry has them (``runs`` came later: optional)
EXPORT_FORMATS = ("csv", "parquet")
REGISTRY_NAMESPACE = "atdrone"
DEFAULT_ACTOR_NAME = "registry"
DEFAULT_PATH = "registry.db"
ENV_VAR = "ATDRONE_REGISTRY"

_SCHEMA = (
    "CREATE TABLE IF NOT EXISTS schema_version (version INTEGER NOT NULL)",
    """CREATE TABLE IF NOT EXISTS members (
        id TEXT PRIMARY KEY,
        run TEXT NOT NULL,
        algorithm TEXT NOT NULL,
        generation INTEGER NOT NULL,
        parents TEXT NOT NULL DEFAULT '[]',
        checkpoint TEXT,
        sha256 TEXT,
        task TEXT NOT NULL,
        status TEXT NOT NULL DEFAULT 'active' CHECK (status IN ('active', 'retired', 'missing')),
        mlflow_run_id TEXT,
        tags TEXT NOT NULL DEFAULT '{}',
        metrics TEXT NOT NULL DEFAULT '{}',
        created TEXT NOT NULL
    )""",
    "CREATE INDEX IF NOT EXISTS members_run ON members (run, generation)",
    "CREATE INDEX IF NOT EXISTS members_task ON members (task)",
    """CREATE TABLE IF NOT EXISTS matches (
        id INTEGER PRIMARY KEY AUTOINCREMENT,
        run TEXT NOT NULL,
        generation INTEGER NOT NULL,
        team TEXT NOT NULL,
        task TEXT NOT NULL,
        seeds TEXT NOT NULL,
        episodes INTEGER NOT NULL,
        SUC REAL, COL REAL, AST REAL, REW REAL,
        created TEXT NOT NULL
    )""",
    "CREATE INDEX IF NOT EXISTS matches_run ON matches (run, generation)",
    "CREATE INDEX IF NOT EXISTS matches_task ON matches (task)",
    """CREATE TABLE IF NOT EXISTS generations (
        run TEXT NOT NULL,
        idx INTEGER NOT NULL,
        started TEXT,
        finished TEXT,
        info TEXT NOT NULL DEFAULT '{}',
        PRIMARY KEY (run, idx)
    )""",
    # the run (by its identifier) a service registry belongs to: one row, written by the run's first driver
    "CREATE TABLE IF NOT EXISTS runs (run_id TEXT PRIMARY KEY, name TEXT NOT NULL, created TEXT NOT NULL)",
)
# what makes two registrations of one member id the same (add_member is idempotent on them)
_MEMBER_KEY = ("run", "algorithm", "generation", "task", "parents", "checkpoint", "sha256")
# a match's natural key: a team played on a task with these seeds, in one generation of one run
_MATCH_KEY = ("run", "generation", "team", "task", "seeds")
_JSON_COLUMNS = {
    "members": ("parents", "tags", "metrics"),
    "matches": ("team", "seeds"),
    "generations": ("info",),
}


RUN_RELATIVE = "./"  # a stored checkpoint path relative to the registry's folder


def default_path() -> Path:
    """Where the registry lives unless told: ``$ATDRONE_REGISTRY``, else ``./registry.db``."""
    return Path(os.environ.get(ENV_VAR) or DEFAULT_PATH)


def member_id(algorithm: str, generation: int, suffix: object) -> str:
    """A member id ``<algorithm slug>-g<generation>-<suffix>``, e.g. ``hola-g3-0``."""
    slug = re.sub(r"[^a-z0-9]+", "-", algorithm.lower()).strip("-") or "member"
    return f"{slug}-g{generation}-{suffix}"


def new_member_id(algorithm: str, generation: int) -> str:
    """A fresh member id such as ``hola-g3-a1b2c3`` (6 random hex digits as the suffix)."""
    return member_id(algorithm, generation, secrets.token_hex(3))


def _now() -> str:
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")


def _json_default(value: Any) -> Any:
    """numpy scalars and arrays (metrics straight from a learner) as plain JSON values."""
    for convert in ("tolist", "item"):  # numpy: tolist() is the value for scalars and arrays alike
        if hasattr(value, convert):
            return getattr(value, convert)()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def _dumps(value: Any) -> str:
    return json.dumps(value, sort_keys=True, default=_json_default)


def _check_int(name: str, value: Any, minimum: int = 0) -> int:
    """``value`` as a Python int (numpy integers accepted), refusing bools, floats and values below ``minimum``."""
    try:
        number = operator.index(value)
    except TypeError:
        number = None
    if isinstance(value, bool) or number is None or number < minimum:
        raise RegistryError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return number


def _check_text(name: str, value: Any) -> str:
    if not isinstance(value, str) or not value:
        raise RegistryError(f"{name} must be a non-empty string, got {value!r}")
    return value


def _check_dict(name: str, value: Any) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise RegistryError(f"{name} must be a dict, got {type(value).__name__}")
    return dict(value)


def _check_ids(name: str, value: Any) -> list[str]:
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise RegistryError(f"{name} must be a list of member ids, got {value!r}")
    for v in value:
        _check_text(f"each of {name}", v)
    return list(value)


class Registry:
    """The population registry on one sqlite file (created with its schema when missing).

    Arguments:
        path: the sqlite file (default :func:`default_path`).
        create: make the file and schema when missing (the writer, e.g. the Ray actor).
            With ``False`` the file is opened read-only and never written: a missing file
            raises FileNotFoundError; an empty, non-sqlite or foreign sqlite file raises
            RegistryError; the write methods raise RegistryError (what the CLI wants).

    One object holds one connection and a lock, so it may be shared between threads;
    close it with :meth:`close` or use it as a context manager.
    """

    def __init__(self, path: str | os.PathLike[str] | None = None, *, create: bool = True) -> None:
        self.path = Path(path) if path is not None else default_path()
        self.read_only = not create
        self._lock = threading.RLock()
        if create:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            check_header(self.path, empty_ok=True)
            self._conn = sqlite3.connect(self.path, timeout=30.0, isolation_level=None, check_same_thread=False)
        else:
            self._conn = connect_read_only(self.path)
        try:
            if create:
                self.journal_mode = str(self._conn.execute("PRAGMA journal_mode=WAL").fetchone()[0]).lower()
                self._init_schema()
            else:
                self.journal_mode = journal_mode(self._conn, self.path)
                self._check_schema()
        except BaseException:
            self._conn.close()
            raise

    # ------------------------------------------------------------ plumbing
    def _init_schema(self) -> None:
        """Create the tables when missing (the writer's path) and check the schema version."""
        with self._write() as conn:
            for statement in _SCHEMA:
                conn.execute(statement)
            row = conn.execute("SELECT MAX(version) FROM schema_version").fetchone()
            if row[0] is None:
                conn.execute("INSERT INTO schema_version (version) VALUES (?)", (SCHEMA_VERSION,))
            else:
                self._check_version(row[0])

    def _check_schema(self) -> None:
        """Refuse, without writing, a file that lacks the registry's tables or has a newer schema."""
        try:
            with self._lock:
                names = {r[0] for r in self._conn.execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
                has_version = "schema_version" in names
                version = (
                    self._conn.execute("SELECT MAX(version) FROM schema_version").fetchone()[0] if has_version else None
                )
        except sqlite3.DatabaseError as exc:
            raise RegistryError(f"{self.path} cannot be read as an atdrone registry: {exc}") from exc
        if not has_version:
            found = ", ".join(sorted(names)) or "none"
            raise RegistryError(f"{self.path} is not an atdrone registry (no schema_version table; tables: {found})")
        missing = [t for t in TABLES if t not in names]
        if missing:
            raise RegistryError(f"{self.path} is not a complete atdrone registry (no table {', '.join(missing)})")
        self._check_version(version)

    def _check_version(self, version: Any) -> None:
        if not isinstance(version, int):
            raise RegistryError(f"{self.path} has no valid registry schema version (got {version!r})")
        if version > SCHEMA_VERSION:
            raise RegistryError(
                f"{self.path} has registry schema v{version}, this atdrone reads up to v{SCHEMA_VERSION}"
            )

    @contextmanager
    def _write(self) -> Iterator[sqlite3.Connection]:
        """One write transaction: taken at once (BEGIN IMMEDIATE), committed or rolled back whole."""
        if self.read_only:
            raise RegistryError(f"the registry at {self.path} was opened read-only (create=False)")
        with self._lock, self._conn:
            self._conn.execute("BEGIN IMMEDIATE")
            yield self._conn

    def _query(self, sql: str, params: Sequence[Any] = ()) -> pd.DataFrame:
        with self._lock:
            return pd.read_sql_query(sql, self._conn, params=list(params))

    def _decode(self, frame: pd.DataFrame, table: str) -> pd.DataFrame:
        """Decode the JSON columns of rows of ``table``; a malformed row raises RegistryError naming it."""
        keys = _row_keys(frame, table)
        for col in _JSON_COLUMNS[table]:
            frame[col] = [self._json(text, table, key, col) for key, text in zip(keys, frame[col], strict=True)]
        if table == "members":
            frame["checkpoint"] = [self._full_path(text) for text in frame["checkpoint"]]
        return frame

    # Paths inside the registry's folder (the run directory) are stored relative to it, as
    # "./members/x.pt", and read back under wherever the folder is now: a run directory can
    # be moved, copied or mounted elsewhere. Other paths are kept as given.
    def _stored_path(self, path: str | os.PathLike[str]) -> str:
        folder, given = self.path.parent.resolve(), Path(path)
        if given.is_absolute() and given.resolve().is_relative_to(folder):
            return f"{RUN_RELATIVE}{given.resolve().relative_to(folder).as_posix()}"
        return str(path)

    def _full_path(self, text: Any) -> Any:
        if isinstance(text, str) and text.startswith(RUN_RELATIVE):
            return str(self.path.parent.resolve() / text.removeprefix(RUN_RELATIVE))
        return text

    def _json(self, text: Any, table: str, key: str, column: str) -> Any:
        """One JSON cell decoded and checked for its type (list of ids, object, list of ints)."""
        return _load_json(text, f"{self.path}: {table} row {key}: {column}", column)

    @staticmethod
    def _where(**filters: Any) -> tuple[str, list[Any]]:
        items = [(k, v) for k, v in filters.items() if v is not None]
        if not items:
            return "", []
        return " WHERE " + " AND ".join(f"{k} = ?" for k, _ in items), [v for _, v in items]

    def db_path(self) -> str:
        """The absolute path of the sqlite file (a method, so a Ray actor handle can answer it)."""
        return str(self.path.resolve())

    def owners(self) -> dict[str, str]:
        """The runs this registry belongs to, ``{run_id: name}`` (empty for a registry no run has claimed)."""
        with self._lock:
            try:
                rows = self._conn.execute("SELECT run_id, name FROM runs ORDER BY created").fetchall()
            except sqlite3.OperationalError:  # a registry from before the table existed
                return {}
        return {str(run_id): str(name) for run_id, name in rows}

    def claim(self, run_id: str, name: str) -> None:
        """Make this the registry of run ``run_id`` (named ``name``); RegistryError when another run has it."""
        _check_text("run_id", run_id)
        with self._write() as conn:
            rows = conn.execute("SELECT run_id, name FROM runs").fetchall()
            others = [f"{n} (run id {r})" for r, n in rows if r != run_id]
            if others:
                raise RegistryError(
                    f"{self.path} is the registry of {', '.join(others)}, not of {name} (run id {run_id})"
                )
            if not rows:
                conn.execute("INSERT INTO runs (run_id, name, created) VALUES (?, ?, ?)", (run_id, name, _now()))

    def checkpoint(self) -> bool:
        """Fold the write-ahead log back into the file (``wal_checkpoint(TRUNCATE)``), so the file alone holds
        every commit; False when a reader kept part of it (the rest is folded back by the next checkpoint)."""
        if self.read_only:
            return False
        with self._lock:
            busy = self._conn.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()[0]
        return not busy

    def close(self) -> None:
        """Close the connection; the object is unusable afterwards."""
        with self._lock:
            self._conn.close()

    def __enter__(self) -> Registry:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------- members
    def add_member(
        self,
        *,
        run: str,
        algorithm: str,
        generation: int,
        task: str,
        parents: Sequence[str] = (),
        checkpoint: str | os.PathLike[str] | None = None,
        sha256: str | None = None,
        status: str = "active",
        mlflow_run_id: str | None = None,
        tags: Mapping[str, Any] | None = None,
        metrics: Mapping[str, Any] | None = None,
        member_id: str | None = None,
    ) -> str:
        """Register a member and return its id (generated by :func:`new_member_id` when not given).

        Parents must already be registered, so lineage has no dangling links or cycles.
        Idempotent on ``member_id``: registering an id again with the same fields
        (:meth:`_same_member`) returns it and changes nothing; with other fields it is
        refused with RegistryError.
        """
        _check_text("run", run)
        _check_text("algorithm", algorithm)
        generation = _check_int("generation", generation)
        _check_text("task", task)
        parent_ids = _check_ids("parents", parents)
        if status not in STATUSES:
            raise RegistryError(f"status must be one of {STATUSES}, got {status!r}")
        row = {
            "run": run,
            "algorithm": algorithm,
            "generation": generation,
            "parents": _dumps(parent_ids),
            "checkpoint": None if checkpoint is None else self._stored_path(checkpoint),
            "sha256": sha256,
            "task": task,
            "status": status,
            "mlflow_run_id": mlflow_run_id,
            "tags": _dumps(_check_dict("tags", tags or {})),
            "metrics": _dumps(_check_dict("metrics", metrics or {})),
            "created": _now(),
        }
        with self._write() as conn:
            missing = [p for p in parent_ids if not conn.execute("SELECT 1 FROM members WHERE id = ?", (p,)).fetchone()]
            if missing:
                raise RegistryError(f"parents {missing} are not registered members")
            if member_id is None:
                member_id = new_member_id(algorithm, generation)
                while conn.execute("SELECT 1 FROM members WHERE id = ?", (member_id,)).fetchone():
                    member_id = new_member_id(algorithm, generation)
            _check_text("member_id", member_id)
            if self._same_member(conn, member_id, row):
                return member_id  # a replayed registration (a retried call): already done
            cols = ["id", *row]
            conn.execute(
                f"INSERT INTO members ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})",
                [member_id, *row.values()],
            )
        return member_id

    def _same_member(self, conn: sqlite3.Connection, member_id: str, row: Mapping[str, Any]) -> bool:
        """Whether ``member_id`` is registered already as ``row`` (False: not registered; RegistryError: differently).

        The same registration is its identity fields (run, algorithm, generation, task,
        parents, checkpoint, sha256) equal and its tags and metrics still there with the
        same values (updates merge keys into them; status and MLflow run id may change).
        """
        found = conn.execute(f"SELECT {', '.join(_MEMBER_KEY)}, tags, metrics FROM members WHERE id = ?", (member_id,))
        stored = found.fetchone()
        if stored is None:
            return False
        old = dict(zip((*_MEMBER_KEY, "tags", "metrics"), stored, strict=True))
        differ = [k for k in _MEMBER_KEY if old[k] != row[k]]
        for key in ("tags", "metrics"):
            kept = self._json(old[key], "members", repr(member_id), key)
            if any(k not in kept or kept[k] != v for k, v in json.loads(row[key]).items()):
                differ.append(key)
        if differ:
            raise RegistryError(
                f"member {member_id!r} is already registered with other {', '.join(differ)}; ids are unique"
            )
        return True

    def add_checkpoint(self, checkpoint: str | os.PathLike[str], *, run: str, generation: int, **fields: Any) -> str:
        """Register the policy in a checkpoint file: task, algorithm and sha256 come from its header.

        Other keyword arguments go to :meth:`add_member`. Imports torch (through
        :mod:`atdrone.models.checkpoint`), which verifies the file's sha256 on the way.
        """
        from atdrone.models.checkpoint import read_header

        header = read_header(Path(checkpoint))
        fields.setdefault("task", header["task"])
        fields.setdefault("algorithm", header.get("algorithm") or "unknown")
        return self.add_member(run=run, generation=generation, checkpoint=checkpoint, sha256=header["sha256"], **fields)

    def update_member(
        self,
        member_id: str,
        *,
        status: str | None = None,
        metrics: Mapping[str, Any] | None = None,
        tags: Mapping[str, Any] | None = None,
        mlflow_run_id: str | None = None,
        checkpoint: str | os.PathLike[str] | None = None,
        sha256: str | None = None,
    ) -> dict[str, Any]:
        """Change a member and return it: metrics and tags are merged key by key, the rest replaced.

        Raises KeyError for an unknown id and RegistryError for a bad status.
        """
        if status is not None and status not in STATUSES:
            raise RegistryError(f"status must be one of {STATUSES}, got {status!r}")
        with self._write() as conn:
            row = conn.execute("SELECT metrics, tags FROM members WHERE id = ?", (member_id,)).fetchone()
            if row is None:
                raise KeyError(f"no member {member_id!r} in the registry at {self.path}")
            changes: dict[str, Any] = {}
            if metrics is not None:
                old_metrics = self._json(row[0], "members", repr(member_id), "metrics")
                changes["metrics"] = _dumps({**old_metrics, **_check_dict("metrics", metrics)})
            if tags is not None:
                old_tags = self._json(row[1], "members", repr(member_id), "tags")
                changes["tags"] = _dumps({**old_tags, **_check_dict("tags", tags)})
            for key, value in (("status", status), ("mlflow_run_id", mlflow_run_id), ("sha256", sha256)):
                if value is not None:
                    changes[key] = value
            if checkpoint is not None:
                changes["checkpoint"] = self._stored_path(checkpoint)
            if changes:
                assignments = ", ".join(f"{k} = ?" for k in changes)
                conn.execute(f"UPDATE members SET {assignments} WHERE id = ?", [*changes.values(), member_id])
        return self.member(member_id)

    def member(self, member_id: str) -> dict[str, Any]:
        """One member as a dict (JSON fields decoded); KeyError when the id is unknown."""
        frame = self._decode(self._query("SELECT * FROM members WHERE id = ?", (member_id,)), "members")
        if frame.empty:
            raise KeyError(f"no member {member_id!r} in the registry at {self.path}")
        return {k: (None if _isnull(v) else v) for k, v in frame.iloc[0].to_dict().items()}

    def members(self, run: str | None = None, task: str | None = None, status: str | None = None) -> pd.DataFrame:
        """The members (in registration order), optionally filtered by run, task and status."""
        if status is not None and status not in STATUSES:
            raise RegistryError(f"status must be one of {', '.join(STATUSES)}, got {status!r}")
        where, params = self._where(run=run, task=task, status=status)
        return self._decode(self._query(f"SELECT * FROM members{where} ORDER BY rowid", params), "members")

    # ------------------------------------------------------------- matches
    def add_match(
        self,
        team: Sequence[str],
        task: str,
        run: str,
        generation: int,
        seeds: Sequence[int],
        episodes: int,
        metrics: Mapping[str, float],
    ) -> int:
        """Record one evaluated team (member ids in slot order) and return the match id.

        ``metrics`` must hold SUC, COL, AST and REW (other keys are ignored); AST may be
        NaN when no episode succeeded, and is stored as NULL. Idempotent on the natural key
        (run, generation, team, task, seeds): the same match recorded again returns the
        first one's id; the key with another episode count or other metrics is refused
        with RegistryError.
        """
        team_ids = _check_ids("team", team)
        if not team_ids:
            raise RegistryError("team must name at least one member")
        _check_text("task", task)
        _check_text("run", run)
        generation = _check_int("generation", generation)
        episodes = _check_int("episodes", episodes, minimum=1)
        if isinstance(seeds, str) or not isinstance(seeds, Sequence):
            raise RegistryError(f"seeds must be a list of integers, got {seeds!r}")
        seed_list = [_check_int("each seed", s) for s in seeds]
        missing = [m for m in METRICS if m not in metrics]
        if missing:
            raise RegistryError(f"match metrics lack {missing} (need {list(METRICS)})")
        values = [float(metrics[m]) for m in METRICS]
        key = [run, generation, _dumps(team_ids), task, _dumps(seed_list)]
        with self._write() as conn:
            where = " AND ".join(f"{k} = ?" for k in _MATCH_KEY)
            found = conn.execute(f"SELECT id, episodes, {', '.join(METRICS)} FROM matches WHERE {where}", key)
            same = found.fetchone()
            if same is not None:  # a replayed record (a retried call) is the one recorded; another result is not
                if same[1] != episodes or not all(_same_value(a, b) for a, b in zip(same[2:], values, strict=True)):
                    raise RegistryError(
                        f"match {same[0]} already records team {team_ids} with seeds {seed_list} in generation "
                        f"{generation} of run {run!r} with other results; a match is recorded once"
                    )
                return int(same[0])
            cur = conn.execute(
                "INSERT INTO matches (run, generation, team, task, seeds, episodes, SUC, COL, AST, REW, created)"
                " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)",
                [run, generation, _dumps(team_ids), task, _dumps(seed_list), episodes, *values, _now()],
            )
            match_id = cur.lastrowid
        assert match_id is not None
        return match_id

    def matches(self, run: str | None = None, task: str | None = None) -> pd.DataFrame:
        """The match results (in recording order), optionally filtered by run and task."""
        where, params = self._where(run=run, task=task)
        return self._decode(self._query(f"SELECT * FROM matches{where} ORDER BY id", params), "matches")

    # --------------------------------------------------------- generations
    def start_generation(self, run: str, idx: int, info: Mapping[str, Any] | None = None) -> None:
        """Mark generation ``idx`` of ``run`` started (again: a restart clears ``finished``)."""
        _check_text("run", run)
        idx = _check_int("idx", idx)
        with self._write() as conn:
            conn.execute(
                "INSERT INTO generations (run, idx, started, finished, info) VALUES (?, ?, ?, NULL, ?) ON CONFLICT"
                " (run, idx) DO UPDATE SET started = excluded.started, finished = NULL, info = excluded.info",
                (run, idx, _now(), _dumps(_check_dict("info", info or {}))),
            )

    def finish_generation(self, run: str, idx: int, info: Mapping[str, Any] | None = None) -> None:
        """Mark generation ``idx`` of ``run`` finished, merging ``info`` into what start recorded."""
        idx = _check_int("idx", idx)
        with self._write() as conn:
            row = conn.execute("SELECT info FROM generations WHERE run = ? AND idx = ?", (run, idx)).fetchone()
            if row is None:
                raise RegistryError(f"generation {idx} of run {run!r} was never started")
            old_info = self._json(row[0], "generations", f"{run}/{idx}", "info")
            merged = {**old_info, **_check_dict("info", info or {})}
            conn.execute(
                "UPDATE generations SET finished = ?, info = ? WHERE run = ? AND idx = ?",
                (_now(), _dumps(merged), run, idx),
            )

    def discard_generations(self, run: str, start: int) -> int:
        """Delete ``run``'s members, matches and generation rows from generation ``start`` on.

        A resumed service run calls this for the generation it repeats, so a generation
        killed half-way leaves no rows behind; match ids continue from the highest one
        kept, so the repeated generation's rows come out exactly as the first time.
        Returns the number of rows deleted.
        """
        _check_text("run", run)
        start = _check_int("start", start)
        with self._write() as conn:
            deleted = 0
            for table, column in (("members", "generation"), ("matches", "generation"), ("generations", "idx")):
                deleted += conn.execute(f"DELETE FROM {table} WHERE run = ? AND {column} >= ?", (run, start)).rowcount
            conn.execute(
                "UPDATE sqlite_sequence SET seq = (SELECT COALESCE(MAX(id), 0) FROM matches) WHERE name = 'matches'"
            )
        return deleted

    def generations(self, run: str | None = None) -> pd.DataFrame:
        """The generations, by run and index; ``finished`` is None for one still running (or interrupted)."""
        where, params = self._where(run=run)
        return self._decode(self._query(f"SELECT * FROM generations{where} ORDER BY run, idx", params), "generations")

    def last_completed_generation(self, run: str) -> int | None:
        """The highest finished generation index of ``run``, or None when none has finished."""
        with self._lock:
            row = self._conn.execute(
                "SELECT MAX(idx) FROM generations WHERE run = ? AND finished IS NOT NULL", (run,)
            ).fetchone()
        return None if row[0] is None else int(row[0])

    # --------------------------------------------------------------- views
    def crossplay(self, task: str | None = None, metric: str = "SUC") -> pd.DataFrame:
        """The member x member matrix of ``metric``, averaged over matches (each match counts once).

        Cell (a, b), a != b: the mean over matches whose team contains both a and b. Diagonal
        (a, a): the mean over matches whose team is only a (self-play). NaN where no match
        qualifies. Rows and columns: every id seen in a team, registered members first in
        registration order, then any other ids sorted.
        """
        if metric not in METRICS:
            raise RegistryError(f"metric must be one of {METRICS}, got {metric!r}")
        matches = self.matches(task=task)
        if matches.empty:
            return pd.DataFrame(index=pd.Index([], name="member"), columns=pd.Index([], name="partner"), dtype=float)
        order = self._id_order(matches)
        slots = pd.DataFrame(
            {"match": matches["id"], "member": [sorted(set(t)) for t in matches["team"]], "value": matches[metric]}
        )
        sizes = slots["member"].map(len)
        slots = slots.explode("member")
        pairs = slots.merge(slots[["match", "member"]].rename(columns={"member": "partner"}), on="match")
        pairs = pairs[pairs["member"] != pairs["partner"]]
        solo = slots[slots["match"].isin(matches["id"][sizes.to_numpy() == 1])].assign(partner=lambda f: f["member"])
        cells = pd.concat([pairs, solo]).astype({"value": float}).groupby(["member", "partner"])["value"].mean()
        matrix = cells.unstack("partner").reindex(index=order, columns=order)
        matrix.index.name, matrix.columns.name = "member", "partner"
        return matrix

    def _id_order(self, matches: pd.DataFrame) -> list[str]:
        seen = {m for team in matches["team"] for m in team}
        registered = [m for m in self.members()["id"] if m in seen]
        return registered + sorted(seen - set(registered))

    def lineage(self, member_id: str) -> pd.DataFrame:
        """The member and all its ancestors (through ``parents``), nearest first.

        Columns: id, depth (0 for the member, 1 for its parents, ...; the shortest path
        when an ancestor is reached twice), generation, algorithm, run, parents, status.
        """
        self.member(member_id)  # KeyError for an unknown id
        depth = {member_id: 0}
        frontier = [member_id]
        while frontier:
            marks = ", ".join("?" * len(frontier))
            rows = self._query(f"SELECT id, parents FROM members WHERE id IN ({marks})", frontier)
            nxt = []
            for child, parents in zip(rows["id"], rows["parents"], strict=True):
                for parent in self._json(parents, "members", repr(child), "parents"):
                    if parent not in depth:
                        depth[parent] = depth[child] + 1
                        nxt.append(parent)
            frontier = nxt
        ids = list(depth)
        marks = ", ".join("?" * len(ids))
        frame = self._decode(self._query(f"SELECT * FROM members WHERE id IN ({marks})", ids), "members")
        frame.insert(1, "depth", frame["id"].map(depth))
        cols = ["id", "depth", "generation", "algorithm", "run", "parents", "status"]
        return frame[cols].sort_values(["depth", "generation", "id"], ascending=[True, False, True], ignore_index=True)

    # -------------------------------------------------------------- export
    def export(self, path: str | os.PathLike[str], format: str = "csv", table: str = "members") -> Path:
        """Write one table to ``path`` as CSV or Parquet, whole or not at all (temp file + rename).

        JSON columns are written as JSON text, so the file round-trips without loss.
        Returns the path.
        """
        if format not in EXPORT_FORMATS:
            raise RegistryError(f"format must be one of {EXPORT_FORMATS}, got {format!r}")
        if table not in TABLES:
            raise RegistryError(f"table must be one of {TABLES}, got {table!r}")
        order = "id" if table == "matches" else ("rowid" if table == "members" else "run, idx")
        frame = self._query(f"SELECT * FROM {table} ORDER BY {order}")
        out = Path(path)
        if format == "csv":
            atomic_write_bytes(out, frame.to_csv(index=False).encode())
        else:
            atomic_write(out, lambda f: frame.to_parquet(f, index=False))
        return out


_JSON_TYPES: dict[str, tuple[type, str]] = {
    "parents": (list, "list of member ids"),
    "team": (list, "list of member ids"),
    "seeds": (list, "list of integers"),
    "tags": (dict, "object"),
    "metrics": (dict, "object"),
    "info": (dict, "object"),
}


def _row_keys(frame: pd.DataFrame, table: str) -> list[str]:
    """How error messages name the rows of ``table``: member id, match id, ``run/idx``."""
    if table == "generations":
        return [f"{run}/{idx}" for run, idx in zip(frame["run"], frame["idx"], strict=True)]
    return [repr(key) for key in frame["id"]]


def _load_json(text: Any, where: str, column: str) -> Any:
    """Decode one JSON column and check its type, or raise RegistryError naming ``where``."""
    if not isinstance(text, str):
        raise RegistryError(f"malformed registry row: {where} is {text!r}, not JSON text")
    try:
        value = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RegistryError(f"malformed registry row: {where} is not valid JSON ({exc}): {text[:60]!r}") from exc
    kind, name = _JSON_TYPES[column]
    items_ok = not isinstance(value, list) or all(
        isinstance(v, int) if column == "seeds" else isinstance(v, str) for v in value
    )
    if not isinstance(value, kind) or not items_ok:
        raise RegistryError(f"malformed registry row: {where} is not a JSON {name}: {text[:60]!r}")
    return value


def _same_value(stored: Any, value: float) -> bool:
    """A metric as stored (NaN as NULL) equals ``value``."""
    return (_isnull(stored) and value != value) or stored == value


def _isnull(value: Any) -> bool:
    return value is None or (isinstance(value, float) and value != value)
