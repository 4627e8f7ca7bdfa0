"""Shared fixtures: every test's MLflow store in its own temporary folder; one way to start a local Ray."""

from __future__ import annotations

from collections.abc import Iterator

import pytest


@pytest.fixture(autouse=True)
def _mlflow_in_tmp(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """A test that names no tracking URI writes to a store under a temporary folder (runs and artifacts)."""
    store = tmp_path_factory.mktemp("mlflow")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store}/mlflow.db")


@pytest.fixture(scope="module")
def local_ray() -> Iterator[None]:
    """A local Ray on 2 CPUs as the service starts it (loopback only), shut down after the module."""
    import ray

    from atdrone.service.driver import init_ray

    init_ray(None, num_cpus=2)
    yield
    ray.shutdown()


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """Nothing left running at exit: Ray shut down, figures closed (a live Ray core worker at interpreter exit
    can crash the process after the tests passed)."""
    import sys

    if "ray" in sys.modules:
        import ray

        if ray.is_initialized():
            ray.shutdown()
    if "matplotlib.pyplot" in sys.modules:
        import matplotlib.pyplot as plt

        plt.close("all")
