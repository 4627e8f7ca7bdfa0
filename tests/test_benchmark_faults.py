"""How a benchmark job ends when something goes wrong, without running one (a cell takes minutes): a cell's Ray
error in one line without terminal colours, one exit status per kind (2 bad input, 1 a fault, 143/130 a signal)
and, where the benchmark resumes, what it kept and the command that resumes it."""

from __future__ import annotations

import errno
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import tiny_benchmark

from atdrone.benchmark import job
from atdrone.benchmark.cells import load_benchmark
from atdrone.benchmark.config import BenchmarkConfig
from atdrone.errors import Interrupted
from atdrone.rundir import RunError
from atdrone.service.faults import ServiceFault

DISK_FULL = "No space left on device"


def ray_error(cause: Exception) -> Exception:
    """``cause`` as ``ray.get`` raises it from a task: Ray's wrapper, whose text is the remote traceback in colour."""
    from ray.exceptions import RayTaskError

    traceback = (
        'Traceback (most recent call last):\n  File "cells.py", line 1, in run_cell\n'
        f"\x1b[31m{type(cause).__name__}: {cause}\x1b[39m"
    )
    return RayTaskError(
        "run_cell", traceback, cause, proctitle="ray::run_cell", pid=1, ip="127.0.0.1"
    ).as_instanceof_cause()


@pytest.fixture
def cfg(tmp_path: Path) -> BenchmarkConfig:
    return load_benchmark(tiny_benchmark(tmp_path, "faults"))


def kept(cfg: BenchmarkConfig) -> str:
    return (
        "kept 0 finished cell(s) of 3 (an unfinished one resumes from its last generation) in "
        f"{cfg.folder}; resume with: AGAIN"
    )


def test_a_failed_cells_ray_error_is_its_own_error_in_one_line_without_colours() -> None:
    full = OSError(errno.ENOSPC, DISK_FULL, "/bench/cells/sp-4p2e1o-s0.json")
    failed = job.cells_failed(
        [("sp-4p2e1o-s0", ray_error(full)), ("floor-4p2e1o-zoo1", ray_error(ValueError("x < 0")))]
    )
    assert isinstance(failed, ServiceFault)  # a fault: the benchmark resumes, retrying them
    assert str(failed) == (
        f"2 cell(s) failed: sp-4p2e1o-s0 (disk full: {DISK_FULL}: /bench/cells/sp-4p2e1o-s0.json); "
        "floor-4p2e1o-zoo1 (internal error: ValueError: x < 0)"
    )
    refused = job.cells_failed([("sp-4p2e1o-s1", ray_error(RunError("RUN holds a different experiment")))])
    assert isinstance(refused, RunError) and str(refused) == (
        "1 cell(s) failed: sp-4p2e1o-s1 (RUN holds a different experiment)"
    )  # every cell refused its input: bad input, fixed before running again


def test_a_benchmarks_fault_is_one_line_with_exit_1_and_the_resume_command_bad_input_exit_2(
    cfg: BenchmarkConfig,
) -> None:
    full = OSError(errno.ENOSPC, DISK_FULL, str(cfg.folder / "cells" / "x.json"))
    assert job.ended(cfg, ray_error(full), "AGAIN") == (
        1,
        f"error: disk full: {DISK_FULL}: {full.filename}; {kept(cfg)}",
    )
    assert job.ended(cfg, ServiceFault("1 cell(s) failed: c (d)"), "AGAIN") == (
        1,
        f"error: 1 cell(s) failed: c (d); {kept(cfg)}",
    )
    assert job.ended(cfg, RunError("FOLDER holds a different benchmark"), "AGAIN") == (
        2,
        "error: FOLDER holds a different benchmark",
    )
    assert job.ended(cfg, Interrupted(signal.SIGTERM), "AGAIN") == (143, f"interrupted; {kept(cfg)}")
    assert job.ended(cfg, Interrupted(signal.SIGINT), "AGAIN") == (130, f"interrupted; {kept(cfg)}")
    assert job.ended(cfg, ray_error(ValueError("a bug")), "AGAIN") is None  # the caller's internal error


@pytest.fixture
def keep_signal_handlers() -> Iterator[None]:
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}  # the command installs its own
    yield
    for s, h in handlers.items():
        signal.signal(s, h)


def test_atdrone_benchmark_on_a_full_disk_says_so_in_one_line_and_exits_1(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], keep_signal_handlers: None
) -> None:
    import json

    from atdrone.cli import main

    doc = tiny_benchmark(tmp_path, "full")
    path = tmp_path / "full.json"
    path.write_text(json.dumps(doc))
    where = tmp_path / "bench" / "full" / "benchmark_state.json"

    def disk_full(*args: Any, **kwargs: Any) -> None:
        raise OSError(errno.ENOSPC, DISK_FULL, str(where))

    monkeypatch.setattr(job, "run_benchmark", disk_full)
    assert main(["benchmark", str(path), "--tracking-uri", "sqlite:///m.db"]) == 1
    (line,) = capsys.readouterr().err.strip().splitlines()
    folder = load_benchmark(doc).folder
    assert line == (
        f"atdrone benchmark: error: disk full: {DISK_FULL}: {where}; kept 0 finished cell(s) of 3 (an unfinished "
        f"one resumes from its last generation) in {folder}; resume with: atdrone benchmark {path} --tracking-uri "
        "sqlite:///m.db"
    )
