"""The one base class of the errors a user can cause (bad input, a damaged file, a refused run).

Every module's own error (ConfigError, PolicyError, CheckpointError, RegistryError,
DeployError, ...) derives from :class:`UserError` as well as from the builtin it has
always been (ValueError, RuntimeError), so existing ``except`` clauses keep working
and the command line answers any of them with one line and exit code 2
(:func:`atdrone.cli.main`). Anything else is a bug and keeps its traceback under
``atdrone --debug``.
"""

from __future__ import annotations

__all__ = ["UserError"]


class UserError(Exception):
    """An error caused by what the user gave (a file, a config, an argument): its message is the answer."""
