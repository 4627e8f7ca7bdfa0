"""Experiment tracking: the one module that imports mlflow.

Runs go to ``MLFLOW_TRACKING_URI`` when set, else to a sqlite file ``mlflow.db`` in
the working directory (browse with ``mlflow ui --backend-store-uri sqlite:///mlflow.db``).
Metric names are namespaced: train/..., eval/..., perf/..., pop/...
"""

from __future__ import annotations

import logging
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

DEFAULT_URI = "sqlite:///mlflow.db"
log = logging.getLogger(__name__)


def tracking_uri(uri: str | None = None) -> str:
    """The tracking URI in force: the argument, MLFLOW_TRACKING_URI, or ./mlflow.db."""
    return uri or os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_URI


def _flatten(params: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    out: dict[str, str] = {}
    for k, v in params.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(_flatten(v, f"{key}."))
        else:
            out[key] = str(v)[:6000]
    return out


@contextmanager
def _store_lock(uri: str) -> Iterator[None]:
    """An exclusive lock beside a sqlite store while it is opened (and maybe created)."""
    if not uri.startswith("sqlite:///"):
        yield
        return
    import fcntl

    db = Path(uri.removeprefix("sqlite:///"))
    db.parent.mkdir(parents=True, exist_ok=True)
    with open(f"{db}.lock", "w") as handle:
        fcntl.flock(handle, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(handle, fcntl.LOCK_UN)


class Tracker:
    """A thin handle on one MLflow run (and its nested children)."""

    def __init__(self, uri: str | None = None) -> None:
        os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")  # nothing leaves this machine
        import mlflow

        logging.getLogger("alembic").setLevel(logging.WARNING)
        self.mlflow = mlflow
        self.uri = tracking_uri(uri)
        mlflow.set_tracking_uri(self.uri)
        with _store_lock(self.uri):  # two processes creating one sqlite store race on its schema
            mlflow.MlflowClient().search_experiments(max_results=1)

    @contextmanager
    def run(
        self,
        experiment: str,
        run_name: str,
        nested: bool = False,
        run_id: str | None = None,
        tags: Mapping[str, str] | None = None,
    ) -> Iterator[str]:
        """Start (or with ``run_id`` resume) a run; yields its id."""
        if not nested:
            with _store_lock(self.uri):
                self.mlflow.set_experiment(experiment)
        with self.mlflow.start_run(run_name=run_name, nested=nested, run_id=run_id, tags=dict(tags or {})) as r:
            yield r.info.run_id

    def log_params(self, params: Mapping[str, Any]) -> None:
        flat = _flatten(params)
        active = self.mlflow.active_run()
        existing = self.mlflow.get_run(active.info.run_id).data.params if active is not None else {}
        fresh = {k: v for k, v in flat.items() if k not in existing}
        if fresh:
            self.mlflow.log_params(fresh)

    def log_metrics(self, metrics: Mapping[str, float], step: int) -> None:
        clean = {k: float(v) for k, v in metrics.items() if v is not None and v == v}
        if clean:
            self.mlflow.log_metrics(clean, step=step)

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        self.mlflow.log_artifact(str(path), artifact_path=artifact_path)

    def log_dict(self, data: Mapping[str, Any], name: str) -> None:
        self.mlflow.log_dict(dict(data), name)

    def set_tags(self, tags: Mapping[str, str]) -> None:
        self.mlflow.set_tags(dict(tags))

    def log_model(self, model: Any, name: str, alias: str | None = None, tags: Mapping[str, str] | None = None) -> str:
        """Log a torch model to the active run, register it as ``name`` and point ``alias`` at it."""
        import mlflow.pytorch

        info = mlflow.pytorch.log_model(model, name="model", registered_model_name=name, serialization_format="pickle")
        version = str(info.registered_model_version)
        client = self.mlflow.MlflowClient()
        for key, value in (tags or {}).items():
            client.set_model_version_tag(name, version, key, value)
        if alias:
            client.set_registered_model_alias(name, alias, version)
        return version


def model_checkpoint(uri: str, tracking: str | None = None) -> str:
    """The checkpoint file behind a registered model ``models:/NAME@ALIAS`` (or ``models:/NAME/VERSION``).

    Read from the model version's ``checkpoint`` tag (set when the driver registers a
    champion): the project's own checkpoint format is loaded, never the pickled MLflow
    model. KeyError naming the model when it, its alias or its tag is missing.
    """
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    import mlflow

    if not uri.startswith("models:/"):
        raise KeyError(f"not a registered model URI (models:/NAME@ALIAS): {uri!r}")
    ref = uri.removeprefix("models:/")
    client = mlflow.MlflowClient(tracking_uri=tracking_uri(tracking))
    try:
        if "@" in ref:
            name, alias = ref.split("@", 1)
            version = client.get_model_version_by_alias(name, alias)
        else:
            name, number = ref.rsplit("/", 1)
            version = client.get_model_version(name, number)
    except Exception as exc:  # mlflow raises its own RestException / MlflowException for unknown names
        raise KeyError(f"no registered model {uri!r} in {tracking_uri(tracking)}: {exc}") from None
    path = (version.tags or {}).get("checkpoint")
    if not path:
        raise KeyError(f"registered model {uri!r} has no 'checkpoint' tag (registered before deploy support?)")
    return str(path)
