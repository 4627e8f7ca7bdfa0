"""A run directory's identity: what a resume must keep, and the saved state read back safely.

A resumed run continues the population it finds, so it must be the same experiment:
:func:`check_resume` compares the run's saved ``config.json`` with the config given to
resume it and refuses any difference outside the fields a resume may change (more
generations, another final evaluation, other resources). Both the population service
and the local trainer use it.

A run is one driver's at a time: :class:`RunLock` holds an exclusive lock (``flock``) on a
file beside it for the driver's life, and a second driver is refused with a line naming
the holder. The lock goes with the process that holds it, however it ends (a SIGKILL
too), so a killed run is never locked out of its resume.
"""

from __future__ import annotations

import datetime as dt
import fcntl
import json
import os
import socket
import uuid
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from types import TracebackType
from typing import Any

from atdrone.errors import UserError


class RunError(UserError, RuntimeError):
    """A run directory that cannot be started or resumed as asked."""


class RunExistsError(RunError, FileExistsError):
    """A run directory that already holds a run, started again without ``--resume``."""


class RunBusyError(RunError):
    """A run that another live driver holds."""


def new_run_id() -> str:
    """A run's identifier, made once at its birth: 16 random hex digits."""
    return uuid.uuid4().hex[:16]


class RunLock:
    """An exclusive lock on ``path`` (a lock file, made when missing) naming ``run``, held until :meth:`release`.

    The file holds the holder's pid, host and start time, which a refused driver reports. It is
    never deleted (a lock on a file that a second driver just re-created would lock nothing)."""

    def __init__(self, path: Path, run: str) -> None:
        self.path, self.run = Path(path), run
        self._fd: int | None = None

    def acquire(self) -> RunLock:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip() or "another process"
            os.close(fd)
            raise RunBusyError(
                f"{self.run} is in use by {holder}: one driver per run; wait for it to end (or stop it) before resuming"
            ) from None
        except BaseException:
            os.close(fd)
            raise
        started = dt.datetime.now(dt.UTC).isoformat(timespec="seconds")
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"driver pid {os.getpid()} on {socket.gethostname()} since {started}\n".encode(), 0)
        self._fd = fd
        return self

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing the descriptor drops the lock
            self._fd = None

    def __enter__(self) -> RunLock:
        return self.acquire()

    def __exit__(self, kind: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None) -> None:
        self.release()


def refuse_existing(run_dir: Path) -> None:
    """The one answer to starting a run over one that exists."""
    raise RunExistsError(f"{run_dir} holds a run: pass --resume to continue it, or pick another name")


def read_json(path: Path, what: str) -> dict[str, Any]:
    """A JSON object the project wrote; RunError naming the file when it is damaged."""
    try:
        data = json.loads(path.read_bytes())
    except (OSError, ValueError, RecursionError) as exc:  # ValueError: bad JSON, bad UTF-8, a 5000-digit number
        raise RunError(f"{path}: unreadable {what} ({type(exc).__name__}: {exc}); the run cannot be resumed") from None
    if not isinstance(data, dict):
        raise RunError(f"{path}: {what} is not a JSON object; the run cannot be resumed")
    return data


def _flatten(doc: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for key, value in doc.items():
        if isinstance(value, Mapping):
            out.update(_flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def config_changes(saved: Mapping[str, Any], new: Mapping[str, Any], may_change: Iterable[str]) -> list[str]:
    """``key: saved -> new`` for every (dotted) field that differs, except those in ``may_change``."""
    allowed = set(may_change)
    old, fresh = _flatten(saved), _flatten(new)
    changed = []
    for key in sorted(set(old) | set(fresh)):
        if key.split(".")[0] in allowed or key in allowed:
            continue
        if old.get(key, "<unset>") != fresh.get(key, "<unset>"):
            changed.append(f"{key}: {old.get(key, '<unset>')!r} -> {fresh.get(key, '<unset>')!r}")
    return changed


def check_resume(
    run_dir: Path,
    new: Mapping[str, Any],
    may_change: Iterable[str],
    as_run: Callable[[Mapping[str, Any]], Mapping[str, Any]] | None = None,
) -> None:
    """Refuse to resume ``run_dir`` with a config that differs from its saved one (beyond ``may_change``).

    ``as_run``: what the saved document meant when it was written (e.g. a section saved as overrides of
    defaults since changed, completed with the defaults of then), compared instead of its text."""
    path = run_dir / "config.json"
    if not path.is_file():
        raise RunError(f"{path} is missing: cannot tell which experiment {run_dir} holds, so it is not resumed")
    saved: Mapping[str, Any] = read_json(path, "run config")
    if as_run is not None:
        saved = as_run(saved)
    changes = config_changes(saved, new, may_change)
    if changes:
        shown = "; ".join(changes[:6]) + (f"; and {len(changes) - 6} more" if len(changes) > 6 else "")
        raise RunError(
            f"{run_dir} holds a different experiment, refusing to resume it ({shown}); "
            f"resume with the run's own config ({path}) or start a new run under another name"
        )
