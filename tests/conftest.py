"""Every test's MLflow store lies in its own temporary folder, never in the checkout."""

from __future__ import annotations

import pytest


@pytest.fixture(autouse=True)
def _mlflow_in_tmp(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> None:
    """A test that names no tracking URI writes to a store under a temporary folder (runs and artifacts)."""
    store = tmp_path_factory.mktemp("mlflow")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{store}/mlflow.db")
