"""Shared fixtures: every test's MLflow store in its own temporary folder; one local Ray per test process
(subprocess drivers join it); the deploy preflight's hover-and-turn flown once per process; xdist groups."""

from __future__ import annotations

import os
import shutil
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from run_suite import FLIGHTS

from atdrone.service.rayenv import STALL_TOLERANCE

# Under pytest-xdist (`make test` runs `-n 2 --dist loadgroup`): the tests of a module that starts Ray run on
# one worker (one Ray session per worker, at most two at once, each started as the service starts a local Ray:
# its own, never another's); the deploy flights (real-time, on UDP) share one worker, so their clocks are not
# starved by each other; everything else is spread over the workers.
_RAY_MODULES = (
    "test_benchmark",
    "test_faults",
    "test_hardening",
    "test_jobs",
    "test_learner",
    "test_registry",
    "test_service",
    "test_service_runs",
    "test_teammate_service",
)
# a module split in two stays one group: its halves on one worker, as before the split (no second Ray for it)
_RAY_GROUPS = {"test_service_runs": "test_service"}
# the flights (real-time, on UDP): the modules `make test` runs as their own session (tests/run_suite.py)
_FLIGHT_MODULES = tuple(Path(f).stem for f in FLIGHTS)

# the test modules' shared helpers: their asserts explained on failure as a test module's are
pytest.register_assert_rewrite("flight_helpers", "service_helpers")

# Every Ray a test starts (the session's, a test's head or cluster; each inherits this environment) starts a
# worker process only for an actor or task that asks for one: no idle Python workers started ahead of time at
# start-up and for the first driver, a second or two of CPU each that the suite's tests never use.
os.environ.setdefault("RAY_enable_worker_prestart", "0")
os.environ.setdefault("RAY_prestart_worker_first_driver", "0")
# and outlives a starved minute as a local start does (the suite's Rays run at nice +15 beside the flights)
for _name, _value in STALL_TOLERANCE.items():
    os.environ.setdefault(_name, _value)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        module = item.path.stem
        if module in _RAY_MODULES:
            item.add_marker(pytest.mark.xdist_group(_RAY_GROUPS.get(module, module)))
        elif module in _FLIGHT_MODULES:
            item.add_marker(pytest.mark.xdist_group("flight"))


@pytest.fixture(autouse=True)
def _mlflow_in_tmp(
    tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch, mlflow_store: Callable[[Path], str]
) -> None:
    """A test that names no tracking URI writes to a new store under a temporary folder (runs and artifacts)."""
    monkeypatch.setenv("MLFLOW_TRACKING_URI", mlflow_store(tmp_path_factory.mktemp("mlflow") / "mlflow.db"))


@pytest.fixture(autouse=True)
def _cache_in_tmp(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """atdrone's user cache (downloaded models, cflib's TOC) in a temporary folder, not the user's home."""
    monkeypatch.setenv("ATDRONE_CACHE", str(tmp_path_factory.mktemp("cache")))


@pytest.fixture(scope="session")
def _mlflow_template(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An empty MLflow sqlite store with MLflow's schema, made by MLflow once per test process."""
    import logging

    import mlflow

    logging.getLogger("alembic").setLevel(logging.WARNING)
    db = tmp_path_factory.mktemp("mlflow-template") / "mlflow.db"
    mlflow.MlflowClient(f"sqlite:///{db}").search_experiments(max_results=1)
    return db


@pytest.fixture
def mlflow_store(_mlflow_template: Path) -> Callable[[Path], str]:
    """``mlflow_store(path)``: a new MLflow store at ``path`` (a copy of the template), its tracking URI.

    MLflow migrates a new sqlite store's schema step by step (about 1.5 s, the same every time); a test that
    needs a fresh store gets the result of that, not a repeat of it."""

    def make(path: Path) -> str:
        path.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(_mlflow_template, path)
        return f"sqlite:///{path}"

    return make


@pytest.fixture(scope="session")
def _ray_session() -> Iterator[str]:
    """A local Ray on 2 CPUs as the service starts it (loopback only), started once; yields its GCS address."""
    import ray

    from atdrone.service.driver import init_ray

    init_ray(None, num_cpus=2)
    yield ray.get_runtime_context().gcs_address
    ray.shutdown()


@pytest.fixture
def local_ray(_ray_session: str) -> str:
    """The session's Ray, with every CPU free (a killed actor goes asynchronously); yields its GCS address,
    which a subprocess driver passes as ``address`` to join it instead of starting a Ray of its own.

    A test that leaves an actor holding a CPU would make every later service test wait for Ray to place its
    workers; it fails here instead, naming what is left. So does every test after the session's Ray died (its
    GCS or raylet gone): each would otherwise wait for Ray until its timeout."""
    import ray

    node = ray._private.worker._global_node  # None when a test shut the session's Ray down (it restarts it)
    processes = node.all_processes if node is not None else {}
    dead = [kind for kind in ("gcs_server", "raylet") for p in processes.get(kind, []) if p.process.poll() is not None]
    if dead:
        pytest.fail(f"this test process's Ray died earlier ({', '.join(dead)} ended): its Ray tests cannot run")
    deadline = time.monotonic() + 60
    while (free := ray.available_resources().get("CPU", 0.0)) < ray.cluster_resources().get("CPU", 0.0):
        if time.monotonic() > deadline:
            from ray.util.state import list_actors

            alive = [f"{a.class_name} ({a.name or a.actor_id})" for a in list_actors(filters=[("state", "=", "ALIVE")])]
            pytest.fail(f"only {free:g} CPUs free: an earlier test left actors running: {', '.join(alive)}")
        time.sleep(0.1)
    return _ray_session


@pytest.fixture(scope="session")
def _hover_and_turn_results() -> dict[str, list[str]]:
    return {}


@pytest.fixture(autouse=True)
def _hover_and_turn_once(
    _hover_and_turn_results: dict[str, list[str]], monkeypatch: pytest.MonkeyPatch
) -> Iterator[None]:
    """The deploy preflight's command-path check (a simulated hover-and-turn through cflib, seconds of flight)
    depends only on the task, the flight height and the command function: each combination that passed is
    not flown again in the session (one that found problems is). Tests that call ``hover_and_turn`` directly
    still fly it."""
    job = sys.modules.get("atdrone.deploy.job")
    real: Callable[..., list[str]] | None = getattr(job, "hover_and_turn", None)
    if real is None:
        yield
        return

    def once(task: Any, height: float, command: Callable[..., Any], *args: Any, **kwargs: Any) -> list[str]:
        key = repr((task, height, command.__module__, command.__qualname__, args, sorted(kwargs.items())))
        if key in _hover_and_turn_results:
            return []
        problems = real(task, height, command, *args, **kwargs)
        if not problems:  # only a pass is reused: a finding is flown again, never repeated from memory
            _hover_and_turn_results[key] = problems
        return list(problems)

    monkeypatch.setattr(job, "hover_and_turn", once)
    yield


@pytest.fixture(scope="session")
def load_script() -> Callable[[Path], Any]:
    """``load_script(path)``: a script of jobs/ or benchmarks/ imported as a module (they are no package)."""
    import importlib.util

    def load(path: Path) -> Any:
        spec = importlib.util.spec_from_file_location(f"atdrone_script_{path.stem}", path)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module

    return load


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Nothing left running at exit: Ray shut down, figures closed (a live Ray core worker at interpreter exit
    can crash the process after the tests passed)."""
    if "ray" in sys.modules:
        import ray

        if ray.is_initialized():
            ray.shutdown()
    if "matplotlib.pyplot" in sys.modules:
        import matplotlib.pyplot as plt

        plt.close("all")


TINY_BENCHMARK_PPO = {
    "epochs": 2,
    "entity_dim": 16,
    "hidden": 32,
    "minibatch_size": 64,
    "num_envs": 8,
    "rollout_steps": 16,
}


def tiny_benchmark(tmp_path: Path, name: str) -> dict[str, Any]:
    """A benchmark config of one method, one task, two seeds, one update per run, no best responses: two training
    cells and a floor, one at a time, each learner played on zoo3+swap too (the benchmark tests')."""
    return {
        "name": name,
        "tasks": ["4p2e1o"],
        "seeds": [0, 1],
        "zoos": ["zoo1"],
        "protocols": ["zoo3+swap"],
        "env_steps": 128,
        "updates_per_generation": 1,
        "eval_episodes": 4,
        "bootstrap_reps": 50,
        "best_response": False,
        "max_parallel": 1,
        "methods": {"sp": {"experiment": "sp_quick"}},
        "experiment": {"num_workers": 1, "eval_episodes": 4, "ppo": TINY_BENCHMARK_PPO},
        "out_dir": str(tmp_path / "bench"),
        "results_dir": str(tmp_path / "results" / name),
    }


def missing_zoo(tmp_path: Path) -> Path:
    """A zoo document with a greedy member and a checkpoint member whose file is absent."""
    import json

    doc = {
        "name": "ghosts",
        "members": [
            {"name": "greedy", "kind": "greedy"},
            {"name": "ghost", "kind": "checkpoint", "checkpoint": str(tmp_path / "ghost.pt")},
        ],
    }
    path = tmp_path / "ghosts.json"
    path.write_text(json.dumps(doc))
    return path
