"""A run directory's identity: what a resume must keep, and the saved state read back safely.

A resumed run continues the population it finds, so it must be the same experiment:
:func:`check_resume` compares the run's saved ``config.json`` with the config given to
resume it and refuses any difference outside the fields a resume may change (more
generations, another final evaluation, other resources). Both the population service
and the local trainer use it.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Mapping
from pathlib import Path
from typing import Any

from atdrone.errors import UserError


class RunError(UserError, RuntimeError):
    """A run directory that cannot be started or resumed as asked."""


class RunExistsError(RunError, FileExistsError):
    """A run directory that already holds a run, started again without ``--resume``."""


def refuse_existing(run_dir: Path) -> None:
    """The one answer to starting a run over one that exists."""
    raise RunExistsError(f"{run_dir} holds a run: pass --resume to continue it, or pick another name")


def read_json(path: Path, what: str) -> dict[str, Any]:
    """A JSON object the project wrote; RunError naming the file when it is damaged."""
    try:
        data = json.loads(path.read_bytes())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError, RecursionError) as exc:
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
