"""A service run's directory before Ray starts: its identifier, its lock, its registry's place, and the checks
a resume makes of what it is about to trust.

A run is born with an identifier (:func:`atdrone.rundir.new_run_id`) written to its state
file (``service_state.json``) before anything else of it; the registry records it (the
``runs`` table) and the MLflow records carry it as a tag (:func:`run_tags`), so a run is
found by what it is, not by where its directory is. A registry kept outside the run
directory (``$ATDRONE_REGISTRY_DIR``, a cluster's driver-local disk) lives under the
run's name and identifier: a fresh run of the same name never opens another run's file.

:func:`open_run` takes the run's lock (the run directory's, and the registry file's when
it lies elsewhere) and, on a resume, checks before Ray starts: the state file's counts,
the registry's owner, its finished generations and members against the state file, and
every member checkpoint's sha256 against its registry row. A mismatch is one line
(:class:`~atdrone.rundir.RunError`) and nothing is written.
"""

from __future__ import annotations

import hashlib
import json
import os
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from atdrone.fileio import atomic_write_bytes
from atdrone.learn.ppo import saved_ppo_document
from atdrone.rundir import RunError, RunLock, check_resume, new_run_id, read_json, refuse_existing
from atdrone.service.experiment import ExperimentConfig

STATE_FILE = "service_state.json"
SUMMARY_FILE = "summary.json"
LOCK_FILE = ".lock"
REGISTRY_DIR_ENV = "ATDRONE_REGISTRY_DIR"
# what a resume may change; anything else in config.json must match (atdrone.rundir.check_resume)
RESUME_MAY_CHANGE = (
    "generations",
    "final_zoo",
    "final_episodes",
    "select_zoo",
    "gif",
    "learner_gpus",
    "learner_threads",
    "out_dir",
)


def write_json(path: Path, data: Any) -> None:
    atomic_write_bytes(path, json.dumps(data, indent=2, default=_jsonable).encode())


def _jsonable(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    return str(value)


def kept(run_dir: Path) -> str:
    """What an interrupted or failed run left, in words, for its last line."""
    try:
        done = int(json.loads((run_dir / STATE_FILE).read_text())["coordinator"]["generation"])
    except (OSError, ValueError, KeyError, TypeError):
        done = 0
    if done < 1:
        return "no completed generation"
    return f"{done} completed generation(s) (the registry, member checkpoints; the unfinished one is played again)"


def registry_path(cfg: ExperimentConfig, run_dir: Path, run_id: str = "") -> Path:
    """The run's registry file: ``$ATDRONE_REGISTRY_DIR/<name>/<run id>/registry.db`` when set (a cluster: a
    local disk of the driver's node, as sqlite's WAL needs), else ``<run_dir>/registry.db``."""
    folder = os.environ.get(REGISTRY_DIR_ENV)
    if not folder:
        return run_dir / "registry.db"
    return Path(folder).resolve() / cfg.name / run_id / "registry.db"


def registry_record(db: Path, run_dir: Path) -> str:
    """The registry's place as the state file keeps it: relative to the run directory when inside it
    (``./registry.db``: a moved or copied run directory resumes with its own), else the absolute path."""
    try:
        return "./" + db.relative_to(run_dir).as_posix()
    except ValueError:
        return str(db)


def run_tags(name: str, run_id: str, legacy: bool = False) -> dict[str, str]:
    """The MLflow tags of a run's records: its name and its identifier (a moved run keeps them; two runs of one
    name are two runs). ``legacy``: a run born before identifiers, whose records carry a key of its directory."""
    return {"atdrone.run": name, "atdrone.run_dir" if legacy else "atdrone.run_id": run_id}


@dataclass
class OpenRun:
    """A run directory opened by this driver (its locks held until :meth:`close`)."""

    run_dir: Path
    run_id: str
    registry: Path
    saved: dict[str, Any]
    legacy: bool = False  # born before run identifiers: its MLflow records are keyed by its directory
    locks: ExitStack = field(default_factory=ExitStack)

    @property
    def start(self) -> int:
        """The generations completed (the next one to run)."""
        return int(self.saved.get("coordinator", {}).get("generation", 0))

    def tags(self, name: str) -> dict[str, str]:
        return run_tags(name, self.run_id, self.legacy)

    def save(self, state: dict[str, Any]) -> None:
        """Write the state file: ``state`` with the run's identifier and registry."""
        self.saved = {**state, "run_id": self.run_id, "registry": registry_record(self.registry, self.run_dir)}
        write_json(self.run_dir / STATE_FILE, self.saved)

    def close(self) -> None:
        self.locks.close()


def open_run(cfg: ExperimentConfig, resume: bool) -> OpenRun:
    """Lock the run directory of ``cfg`` and check it (module docstring); a fresh run is born here (its state file
    written, with its identifier). Raises RunError, RunExistsError (a run without ``resume``) or RunBusyError."""
    run_dir = Path(cfg.out_dir).resolve() / cfg.name
    locks = ExitStack()
    try:
        locks.enter_context(RunLock(run_dir / LOCK_FILE, f"run {run_dir}"))
        run = _open_locked(cfg, run_dir, resume, locks)
    except BaseException:
        locks.close()
        raise
    return run


def _open_locked(cfg: ExperimentConfig, run_dir: Path, resume: bool, locks: ExitStack) -> OpenRun:
    state_path = run_dir / STATE_FILE
    if not state_path.exists():
        if resume and (run_dir / "config.json").exists():
            check_resume(run_dir, cfg.to_dict(), RESUME_MAY_CHANGE, saved_ppo_document)
        run_id = new_run_id()
        run = OpenRun(run_dir, run_id, registry_path(cfg, run_dir, run_id), {}, locks=locks)
        _lock_registry(run)
        _refuse_a_registry_in_the_way(run.registry, cfg.name)
        write_json(run_dir / "config.json", cfg.to_dict())
        run.save({})  # born: from now on a start without --resume is refused
        return run
    if not resume:
        refuse_existing(run_dir)
    saved = read_json(state_path, "service state")
    check_resume(run_dir, cfg.to_dict(), RESUME_MAY_CHANGE, saved_ppo_document)
    _check_counts(state_path, saved)
    legacy = not isinstance(saved.get("run_id"), str)
    run_id = hashlib.sha256(str(run_dir).encode()).hexdigest()[:16] if legacy else saved["run_id"]
    run = OpenRun(run_dir, run_id, _saved_registry(cfg, run_dir, saved, run_id), saved, legacy, locks)
    _lock_registry(run)
    check_registry(run, cfg.name)
    write_json(run_dir / "config.json", cfg.to_dict())  # only once every check passed: a refusal writes nothing
    return run


def _lock_registry(run: OpenRun) -> None:
    """The registry file's own lock when it lies outside the run directory (a copy of the run directory names
    the same file)."""
    if not run.registry.is_relative_to(run.run_dir):
        run.locks.enter_context(
            RunLock(run.registry.with_name(run.registry.name + LOCK_FILE), f"registry {run.registry}")
        )


def _check_counts(path: Path, saved: dict[str, Any]) -> None:
    """The state file's counts are counts: completed generations and logged generations, 0 <= logged <= done."""
    coordinator = saved.get("coordinator", {})
    done: Any = coordinator.get("generation", 0) if isinstance(coordinator, dict) else None
    logged: Any = saved.get("logged", done)

    def count(value: Any) -> bool:
        return isinstance(value, int) and not isinstance(value, bool) and value >= 0

    if not count(done) or not count(logged) or logged > done:
        raise RunError(
            f"{path}: {done!r} completed and {logged!r} logged generations are not counts of this run's "
            "generations; the state file was edited or damaged, so the run cannot be resumed"
        )


def _saved_registry(cfg: ExperimentConfig, run_dir: Path, saved: dict[str, Any], run_id: str) -> Path:
    """The registry the state file names, refused when the registry folder given now is another one."""
    record = saved.get("registry", "./registry.db")
    if not isinstance(record, str):
        raise RunError(f"{run_dir / STATE_FILE}: the registry's place is {record!r}, not a path")
    db = run_dir / record[2:] if record.startswith("./") else Path(record)
    inside = db.is_relative_to(run_dir)
    folder = os.environ.get(REGISTRY_DIR_ENV)
    if inside != (not folder) or (folder and not db.is_relative_to(Path(folder).resolve())):
        raise RunError(
            f"{run_dir} keeps its registry at {record}, not under {folder or 'the run directory'}: resume with "
            f"the same {REGISTRY_DIR_ENV} (or --registry-dir)"
        )
    return db


def _refuse_a_registry_in_the_way(db: Path, name: str) -> None:
    """A new run's registry file must not hold another run's rows (a new run starts by discarding its own)."""
    if not db.exists():
        return
    from atdrone.registry import Registry

    with Registry(db, create=False) as reg:
        owners, members = reg.owners(), len(reg.members())
    if owners or members:
        held = ", ".join(f"{n} (run id {r})" for r, n in owners.items()) or f"{members} members"
        raise RunError(f"{db} already holds a registry ({held}): a new run {name} would overwrite it; move it away")


def check_registry(run: OpenRun, name: str) -> None:
    """What a resume trusts in the registry, checked against the state file (module docstring)."""
    from atdrone.models.checkpoint import CheckpointError, read_header
    from atdrone.registry import Registry, RegistryError

    done, where = run.start, run.run_dir / STATE_FILE
    if not run.registry.exists():
        if done:
            raise RunError(f"{run.registry} is missing: {where} says {done} generation(s) completed")
        return
    try:
        with Registry(run.registry, create=False) as reg:
            owners = reg.owners()
            generations = reg.generations(run=name)
            members = reg.members(run=name)
    except RegistryError as exc:
        raise RunError(f"{exc}; the run cannot be resumed") from None
    if owners and run.run_id not in owners:
        others = ", ".join(f"{n} (run id {r})" for r, n in owners.items())
        raise RunError(f"{run.registry} is the registry of {others}, not of this run (run id {run.run_id})")
    finished = set(generations.loc[generations["finished"].notna(), "idx"].astype(int))
    if not set(range(done)) <= finished:
        raise RunError(
            f"{run.registry} has finished generations {sorted(finished)} but {where} says 0..{done - 1}: the "
            "registry lost commits or belongs to another run"
        )
    population = run.saved.get("coordinator", {}).get("algorithm", {}).get("population", [])
    kept = members[members["generation"] < done]
    missing = sorted(set(population) - set(kept["id"]))
    if missing:
        raise RunError(f"{run.registry} lacks member(s) {', '.join(missing)} of {where}'s population")
    for member, checkpoint, digest in zip(kept["id"], kept["checkpoint"], kept["sha256"], strict=True):
        try:
            found = read_header(checkpoint)["sha256"]
        except (CheckpointError, OSError) as exc:
            raise RunError(f"member {member}: {' '.join(str(exc).split())}; the run cannot be resumed") from None
        if found != digest:
            raise RunError(
                f"member {member}: {checkpoint} has sha256 {found[:12]}..., its registry row {str(digest)[:12]}...: "
                "the checkpoint was replaced, so the run cannot be resumed"
            )
