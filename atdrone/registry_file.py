"""The registry's sqlite file as a file: its header checked, opened read-only without writing it, its WAL.

A reader opens the file with ``mode=ro`` so that it changes nothing in it; a WAL-mode file
in a folder the reader may not write (where no ``-shm`` can be made) is opened
``immutable`` instead, when no ``-wal`` file holds commits not yet folded back.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path

from atdrone.errors import UserError

SQLITE_MAGIC = b"SQLite format 3\x00"


class RegistryError(UserError, ValueError):
    """A request the registry refuses: a duplicate id, a bad field, a file that is not a registry."""


def check_header(path: Path, *, empty_ok: bool) -> None:
    """Refuse a file that is not a sqlite database (and, unless ``empty_ok``, an empty file)."""
    if not path.is_file():
        return
    with path.open("rb") as f:
        head = f.read(len(SQLITE_MAGIC))
    if not head and not empty_ok:
        raise RegistryError(f"{path} is an empty file, not an atdrone registry")
    if head and head != SQLITE_MAGIC:
        raise RegistryError(f"{path} is not a sqlite database, so not an atdrone registry")


def connect_read_only(path: Path) -> sqlite3.Connection:
    """A read-only connection (``mode=ro``) to an existing sqlite file; it never writes the file.

    A WAL-mode file in a folder the reader may not write (so no ``-shm`` can be made) is
    opened ``immutable`` instead, provided no ``-wal`` file holds commits not yet merged
    (none can: nobody could write one there).
    """
    if not path.is_file():
        raise FileNotFoundError(f"no registry at {path}")
    check_header(path, empty_ok=False)
    uri = path.resolve().as_uri() + "?mode=ro"
    try:
        return probe(uri)
    except sqlite3.OperationalError as exc:
        if not is_wal(path) or wal_has_data(path):
            raise RegistryError(f"cannot read the registry at {path}: {exc}") from exc
        first = exc
    except sqlite3.DatabaseError as exc:
        raise RegistryError(f"{path} cannot be read as an atdrone registry: {exc}") from exc
    try:
        return probe(uri + "&immutable=1")
    except sqlite3.DatabaseError as exc:
        raise RegistryError(f"cannot read the registry at {path}: {first}") from exc


def probe(uri: str) -> sqlite3.Connection:
    """Connect to ``uri`` and read the schema once (sqlite opens lazily), closing it on failure."""
    conn = sqlite3.connect(uri, uri=True, timeout=30.0, isolation_level=None, check_same_thread=False)
    try:
        conn.execute("SELECT COUNT(*) FROM sqlite_master").fetchone()
    except BaseException:
        conn.close()
        raise
    return conn


def is_wal(path: Path) -> bool:
    """Whether the file's header says WAL mode (bytes 18 and 19 are 2)."""
    with path.open("rb") as f:
        header = f.read(20)
    return len(header) == 20 and header[18] == 2


def wal_has_data(path: Path) -> bool:
    wal = path.with_name(path.name + "-wal")
    return wal.is_file() and wal.stat().st_size > 0


def journal_mode(conn: sqlite3.Connection, path: Path) -> str:
    """The journal mode as stored, read without changing it (an immutable connection reports none)."""
    return "wal" if is_wal(path) else str(conn.execute("PRAGMA journal_mode").fetchone()[0]).lower()
