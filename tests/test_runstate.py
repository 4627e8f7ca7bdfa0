"""What a service run keeps private and what a resume trusts, checked without starting Ray: Ray's token file made
readable by its owner only, and a registry whose write-ahead log lost a commit refused in one line, writing
nothing."""

from __future__ import annotations

import shutil
import stat
from pathlib import Path
from typing import Any

import pytest

from atdrone.registry import Registry
from atdrone.service.experiment import load_experiment
from atdrone.service.runstate import REGISTRY_DIR_ENV, STATE_FILE, open_run

REPO = Path(__file__).resolve().parent.parent
SP_QUICK = REPO / "configs" / "experiments" / "sp_quick.json"
WAL_HEADER, FRAME_HEADER = 32, 24  # sqlite's write-ahead log: a header, then frames of a header and one page each


def mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_rays_token_file_is_made_readable_by_its_owner_only(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A missing token is made 0600 in a 0700 folder (never readable by others, even for a moment); one that Ray
    wrote 0644 is made 0600, its token kept (every node and client holds the same one)."""
    from atdrone.service.driver import _private_token

    monkeypatch.setenv("HOME", str(tmp_path))
    token = tmp_path / ".ray" / "auth_token"
    _private_token()
    assert mode(token) == 0o600 and mode(token.parent) == 0o700
    assert len(token.read_text()) == 64  # 256 bits in hex, as Ray's own
    kept = token.read_text()
    token.chmod(0o644)
    _private_token()
    assert mode(token) == 0o600 and token.read_text() == kept


def _crashed_run(tmp_path: Path, generations: int) -> tuple[Path, bytes, bytes]:
    """A run of ``generations`` completed generations, as a driver killed before its registry's write-ahead log was
    folded back leaves it, copied elsewhere (the files, no ``-shm``): its run directory, registry.db and -wal."""
    cfg = load_experiment(SP_QUICK, name="wal", out_dir=str(tmp_path / "killed"), generations=generations)
    run = open_run(cfg, resume=False)
    with Registry(run.registry) as writer:
        writer.claim(run.run_id, cfg.name)
        writer.checkpoint()
        for g in range(generations):  # each commit in the log only
            writer.start_generation(cfg.name, g)
            writer.finish_generation(cfg.name, g)
        run.save({"coordinator": {"generation": generations, "algorithm": {"population": []}}})
        copy = tmp_path / "out" / "wal"
        shutil.copytree(run.run_dir, copy, ignore=shutil.ignore_patterns("*-shm", ".lock"))
        db, wal = (copy / "registry.db").read_bytes(), (copy / "registry.db-wal").read_bytes()
    run.close()
    return copy, db, wal


def test_a_registry_whose_write_ahead_log_lost_a_commit_is_refused_in_one_line_and_nothing_is_written(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two generations completed, both commits still in the registry's write-ahead log: intact, the run resumes
    from it; with a byte flipped in the log's last frame (the second generation's commit), sqlite drops that
    commit, so the registry holds one finished generation where the state file says two: refused in one line
    (exit 2) before Ray starts, nothing written, config.json untouched though the resume asks for 3 generations."""
    import signal

    from atdrone.cli import main
    from atdrone.service import driver

    monkeypatch.delenv(REGISTRY_DIR_ENV, raising=False)
    run_dir, db, wal = _crashed_run(tmp_path, generations=2)
    assert len(wal) > WAL_HEADER + FRAME_HEADER
    shutil.copytree(run_dir, tmp_path / "intact" / "wal")
    intact = load_experiment(SP_QUICK, name="wal", out_dir=str(tmp_path / "intact"), generations=3)
    open_run(intact, resume=True).close()  # every commit read back from the log: it resumes
    damaged = bytearray(wal)
    damaged[-1] ^= 0xFF  # the last page of the last frame: its checksum no longer matches
    (run_dir / "registry.db-wal").write_bytes(bytes(damaged))
    before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file() and p.name != ".lock"}

    def ray_started(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("Ray was started before the run was checked")

    monkeypatch.setattr(driver, "init_ray", ray_started)
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}  # main installs its own
    try:
        args = ["--resume", "--name", "wal", "--out-dir", str(tmp_path / "out"), "--generations", "3"]
        code = main(["train", str(SP_QUICK), *args, "--no-progress"])
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
    lines = capsys.readouterr().err.strip().splitlines()
    registry = run_dir.resolve() / "registry.db"
    assert code == 2 and lines[-1] == (
        f"atdrone train: error: {registry} has finished generations [0] but {run_dir.resolve() / STATE_FILE} says "
        "0..1: the registry lost commits or belongs to another run"
    ), lines
    after = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.is_file() and p.name in before}
    assert after == before  # config.json, the state file, registry.db and its log as they were
    assert db == before["registry.db"]
