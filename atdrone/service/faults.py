"""A failed run's one line: what went wrong, by kind, with one exit code per kind.

Errors raised inside Ray reach the driver wrapped (a ``RayTaskError`` whose text is the
remote traceback, with terminal colours); :func:`explain` finds the error that caused it
and names its kind:

- bad input (exit 2): any :class:`~atdrone.errors.UserError` (a config, a run directory
  or registry that cannot be resumed, a damaged checkpoint);
- a fault the run cannot survive (exit 1): the disk full, a store or folder that cannot
  be written (read-only, permissions), a service process that died past its restarts, a
  :class:`ServiceFault` (already put in words: a benchmark's failed cells).

Anything else is a bug: :func:`explain` answers None and the caller reports it as one.
"""

from __future__ import annotations

import errno
import re
import sqlite3
from dataclasses import dataclass

from atdrone.errors import UserError

EXIT_BAD_INPUT = 2
EXIT_FAULT = 1
_ANSI = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


class ServiceFault(RuntimeError):
    """A fault the run cannot survive, put in words by the code that met it: exit 1 with its message."""


@dataclass(frozen=True)
class Fault:
    """A failure's exit code and its line (without the program's name)."""

    code: int
    line: str


def causes(exc: BaseException) -> list[BaseException]:
    """``exc`` and what caused it, outermost first: Ray's wrapped causes (``.cause``) and Python's chain."""
    chain: list[BaseException] = []
    seen: set[int] = set()
    current: BaseException | None = exc
    while current is not None and id(current) not in seen:
        seen.add(id(current))
        chain.append(current)
        wrapped = getattr(current, "cause", None)
        if isinstance(wrapped, BaseException):
            current = wrapped
        else:  # what ``raise ... from None`` hid stays hidden: the error raised says it better
            current = current.__cause__ or (None if current.__suppress_context__ else current.__context__)
    return chain


def one_line(exc: BaseException) -> str:
    """An error's own message on one line, without terminal colours or a remote traceback."""
    text = _ANSI.sub("", str(exc.args[0]) if isinstance(exc, KeyError) and exc.args else str(exc))
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    if lines and lines[0].startswith(("ray::", "Traceback")):  # a RayTaskError's text: its last line is the error
        lines = lines[-1:]
    return " ".join(lines[:1]) or type(exc).__name__


def bug_line(exc: BaseException) -> str:
    """A bug's one line: the type and message of its own error, not of Ray's wrapper."""
    root = getattr(exc, "cause", None)
    root = root if isinstance(root, BaseException) else exc
    return f"{type(root).__name__}: {one_line(root)}"


def explain(exc: BaseException) -> Fault | None:
    """The kind of ``exc`` as a :class:`Fault`, or None for a bug (module docstring)."""
    from atdrone.service.actors import WorkerFailed

    chain = causes(exc)[::-1]  # the root cause first: Ray's wrapper says the same in a traceback
    for cause in chain:
        if isinstance(cause, UserError):
            return Fault(EXIT_BAD_INPUT, one_line(cause))
    for cause in chain:
        if isinstance(cause, OSError) and cause.errno in (errno.ENOSPC, errno.EDQUOT):
            return Fault(EXIT_FAULT, f"disk full: {_os_line(cause)}")
        if isinstance(cause, OSError) and cause.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
            return Fault(EXIT_FAULT, f"cannot write: {_os_line(cause)}")
        text = one_line(cause)
        if "database or disk is full" in text:
            return Fault(EXIT_FAULT, f"disk full: {text}")
        if "readonly database" in text or "read-only file system" in text.lower():
            return Fault(EXIT_FAULT, f"a store is read-only: {text}")
        if isinstance(cause, sqlite3.DatabaseError):
            return Fault(EXIT_FAULT, f"a database failed: {text}")
        if isinstance(cause, (WorkerFailed, ServiceFault)):
            return Fault(EXIT_FAULT, text)
    import ray

    for cause in chain:
        if isinstance(cause, ray.exceptions.RayActorError):
            return Fault(EXIT_FAULT, f"a service process died and could not be replaced: {one_line(cause)}")
        if isinstance(cause, OSError):
            return Fault(EXIT_FAULT, _os_line(cause))
    return None


def _os_line(exc: OSError) -> str:
    where = f": {exc.filename}" if exc.filename else ""
    return f"{exc.strerror or one_line(exc)}{where}"
