"""Faults injected into a service run: the driver SIGKILLed at every step of a generation's bookkeeping, each entry
point stopped by SIGTERM, a learner and the coordinator killed, the disk full and the MLflow store read-only. After
each, what the run produced (once resumed) equals what an uninterrupted run produces."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import mlflow
import pandas as pd
import pytest
import ray

from atdrone.registry import Registry
from atdrone.service.driver import run_experiment
from atdrone.service.experiment import load_experiment

# ------------------------------------------------------------------ the driver SIGKILLed at every step
REPO = Path(__file__).resolve().parents[1]
FAULTY = {
    "task": "4p2e1o",
    "algorithm": "hola",
    "generations": 2,
    "updates_per_generation": 2,
    "num_workers": 1,
    "eval_episodes": 4,
    "final_zoo": "zoo1",
    "final_episodes": 4,
    "gif": False,
    "hola": {"pi0_seeds": 1, "pi0_levels": 2, "min_episodes": 4, "max_episodes": 8},
    "ppo": {"epochs": 2, "entity_dim": 16, "hidden": 32, "minibatch_size": 64, "num_envs": 4, "rollout_steps": 16},
}
# (side, target, when, nth, generation saved after the kill) in the order a run meets them; each kill is
# resumed by the next entry's driver
KILLS = [
    ("coordinator", "add_member", "before", 1, 0),  # generation 0: the first checkpoint written, its row not
    ("driver", "update_member", "after", 1, 0),  # generation 0 half logged: a learner's nested run RUNNING
    ("driver", "file:service_state.json", "before", 1, 0),  # generation 0 fully logged, not saved
    ("coordinator", "add_match", "after", 1, 1),  # generation 1: its first match recorded
    ("driver", "tracker.log_dict", "after", 1, 1),  # generation 1's learner run begun; then the run is moved
    ("driver", "file:summary.json", "after", 1, 2),  # the summary written, the parent run still RUNNING
]


def _mlflow_record(uri: str, experiment: str) -> dict[str, Any]:
    """Every (undeleted) run by name: status, parent's name, member tag, metric points; and the model versions.

    Timings (perf/...) are compared by their steps only."""
    client = mlflow.MlflowClient(tracking_uri=uri)
    ident = client.get_experiment_by_name(experiment).experiment_id
    runs = client.search_runs([ident], max_results=1000)
    names = {r.info.run_id: r.info.run_name for r in runs}
    record: dict[str, Any] = {}
    for r in runs:
        points = {}
        for key in r.data.metrics:
            history = sorted((m.step, m.value) for m in client.get_metric_history(r.info.run_id, key))
            points[key] = [s for s, _ in history] if key.startswith("perf/") else history
        assert r.info.run_name not in record, f"two runs named {r.info.run_name}"
        record[r.info.run_name] = {
            "status": r.info.status,
            "parent": names.get(r.data.tags.get("mlflow.parentRunId", "")),
            "member": r.data.tags.get("atdrone.member"),
            "generation": r.data.tags.get("atdrone.generation"),
            "metrics": points,
            "artifacts": sorted(a.path for a in client.list_artifacts(r.info.run_id)),
        }
    versions = client.search_model_versions(f"name = 'atdrone-{experiment}'")
    record["versions"] = sorted(
        (v.version, v.tags.get("member"), v.tags.get("score"), names[v.run_id]) for v in versions
    )
    champion = client.get_model_version_by_alias(f"atdrone-{experiment}", "champion")
    record["champion"] = champion.tags["member"]
    return record


def _run_state(run_dir: Path) -> dict[str, Any]:
    """The registry rows (timestamps and MLflow ids aside), checkpoint digests, the state and summary files."""
    from atdrone.models.checkpoint import read_header

    reg = Registry(run_dir / "registry.db", create=False)
    members = reg.members().drop(columns=["created", "mlflow_run_id"])
    members["checkpoint"] = [Path(c).relative_to(run_dir).as_posix() for c in members["checkpoint"]]
    frames = {
        "members": members,
        "matches": reg.matches().drop(columns=["created"]),
        "generations": reg.generations().drop(columns=["started", "finished"]),
    }
    state = {k: json.loads(v.to_json(orient="records")) for k, v in frames.items()}
    state["files"] = {p.name: read_header(p)["sha256"] for p in sorted((run_dir / "members").glob("*.pt"))}
    saved = json.loads((run_dir / "service_state.json").read_text())
    assert saved["registry"] == "./registry.db"  # relative: a moved run directory keeps its own
    state["state"] = {k: v for k, v in saved.items() if k not in ("mlflow_run_id", "registry", "run_id")}
    state["summary"] = json.loads((run_dir / "summary.json").read_text())
    state["population"] = (run_dir / "population.csv").read_text()
    reg.close()
    return state


def _wait_for_the_dead_drivers_actors(name: str) -> None:
    """A killed driver's actors (its registry actor, by name) go once Ray sees the driver gone."""
    from atdrone.registry import REGISTRY_NAMESPACE

    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            ray.get_actor(f"registry-{name}", namespace=REGISTRY_NAMESPACE)
        except ValueError:
            return
        time.sleep(0.1)
    pytest.fail(f"the killed driver's registry actor registry-{name} is still alive")


@pytest.fixture(scope="session")  # not module: xdist ends a module's fixtures whenever its worker runs another's test
def reference(_ray_session: str, _mlflow_template: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """The uninterrupted run of FAULTY (named faults_t), made once for the module's faults to be compared with:
    its registry, files and state (``state``) and its MLflow record (``mlflow``)."""
    folder = tmp_path_factory.mktemp("reference")
    shutil.copyfile(_mlflow_template, folder / "ref.db")
    uri = f"sqlite:///{folder / 'ref.db'}"
    cfg = load_experiment({**FAULTY, "name": "faults_t", "out_dir": str(folder / "ref")})
    run_experiment(cfg, tracking_uri=uri, progress=False)
    return {"state": _run_state(folder / "ref" / "faults_t"), "mlflow": _mlflow_record(uri, "faults_t")}


def _same_as(reference: dict[str, Any], run_dir: Path, uri: str) -> None:
    got = _run_state(run_dir)
    for part, want in reference["state"].items():
        assert got[part] == want, part
    got_mlflow = _mlflow_record(uri, "faults_t")
    assert sorted(got_mlflow) == sorted(reference["mlflow"])
    for name, want in reference["mlflow"].items():
        assert got_mlflow[name] == want, name


def test_a_driver_killed_at_each_step_of_a_generation_and_resumed_ends_as_an_uninterrupted_run(
    local_ray, tmp_path, mlflow_store, reference
):
    """One run is SIGKILLed at six points of its life, each resumed by the next driver (joined to the same
    Ray): before and after registry writes of the coordinator and the driver, inside the MLflow logging of
    a generation, before the state file and after the summary (its best member registered). Killed with a
    learner's MLflow run RUNNING, the run directory is moved and resumed from its new place. The last
    resume completes it. Registry, checkpoints, state, MLflow runs (names, statuses, parents, metric
    points, artifacts; no run left RUNNING or twice) and model versions equal those of an uninterrupted run
    of the same config, and the registry's .db file copied alone holds every row."""
    faulty_uri = mlflow_store(tmp_path / "faulty.db")
    doc = {**FAULTY, "name": "faults_t"}

    run_dir = tmp_path / "faulty" / "faults_t"
    faulty = {**doc, "out_dir": str(tmp_path / "faulty")}
    moved = tmp_path / "moved"
    server = subprocess.Popen(
        [sys.executable, str(REPO / "tests" / "fault_driver.py"), "--serve"],
        cwd=REPO,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert server.stdin is not None and server.stdout is not None
    try:
        for side, target, when, nth, generation in KILLS:
            spec = {"doc": faulty, "uri": faulty_uri, "address": local_ray, "side": side, "target": target}
            server.stdin.write(json.dumps({**spec, "when": when, "nth": nth}) + "\n")
            server.stdin.flush()
            status = int(server.stdout.readline())
            assert status == -signal.SIGKILL, f"{side} {target} {when} #{nth}: exit {status}, not killed there"
            saved = json.loads((run_dir / "service_state.json").read_text())
            assert saved["coordinator"]["generation"] == saved["logged"] == generation, (target, saved)
            _wait_for_the_dead_drivers_actors("faults_t")
            if target == "add_member":  # a killed run is continued only when asked to
                with pytest.raises(FileExistsError, match="--resume"):
                    run_experiment(load_experiment(faulty), tracking_uri=faulty_uri, progress=False)
            if target == "tracker.log_dict":  # killed with a learner's MLflow run RUNNING: resumed elsewhere
                moved.mkdir()
                run_dir = Path(shutil.move(run_dir, moved / "faults_t"))
                faulty["out_dir"] = str(moved)
    finally:
        server.stdin.close()
        server.wait(timeout=60)
    client = mlflow.MlflowClient(tracking_uri=faulty_uri)
    assert client.get_run(saved["mlflow_run_id"]).info.status == "RUNNING"  # killed before the run's end

    summary = run_experiment(load_experiment(faulty), tracking_uri=faulty_uri, resume=True, progress=False)
    assert summary["complete"]
    _same_as(reference, run_dir, faulty_uri)
    # the registry names each learner's live MLflow run
    runs = {
        r.info.run_id: r.info.run_name
        for r in client.search_runs([client.get_experiment_by_name("faults_t").experiment_id])
    }
    for _, m in Registry(run_dir / "registry.db", create=False).members().iterrows():
        assert runs[m["mlflow_run_id"]] == f"learner-{m['id']}"
    # the registry's file alone (no -wal beside it) holds the whole registry
    alone = tmp_path / "alone" / "registry.db"
    alone.parent.mkdir()
    shutil.copyfile(run_dir / "registry.db", alone)
    with Registry(alone, create=False) as copy, Registry(run_dir / "registry.db", create=False) as reg:
        for table in ("members", "matches", "generations"):
            pd.testing.assert_frame_equal(
                getattr(copy, table)().drop(columns="checkpoint", errors="ignore"),
                getattr(reg, table)().drop(columns="checkpoint", errors="ignore"),
            )
        assert len(copy.members()) == len(reference["state"]["members"])


# ------------------------------------------------------------------ a stop signal to each entry point
def _state(run_dir: Path) -> dict[str, Any]:
    try:
        return json.loads((run_dir / "service_state.json").read_text())
    except (OSError, ValueError):
        return {}


def _stop_when(proc: subprocess.Popen[str], ready: Any, timeout_s: float = 240.0) -> tuple[str, str]:
    """SIGTERM to ``proc`` once ``ready()``; its stdout and stderr."""
    deadline = time.monotonic() + timeout_s
    while not ready():
        assert proc.poll() is None, f"ended before the signal: {proc.communicate()}"
        assert time.monotonic() < deadline, "never got there"
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    return proc.communicate(timeout=180)


def _registry_up(name: str) -> bool:
    from atdrone.registry import REGISTRY_NAMESPACE

    try:
        ray.get_actor(f"registry-{name}", namespace=REGISTRY_NAMESPACE)
    except ValueError:
        return False
    return True


def test_sigterm_to_a_training_driver_ends_in_one_line_with_143_and_its_resume_equals_an_uninterrupted_run(
    local_ray, tmp_path, mlflow_store, reference
):
    """SIGTERM (`ray job stop`) to `atdrone train` once generation 0 is saved, then to `jobs/train.py --resume`
    as soon as its run's registry actor is up: each driver (joined to the session's Ray, whose handlers ray.init
    replaced) ends its MLflow runs, says in its last line what it kept and how to resume, and exits 143 with no
    traceback. The last resume then ends as an uninterrupted run."""
    uri = mlflow_store(tmp_path / "mlflow.db")
    doc = {**FAULTY, "name": "faults_t", "out_dir": str(tmp_path / "out")}
    config = tmp_path / "faults_t.json"
    config.write_text(json.dumps(doc))
    run_dir = tmp_path / "out" / "faults_t"
    env = {**os.environ, "MLFLOW_TRACKING_URI": uri}
    drivers = [
        (
            "atdrone train",
            [sys.executable, "-m", "atdrone.cli", "train", str(config), "--address", local_ray, "--no-progress"],
            lambda: _state(run_dir).get("logged", 0) >= 1,
        ),
        (
            "jobs/train.py",
            [sys.executable, "jobs/train.py", str(config), "--address", local_ray, "--tracking-uri", uri, "--resume"],
            lambda: _registry_up("faults_t"),
        ),
    ]
    kept = (
        r"kept [12] completed generation\(s\) \(the registry, member checkpoints; the unfinished one is played again\)"
    )
    for prog, command, ready in drivers:
        proc = subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        _, err = _stop_when(proc, ready)
        assert proc.returncode == 143, err
        assert "Traceback" not in err and "SIGTERM received" not in err, err
        last = err.strip().splitlines()[-1]
        assert re.fullmatch(rf"{re.escape(prog)}: interrupted; {kept} in \S+; resume with: .*--resume", last), last
        _wait_for_the_dead_drivers_actors("faults_t")
    run_experiment(load_experiment(doc), tracking_uri=uri, resume=True, progress=False)
    _same_as(reference, run_dir, uri)


# ------------------------------------------------------------------ a learner and the coordinator killed
def test_a_learner_killed_mid_update_and_the_coordinator_killed_mid_generation_end_as_an_uninterrupted_run(
    local_ray, tmp_path, mlflow_store, reference, monkeypatch
):
    """In generation 0 the learner's process is SIGKILLed while it trains (after its first update); in
    generation 1 the coordinator's (the one that replaced the first). The driver replaces the dead actors each
    time and plays the generation again from the last saved one: the run ends as an uninterrupted one
    (registry, checkpoints, state, MLflow), with three coordinators used."""
    import threading

    from atdrone.service import pool

    class Recording(pool.CoordinatorPool):
        def __init__(self) -> None:
            super().__init__()
            self.taken: list[Any] = []

        def take(self) -> Any:
            self.taken.append(super().take())
            return self.taken[-1]

    coordinators = Recording()
    monkeypatch.setattr(pool, "COORDINATORS", coordinators)
    killed: list[str] = []
    done = threading.Event()

    def progress(c: Any) -> tuple[int, str]:
        return ray.get(c.state.remote())["generation"], ray.get(c.progress.remote())

    def kill() -> None:
        try:
            while not done.is_set() and len(killed) < 2:
                time.sleep(0.02)
                if not coordinators.taken:
                    continue
                current = coordinators.taken[-1]
                try:
                    generation, line = progress(current)
                except ray.exceptions.RayError:
                    continue
                if not killed and "update 1/" in line:
                    for pid in ray.get(current.learner_pids.remote()):
                        os.kill(pid, signal.SIGKILL)
                    killed.append(f"learners in generation {generation}: {line}")
                elif len(killed) == 1 and len(coordinators.taken) == 2 and (generation, line[:6]) == (1, "train:"):
                    os.kill(ray.get(current.pid.remote()), signal.SIGKILL)
                    killed.append(f"coordinator in generation {generation}: {line}")
        except BaseException as exc:  # reported by the test
            killed.append(f"killer failed: {exc!r}")

    uri = mlflow_store(tmp_path / "mlflow.db")
    doc = {**FAULTY, "name": "faults_t", "out_dir": str(tmp_path / "out")}
    killer = threading.Thread(target=kill, daemon=True)
    killer.start()
    try:
        run_experiment(load_experiment(doc), tracking_uri=uri, progress=False)
    finally:
        done.set()
        killer.join(timeout=30)
    assert [k.split(" in ")[0] for k in killed] == ["learners", "coordinator"], killed
    assert killed[0].startswith("learners in generation 0"), killed
    assert len(coordinators.taken) == 3
    _same_as(reference, tmp_path / "out" / "faults_t", uri)


# ------------------------------------------------------------------ the disk full, the MLflow store read-only
@pytest.fixture(scope="module")
def faultfs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """tests/faultfs.c built: a preload library that fails writes under one folder (ENOSPC or EROFS) once armed."""
    compiler = shutil.which("cc") or shutil.which("gcc")
    if compiler is None:
        pytest.skip("needs a C compiler to build tests/faultfs.c")
    lib = tmp_path_factory.mktemp("faultfs") / "faultfs.so"
    subprocess.run(
        [compiler, "-shared", "-fPIC", "-O2", "-o", str(lib), str(REPO / "tests" / "faultfs.c"), "-ldl"], check=True
    )
    return lib


def test_a_full_disk_then_a_read_only_store_end_in_one_line_with_exit_1_and_the_resume_equals_an_uninterrupted_run(
    local_ray, tmp_path, mlflow_store, reference, faultfs
):
    """The run folder's disk fills up once generation 0 is saved (every write of the driver there fails with
    ENOSPC; it is joined to the session's Ray, whose actors write on), then the resume finds the MLflow store on a
    read-only file system (EROFS).
    Each driver ends with one line naming the fault and what was kept, exit 1, no traceback; with the disk and
    the store writable again the run resumes and ends as an uninterrupted run."""
    uri = mlflow_store(tmp_path / "store" / "mlflow.db")
    doc = {**FAULTY, "name": "faults_t", "out_dir": str(tmp_path / "out")}
    config = tmp_path / "faults_t.json"
    config.write_text(json.dumps(doc))
    run_dir = tmp_path / "out" / "faults_t"
    trigger = tmp_path / "armed"
    base = {**os.environ, "MLFLOW_TRACKING_URI": uri, "LD_PRELOAD": str(faultfs), "FAULTFS_TRIGGER": str(trigger)}
    kept = (
        r"kept [12] completed generation\(s\) \(the registry, member checkpoints; the unfinished one is played again\)"
    )
    faults = [  # (folder, errno, armed when, the fault's words)
        (tmp_path / "out", "28", lambda: _state(run_dir).get("logged", 0) >= 1, r"disk full: .+"),
        (tmp_path / "store", "30", lambda: True, r"(a store is read-only|cannot write): .+"),
    ]
    for folder, code, ready, words in faults:
        env = {**base, "FAULTFS_DIR": str(folder), "FAULTFS_ERRNO": code}
        command = [sys.executable, "-m", "atdrone.cli", "train", str(config), "--address", local_ray, "--no-progress"]
        command.append("--resume")
        proc = subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        deadline = time.monotonic() + 240
        while not ready():
            assert proc.poll() is None, f"ended before the fault: {proc.communicate()}"
            assert time.monotonic() < deadline, "never got there"
            time.sleep(0.05)
        trigger.touch()
        _, err = proc.communicate(timeout=240)
        trigger.unlink()
        _wait_for_the_dead_drivers_actors("faults_t")
        assert proc.returncode == 1, err
        assert "Traceback" not in err, err
        last = err.strip().splitlines()[-1]
        assert re.fullmatch(rf"atdrone train: error: {words}; {kept} in \S+; resume with: .*--resume", last), last
    run_experiment(load_experiment(doc), tracking_uri=uri, resume=True, progress=False)
    _same_as(reference, run_dir, uri)
