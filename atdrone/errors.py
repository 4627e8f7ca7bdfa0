"""The one base class of the errors a user can cause (bad input, a damaged file, a refused run), and the
interrupt a stop signal raises.

Every module's own error (ConfigError, PolicyError, CheckpointError, RegistryError,
DeployError, ...) derives from :class:`UserError` as well as from the builtin it has
always been (ValueError, RuntimeError), so existing ``except`` clauses keep working
and the command line answers any of them with one line and exit code 2
(:func:`atdrone.cli.main`). Anything else is a bug and keeps its traceback under
``atdrone --debug``.

A stop signal (SIGTERM from ``ray job stop`` or a scheduler, SIGINT from Ctrl-C) raises
:class:`Interrupted`, a KeyboardInterrupt that remembers which signal it was, so every
``except KeyboardInterrupt`` and ``finally`` runs as for Ctrl-C and the process ends with
the shell's code for that signal (:func:`interrupt_exit_code`: 143 for SIGTERM, 130 for
SIGINT).
"""

from __future__ import annotations

import signal
import threading
from typing import Any

__all__ = ["Interrupted", "UserError", "interrupt_exit_code", "interrupt_on_signals", "interrupted"]

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


class UserError(Exception):
    """An error caused by what the user gave (a file, a config, an argument): its message is the answer."""


class Interrupted(KeyboardInterrupt):
    """A stop signal received: ``signum`` says which."""

    def __init__(self, signum: int = signal.SIGINT) -> None:
        super().__init__(f"signal {signal.Signals(signum).name}")
        self.signum = int(signum)


_received: list[int] = []  # the stop signals this process received, in order


def _raise_interrupted(signum: int, frame: Any) -> None:
    _received.append(signum)
    raise Interrupted(signum)


def interrupt_on_signals() -> bool:
    """Make SIGTERM and SIGINT raise :class:`Interrupted` in the main thread; False (nothing done) elsewhere.

    Call it after ``ray.init``: Ray's core worker installs its own SIGTERM handler, which aborts
    the process (exit -6) without running any ``finally``."""
    if threading.current_thread() is not threading.main_thread():
        return False
    for signum in STOP_SIGNALS:
        signal.signal(signum, _raise_interrupted)
    return True


def interrupted(exc: BaseException) -> bool:
    """Whether ``exc`` is, or was caused by, an interrupt (one that lands while an extension module initialises
    comes out as ``ImportError: initialization failed`` raised from the KeyboardInterrupt)."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, KeyboardInterrupt):
            return True
        seen.add(id(cause))
        cause = cause.__cause__ or cause.__context__
    return False


def interrupt_exit_code(exc: BaseException | None) -> int:
    """The exit code of a process ended by ``exc``, an interrupt: 128 + the signal (143 SIGTERM, 130 SIGINT). A
    library that caught the :class:`Interrupted` and raised a plain KeyboardInterrupt in its place (Ray's ``get``
    does) is seen through: the last signal received counts."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, Interrupted):
            return 128 + exc.signum
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return 128 + (_received[-1] if _received else signal.SIGINT)
