"""Files written whole or not at all: write to a temp file beside the target, then rename.

A reader (or a crash half-way) never sees a half-written GIF, JSON or CSV: the new
content appears under its name in one ``os.replace``. The file is fsynced before the
rename and its directory after it, so once the call returns the new content survives a
power loss too (not only a killed process).
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import IO, Any


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path: str | os.PathLike[str], write: Callable[[IO[bytes]], Any]) -> Path:
    """Write through ``write(file)`` to a temp file beside ``path``, then move it into place."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the file the usual mode
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    fsync_dir(path.parent)
    return path


def fsync_dir(folder: str | os.PathLike[str]) -> None:
    """Make a rename (or creation) in ``folder`` durable: fsync the directory itself (POSIX; a no-op where
    directories cannot be opened, as on Windows)."""
    try:
        fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def atomic_write_text(path: str | os.PathLike[str], text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_bytes(path: str | os.PathLike[str], data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically."""
    return atomic_write(path, lambda f: f.write(data))


def user_cache(*parts: str) -> Path:
    """A folder of atdrone's cache: ``$ATDRONE_CACHE`` or ``$XDG_CACHE_HOME/atdrone`` (``~/.cache/atdrone``)."""
    if os.environ.get("ATDRONE_CACHE"):
        return Path(os.environ["ATDRONE_CACHE"]).joinpath(*parts)
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache", "atdrone", *parts)


def output_file(path: Path, suffixes: tuple[str, ...], flag: str = "--out") -> Path:
    """``path`` if it names a file of one of ``suffixes`` in a folder that exists; UserError otherwise.

    An output file is never written under another format's name, and a mistyped folder
    is not created silently.
    """
    from atdrone.errors import UserError

    if path.suffix.lower() not in suffixes:
        raise UserError(f"{flag} {path}: the file name must end in {' or '.join(suffixes)}")
    if path.is_dir():
        raise UserError(f"{flag} {path}: is a folder; give a file name")
    parent = path.parent if str(path.parent) else Path(".")
    if not parent.is_dir():
        raise UserError(f"{flag} {path}: no folder {str(parent)!r} (create it first)")
    return path
