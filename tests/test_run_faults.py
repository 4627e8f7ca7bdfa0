"""A failed run's one line by kind (atdrone.service.faults): what Ray wraps is unwrapped, the kind decides the exit
status (2 bad input, 1 a fault), a bug is left to be reported as one."""

from __future__ import annotations

import errno
import sqlite3

import pytest
import ray

from atdrone.rundir import RunError
from atdrone.service.faults import EXIT_BAD_INPUT, EXIT_FAULT, explain


def _from_ray(cause: BaseException) -> BaseException:
    """``cause`` as the driver receives it from a remote task: a RayTaskError with a coloured remote traceback."""
    trace = f"\x1b[36mray::Coordinator.run_generation()\x1b[39m\nTraceback (most recent call last):\n  ...\n{cause!r}"
    return ray.exceptions.RayTaskError("run_generation", trace, cause).as_instanceof_cause()


@pytest.mark.parametrize(
    "cause, code, line",
    [
        (
            OSError(errno.ENOSPC, "No space left on device", "/runs/x/members/a.pt"),
            EXIT_FAULT,
            "disk full: No space left on device: /runs/x/members/a.pt",
        ),
        (
            OSError(errno.EROFS, "Read-only file system", "/runs/x"),
            EXIT_FAULT,
            "cannot write: Read-only file system: /runs/x",
        ),
        (
            sqlite3.OperationalError("attempt to write a readonly database"),
            EXIT_FAULT,
            "a store is read-only: attempt to write a readonly database",
        ),
        (sqlite3.OperationalError("database or disk is full"), EXIT_FAULT, "disk full: database or disk is full"),
        (
            RunError("/runs/x: the registry is not this run's"),
            EXIT_BAD_INPUT,
            "/runs/x: the registry is not this run's",
        ),
    ],
)
def test_a_fault_raised_inside_ray_is_one_line_of_its_kind(cause, code, line):
    for exc in (cause, _from_ray(cause)):
        fault = explain(exc)
        assert fault is not None and (fault.code, fault.line) == (code, line)
        assert "\x1b" not in fault.line and "\n" not in fault.line


def test_the_error_raised_is_the_line_not_the_one_it_replaced():
    from atdrone.registry import RegistryError

    try:
        try:
            raise RegistryError("/runs/x/registry.db is not a sqlite database")
        except RegistryError as exc:
            raise RunError(f"{exc}; the run cannot be resumed") from None
    except RunError as exc:
        fault = explain(exc)
    assert fault is not None and fault.line == "/runs/x/registry.db is not a sqlite database; the run cannot be resumed"


def test_a_bug_is_not_a_fault():
    assert explain(_from_ray(KeyError("cf7"))) is None
