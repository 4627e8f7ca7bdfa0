"""Experiment tracking: the one module that imports mlflow.

Runs go to ``MLFLOW_TRACKING_URI`` when set, else to a sqlite file ``mlflow.db`` in
the working directory (browse with ``mlflow ui --backend-store-uri sqlite:///mlflow.db``).
Metric names are namespaced: train/..., eval/..., perf/..., pop/...
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import shutil
import tempfile
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Any

from atdrone.fileio import user_cache
from atdrone.tracking_views import (
    VIEW_ID,
    VIEW_TAG,
    member_series,
    population_columns,
    population_markdown,
    read_view,
    runs_view_state,
    view_tag_value,
)

DEFAULT_URI = "sqlite:///mlflow.db"
__all__ = ["Tracker", "member_series", "population_columns", "population_markdown"]
log = logging.getLogger(__name__)


def tracking_uri(uri: str | None = None) -> str:
    """The tracking URI in force: the argument, MLFLOW_TRACKING_URI, or ./mlflow.db; a relative sqlite file made
    absolute (:func:`absolute_uri`), so what is printed names the store wherever it is read (a Ray job runs in a
    temporary copy of the working directory)."""
    return absolute_uri(uri or os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_URI)


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


EXPERIMENT_KIND = {"mlflow.experimentKind": "custom_model_development"}  # MLflow's model-training view
VIEW_REFRESH_S = 60.0  # while a top-level run logs, its experiment's view is written again at most this often
CHAMPION = "champion"


def metric_key(name: str) -> str:
    """``name`` as MLflow takes a metric key: a character it refuses (a protocol's ``+``) becomes ``_``."""
    return _NOT_IN_KEYS.sub("_", name)


_NOT_IN_KEYS = re.compile(r"[^\w/.\- :]")


def artifact_root(uri: str) -> str | None:
    """Where a sqlite store's artifacts go: ``mlartifacts/`` beside the database, never ./mlruns of the cwd."""
    if not uri.startswith("sqlite:///"):
        return None
    return (Path(uri.removeprefix("sqlite:///")).resolve().parent / "mlartifacts").as_uri()


class Tracker:
    """A thin handle on one MLflow run (and its nested children)."""

    def __init__(self, uri: str | None = None) -> None:
        os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")  # nothing leaves this machine
        os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # no download bars in a run's output
        import mlflow

        logging.getLogger("alembic").setLevel(logging.WARNING)
        self.mlflow = mlflow
        self.uri = tracking_uri(uri)
        mlflow.set_tracking_uri(self.uri)
        with _store_lock(self.uri):  # two processes creating one sqlite store race on its schema
            mlflow.MlflowClient().search_experiments(max_results=1)
        self._top: tuple[str, str] | None = None  # the top-level run in progress: its id and its experiment's
        self._view_at = 0.0  # when its view was last written (time.monotonic)

    def experiment(self, name: str) -> str:
        """The id of experiment ``name``; a new one opens in the model-training view, artifacts beside the store."""
        client = self.mlflow.MlflowClient()
        with _store_lock(self.uri):
            found = client.get_experiment_by_name(name)
            if found is None:
                ident = client.create_experiment(name, artifact_location=_experiment_artifacts(self.uri, name))
            else:
                ident = found.experiment_id
            for key, value in EXPERIMENT_KIND.items():
                if found is None or found.tags.get(key) != value:
                    client.set_experiment_tag(ident, key, value)
        if found is None or VIEW_TAG not in found.tags:  # what the printed link opens (ui_link)
            self._refresh_view_quietly(str(ident))
        return str(ident)

    def refresh_view(self, experiment_id: str) -> None:
        """Write the experiment's shared view (:data:`VIEW_TAG`, what :func:`ui_link` opens) from the metric names
        its runs have logged: the key numbers as columns, the top-level runs' charts and no empty sections
        (:func:`atdrone.tracking_views.runs_view_state`). Columns alone when the charts would not fit in a tag."""
        client = self.mlflow.MlflowClient()
        top: set[str] = set()
        nested: set[str] = set()
        for run in client.search_runs([experiment_id], max_results=50_000):
            (nested if "mlflow.parentRunId" in run.data.tags else top).update(run.data.metrics)
        state = runs_view_state(top, nested)
        old = client.get_experiment(experiment_id).tags.get(VIEW_TAG)
        now = int(time.time() * 1000)
        try:
            created = read_view(old)[0] if old else now
        except (ValueError, KeyError, TypeError):  # not ours (a view saved from the UI under the same id)
            created = now
        try:
            value = view_tag_value(state, created, now)
        except ValueError:
            columns = {k: state[k] for k in ("selectedColumns", "hideEmptyCharts")}
            value = view_tag_value(columns, created, now)
        client.set_experiment_tag(experiment_id, VIEW_TAG, value)

    def _refresh_view_quietly(self, experiment_id: str) -> None:
        """:meth:`refresh_view`, a failure logged: a view is never worth a run."""
        try:
            self.refresh_view(experiment_id)
        except Exception as exc:  # MLflow raises its own exceptions (store busy, a deleted experiment)
            log.warning("MLflow view of experiment %s not updated: %s", experiment_id, exc)

    @contextmanager
    def run(
        self,
        experiment: str,
        run_name: str,
        nested: bool = False,
        run_id: str | None = None,
        tags: Mapping[str, str] | None = None,
    ) -> Iterator[str]:
        """Start (or with ``run_id`` resume) a run; yields its id.

        The run ends FINISHED, or KILLED when interrupted (Ctrl-C, SIGTERM as SystemExit),
        or FAILED on any other exception.
        """
        if not nested:
            self.mlflow.set_experiment(experiment_id=self.experiment(experiment))
        active = self.mlflow.start_run(run_name=run_name, nested=nested, run_id=run_id, tags=dict(tags or {}))
        top = None if nested else str(active.info.experiment_id)
        if top is not None:
            self._top, self._view_at = (str(active.info.run_id), top), time.monotonic()
        try:
            yield active.info.run_id
        except (KeyboardInterrupt, SystemExit):
            self.mlflow.end_run("KILLED")
            self._refresh_view_at_end(top)
            raise
        except BaseException:
            self.mlflow.end_run("FAILED")
            self._refresh_view_at_end(top)
            raise
        self.mlflow.end_run("FINISHED")
        self._refresh_view_at_end(top)

    def _refresh_view_at_end(self, experiment_id: str | None) -> None:
        """At the end of a top-level run (``experiment_id`` None for a nested one): its experiment's view."""
        if experiment_id is not None:
            self._top = None
            self._refresh_view_quietly(experiment_id)

    def _refresh_view_now_and_then(self, run_id: str | None) -> None:
        """After metrics reach the top-level run in progress (``run_id``, or the active run when None): its
        experiment's view again when the last one is :data:`VIEW_REFRESH_S` old (a long run's new metrics)."""
        if self._top is None or time.monotonic() - self._view_at < VIEW_REFRESH_S:
            return
        active = self.mlflow.active_run()
        if (run_id or (active.info.run_id if active is not None else None)) != self._top[0]:
            return
        self._view_at = time.monotonic()
        self._refresh_view_quietly(self._top[1])

    def end_stale_runs(self, experiment: str, tags: Mapping[str, str], keep: str | None = None) -> list[str]:
        """End as KILLED the RUNNING runs with ``tags`` (a dead attempt's), except ``keep``; their ids."""
        stale = [r.info.run_id for r in self._search(experiment, tags, running=True) if r.info.run_id != keep]
        client = self.mlflow.MlflowClient()
        for run_id in stale:
            client.set_terminated(run_id, "KILLED")
        return stale

    def forget_runs(self, experiment: str, tags: Mapping[str, str], step_tag: str, first: int, keep: str) -> list[str]:
        """Delete the runs with ``tags`` whose ``step_tag`` is ``first`` or later (a dead attempt's record of
        the generations it never saved), ending them KILLED first when still RUNNING; their ids.

        ``keep`` (the parent run being resumed) is never touched.
        """
        client = self.mlflow.MlflowClient()
        gone = []
        for run in self._search(experiment, tags):
            step = run.data.tags.get(step_tag)
            if run.info.run_id == keep or step is None or int(step) < first:
                continue
            if run.info.status == "RUNNING":
                client.set_terminated(run.info.run_id, "KILLED")
            client.delete_run(run.info.run_id)
            gone.append(run.info.run_id)
        return gone

    def _search(self, experiment: str, tags: Mapping[str, str], running: bool = False) -> list[Any]:
        """The (undeleted) runs of ``experiment`` with ``tags`` (values: names checked by the config's rule, or hex)."""
        client = self.mlflow.MlflowClient()
        found = client.get_experiment_by_name(experiment)
        if found is None:
            return []
        terms = [f"tags.`{k}` = '{v}'" for k, v in tags.items()] + (
            ["attributes.status = 'RUNNING'"] if running else []
        )
        return list(client.search_runs([found.experiment_id], " and ".join(terms), max_results=50_000))

    def end_run_if_running(self, run_id: str, status: str = "FINISHED") -> bool:
        """End run ``run_id`` with ``status`` when it is still RUNNING (an attempt killed after its last record)."""
        client = self.mlflow.MlflowClient()
        if client.get_run(run_id).info.status != "RUNNING":
            return False
        client.set_terminated(run_id, status)
        return True

    def log_params(self, params: Mapping[str, Any]) -> None:
        flat = _flatten(params)
        active = self.mlflow.active_run()
        existing = self.mlflow.get_run(active.info.run_id).data.params if active is not None else {}
        fresh = {k: v for k, v in flat.items() if k not in existing}
        if fresh:
            self.mlflow.log_params(fresh)

    def log_metrics(
        self, metrics: Mapping[str, float], step: int, run_id: str | None = None, once: bool = False
    ) -> None:
        """Log to the active run, or to ``run_id`` (e.g. the parent of the nested run now active).

        ``once``: skip the metrics that already have a point at ``step`` (a resumed run
        logging a step its dead attempt logged: the points are one batch, so all or none).
        """
        clean = {metric_key(k): float(v) for k, v in metrics.items() if v is not None and v == v}
        if once and clean:
            client = self.mlflow.MlflowClient()
            target = run_id or self._active_id()
            clean = {
                k: v for k, v in clean.items() if all(m.step != step for m in client.get_metric_history(target, k))
            }
        if not clean:
            return
        if run_id is None:
            self.mlflow.log_metrics(clean, step=step)
        else:
            client = self.mlflow.MlflowClient()
            stamp = int(time.time() * 1000)
            points = [self.mlflow.entities.Metric(k, v, stamp, step) for k, v in clean.items()]
            client.log_batch(run_id, metrics=points)
        self._refresh_view_now_and_then(run_id)

    def _active_id(self) -> str:
        active = self.mlflow.active_run()
        if active is None:
            raise RuntimeError("no active MLflow run")
        return str(active.info.run_id)

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        self.mlflow.log_artifact(str(path), artifact_path=artifact_path)

    def log_dict(self, data: Mapping[str, Any], name: str) -> None:
        self.mlflow.log_dict(dict(data), name)

    def set_tags(self, tags: Mapping[str, str]) -> None:
        self.mlflow.set_tags(dict(tags))

    def describe(self, text: str, run_id: str | None = None) -> None:
        """The description MLflow shows at the top of a run's page (Markdown; the active run by default)."""
        self.mlflow.MlflowClient().set_tag(run_id or self._active_id(), "mlflow.note.content", text)

    def log_series(self, series: Mapping[str, Sequence[float]], run_id: str | None = None) -> None:
        """Each ``name: values`` as one metric whose step i is value i (NaN values left out): one chart each."""
        client = self.mlflow.MlflowClient()
        stamp = int(time.time() * 1000)
        points = [
            self.mlflow.entities.Metric(name, float(v), stamp, i)
            for name, values in series.items()
            for i, v in enumerate(values)
            if v == v
        ]
        for start in range(0, len(points), 1000):  # MLflow takes at most 1,000 metrics a batch
            client.log_batch(run_id or self._active_id(), metrics=points[start : start + 1000])
        self._refresh_view_now_and_then(run_id)

    def register_checkpoint(
        self, checkpoint: str | Path, name: str, score: float | None, tags: Mapping[str, str] | None = None
    ) -> str:
        """Register a checkpoint file (logged to the active run under ``model/``) as a version of model ``name``.

        Nothing is pickled: the version's source is the project's own checkpoint file
        (JSON header + safetensors, digest-checked when loaded). ``score`` (e.g. the
        best member's final-zoo SUC) is kept as the version's ``score`` tag, and the
        alias ``champion`` moves to the best-scoring version registered under ``name`` by runs
        of the same name (the ``run`` tag; all versions when none has one), and never to
        another run's: a model whose champion is another run's keeps it. Returns the version
        number: the active run's version already registered with the same ``member`` tag when
        there is one (a resumed run registering again), else a new one.
        """
        path = Path(checkpoint)
        self.mlflow.log_artifact(str(path), artifact_path="model")
        active = self.mlflow.active_run()
        if active is None:
            raise RuntimeError("register_checkpoint needs an active run")
        client = self.mlflow.MlflowClient()
        with _store_lock(self.uri):
            if not client.search_registered_models(filter_string=f"name = '{name}'"):
                client.create_registered_model(name, description="atdrone population members (project checkpoints)")
        source = f"{active.info.artifact_uri}/model/{path.name}"
        info = {**(tags or {}), "checkpoint_file": path.name}
        if score is not None:
            info["score"] = repr(float(score))
        mine = [
            v
            for v in client.search_model_versions(f"name = '{name}'")
            if v.run_id == active.info.run_id and v.tags.get("member") == info.get("member")
        ]
        version = mine[0] if mine else client.create_model_version(name, source, run_id=active.info.run_id, tags=info)
        holder = self.champion_version(name)
        held = client.get_model_version(name, holder).tags.get("run") if holder is not None else info.get("run")
        if held == info.get("run"):  # another run's champion stays where it is
            own = [v for v in client.search_model_versions(f"name = '{name}'") if v.tags.get("run") == held]
            best = max(own, key=lambda v: (float(v.tags.get("score", "-inf")), int(v.version)))
            client.set_registered_model_alias(name, CHAMPION, best.version)
        return str(version.version)

    def register_weights(self, checkpoint: str | Path, name: str, alias: str, tags: Mapping[str, str]) -> str:
        """Register published weights as a version of model ``name`` with the alias ``alias`` (a benchmark's
        ``<method>-<task>``), logged to the active run under ``weights/``; a version of the active run with the
        same ``alias`` tag is reused (a resumed benchmark registering again). Returns the version number."""
        path = Path(checkpoint)
        active = self.mlflow.active_run()
        if active is None:
            raise RuntimeError("register_weights needs an active run")
        self.mlflow.log_artifact(str(path), artifact_path=f"weights/{alias}")
        client = self.mlflow.MlflowClient()
        with _store_lock(self.uri):
            if not client.search_registered_models(filter_string=f"name = '{name}'"):
                client.create_registered_model(
                    name, description="a benchmark's published weights (project checkpoints)"
                )
        info = {**tags, "alias": alias, "checkpoint_file": path.name}
        mine = [
            v
            for v in client.search_model_versions(f"name = '{name}'")
            if v.run_id == active.info.run_id and v.tags.get("alias") == alias
        ]
        source = f"{active.info.artifact_uri}/weights/{alias}/{path.name}"
        version = mine[0] if mine else client.create_model_version(name, source, run_id=active.info.run_id, tags=info)
        client.set_registered_model_alias(name, alias, version.version)
        return str(version.version)

    def champion_version(self, name: str) -> str | None:
        """The version of model ``name`` the alias ``champion`` points at (None when it has none)."""
        return champion_version(name, self.uri)


def champion_version(name: str, uri: str | None = None) -> str | None:
    """The version of registered model ``name`` its alias ``champion`` points at now (None when none does)."""
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    import mlflow

    try:
        return str(
            mlflow.MlflowClient(tracking_uri=tracking_uri(uri)).get_model_version_by_alias(name, CHAMPION).version
        )
    except Exception:  # MLflow raises its own exception for a model or alias that does not exist
        return None


def _experiment_artifacts(uri: str, name: str) -> str | None:
    root = artifact_root(uri)
    return None if root is None else f"{root}/{name}"


def model_checkpoint(uri: str, tracking: str | None = None, dst: str | Path | None = None) -> str:
    """A local copy of the checkpoint behind a registered model ``models:/NAME@ALIAS`` (or ``models:/NAME/VERSION``).

    The version's source is the project's checkpoint file; it is downloaded to ``dst``, or by
    default once into the user's cache (:func:`atdrone.fileio.user_cache` ``models/``, keyed by the
    tracking store and the version's source, and read from there after), and loaded by the caller with
    :func:`atdrone.models.checkpoint.load_checkpoint`, never unpickled. KeyError naming
    the model when it, its alias or its file is missing.
    """
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # one file: no bar on a command's output
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
    filename = (version.tags or {}).get("checkpoint_file")
    if not filename:
        raise KeyError(f"registered model {uri!r} is not an atdrone checkpoint (no checkpoint_file tag)")
    source = version.source or ""
    if dst is not None:
        return _download(mlflow, uri, source, Path(dst), tracking)
    # a version's source names its run's artifact, which never changes: one download per store and source
    key = hashlib.sha256(f"{tracking_uri(tracking)}\n{source}".encode()).hexdigest()[:24]
    cached = user_cache("models", key)
    if (cached / filename).is_file():
        return str(cached / filename)
    cached.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{key}.", dir=cached.parent))
    try:
        _download(mlflow, uri, source, staging, tracking)
        os.replace(staging, cached)  # whole or not at all; a concurrent download that got there first wins
    except OSError:
        if not (cached / filename).is_file():
            raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return str(cached / filename)


def _download(mlflow: Any, uri: str, source: str, folder: Path, tracking: str | None) -> str:
    try:
        local = mlflow.artifacts.download_artifacts(
            artifact_uri=source, dst_path=str(folder), tracking_uri=tracking_uri(tracking)
        )
    except Exception as exc:  # a version whose files were deleted or never uploaded
        raise KeyError(f"registered model {uri!r}: cannot fetch {source}: {exc}") from None
    return str(local)


UI_ADDRESS = "http://127.0.0.1:5000"  # where `mlflow ui` serves by default


def ui_link(experiment: str, uri: str | None = None) -> str:
    """The MLflow UI address of ``experiment`` in the model-training view, on its shared view when it has one.

    MLflow 3's UI keeps a workflow type per browser (GenAI by default, so a new browser
    shows "Traces 0"); the ``workflowType=machine_learning`` parameter opens the runs
    table whatever the browser saw before. The experiment's tag (:data:`EXPERIMENT_KIND`)
    says the same for MLflow's own guess. ``viewStateShareKey`` opens the view atdrone wrote
    (:meth:`Tracker.refresh_view`: the key numbers as columns, charts without empty sections); it must
    name the ``/runs`` tab, since MLflow's redirect from the experiment's address drops it.
    """
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    import mlflow

    found = mlflow.MlflowClient(tracking_uri=tracking_uri(uri)).get_experiment_by_name(experiment)
    if found is None:
        return f"{UI_ADDRESS}/#/experiments?workflowType=machine_learning"
    if VIEW_TAG in found.tags:
        page = f"#/experiments/{found.experiment_id}/runs?viewStateShareKey={VIEW_ID}&"
        return f"{UI_ADDRESS}/{page}workflowType=machine_learning"
    return f"{UI_ADDRESS}/#/experiments/{found.experiment_id}?workflowType=machine_learning"


def ui_run_link(run_id: str, uri: str | None = None) -> str:
    """The MLflow UI address of one run, in the model-training view (see :func:`ui_link`)."""
    os.environ.setdefault("MLFLOW_DISABLE_TELEMETRY", "true")
    import mlflow

    experiment = mlflow.MlflowClient(tracking_uri=tracking_uri(uri)).get_run(run_id).info.experiment_id
    return f"{UI_ADDRESS}/#/experiments/{experiment}/runs/{run_id}?workflowType=machine_learning"


def ui_model_link(name: str) -> str:
    """The MLflow UI address of a registered model's page, in the model-training view."""
    return f"{UI_ADDRESS}/#/models/{name}?workflowType=machine_learning"


EVALUATE_EXPERIMENT = "evaluate"  # where `atdrone evaluate --tracking-uri` records its runs


def record_evaluation(
    document: Mapping[str, Any], files: Sequence[Path], run_name: str, uri: str | None = None
) -> tuple[str, str]:
    """Record an evaluation report (:func:`atdrone.teams.reports.report_document`) as one MLflow run of the
    experiment ``evaluate``: its settings as params, per cell ``<task>/<zoo>/<metric>`` with the bounds of
    its 95 % interval over episodes (``..._ci95_low``, ``..._ci95_high``), the report ``files`` as
    artifacts. Returns the run id and its UI link."""
    tracker = Tracker(uri)
    cells = [c for c in document["cells"] if c.get("status") == "ok"]
    metrics: dict[str, float | None] = {}
    for cell in cells:
        summary = cell["summary"]
        for m in ("SUC", "COL", "AST", "REW"):
            key = f"{cell['task']}/{cell['zoo']}/{m}"
            metrics[key] = summary.get(m)
            low, high = summary.get(f"{m}_ci95") or (None, None)
            metrics[f"{key}_ci95_low"], metrics[f"{key}_ci95_high"] = low, high
    params = {
        "policy": document["learner"],
        "episodes_per_seed": document["episodes_per_seed"],
        "seeds": ",".join(map(str, document["seeds"])),
        "tasks": ",".join(dict.fromkeys(c["task"] for c in document["cells"])),
        "zoos": ",".join(dict.fromkeys(c["zoo"] for c in document["cells"])),
    }
    with tracker.run(EVALUATE_EXPERIMENT, run_name, tags={"atdrone.policy": str(document["learner"])}) as run_id:
        tracker.log_params(params)
        tracker.log_metrics({k: float(v) for k, v in metrics.items() if v is not None}, step=0)
        for path in files:
            tracker.log_artifact(path)
    return run_id, ui_run_link(run_id, tracker.uri)


def ui_hint(experiment: str, uri: str | None = None) -> str:
    """One line for the end of a command that logged: the UI link and how to start the UI on this store."""
    store = tracking_uri(uri)
    return f"MLflow: {ui_link(experiment, uri)} (start the UI with: mlflow ui --backend-store-uri {store})"


def absolute_uri(uri: str) -> str:
    """A sqlite URI with its file made absolute (what a Ray job's temporary working folder must not swallow)."""
    if not uri.startswith("sqlite:///") or uri.startswith("sqlite:////"):
        return uri
    return f"sqlite:///{Path(uri.removeprefix('sqlite:///')).resolve()}"
