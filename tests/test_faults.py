"""Faults injected into the service: a rollout worker killed mid-collect, the driver SIGKILLed at every step
of a generation's bookkeeping. After each, what the run produced equals what an uninterrupted run produces."""

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
import numpy as np
import pandas as pd
import pytest
import ray

from atdrone.config import load_task
from atdrone.learn.learner import Learner, LearnerSpec
from atdrone.learn.ppo import ppo_config
from atdrone.policies.zoo import MemberSpec
from atdrone.registry import Registry
from atdrone.service.actors import RolloutJob, RolloutWorkerActor
from atdrone.service.driver import run_experiment
from atdrone.service.experiment import load_experiment
from atdrone.teams.partners import Uniform

TASK = load_task("4p2e1o")


# ------------------------------------------------------------------ a rollout worker killed mid-collect
def _job() -> tuple[RolloutJob, list[Any]]:
    """A job against a greedy and a Vicsek drone (drawn per slot and episode) and 5 updates' distinct weights."""
    ppo = ppo_config(
        {"epochs": 2, "entity_dim": 8, "hidden": 16, "num_envs": 8, "rollout_steps": 192, "minibatch_size": 64}
    )
    zoo = (MemberSpec("greedy", "greedy"), MemberSpec("vicsek", "vicsek"))
    specs = [LearnerSpec(ppo=ppo, num_e=2, num_p=4, seed=s, total_updates=5) for s in range(5)]
    weights = [ray.put(Learner(spec).get_weights()) for spec in specs]
    arch = Learner(specs[0]).model.architecture()
    job = RolloutJob(1234, ppo, 4, TASK.players.num_ctrl, arch, zoo, Uniform(tuple(m.name for m in zoo)))
    return job, weights


def _collect(worker: Any, job: RolloutJob, weights: list[Any], u: int) -> Any:
    return worker.collect.remote(job, weights[u], job.ppo.rollout_steps, u, weights[:u])


def _same_fragment(a: Any, b: Any) -> None:
    for name in ("obs", "u", "logp", "values", "rewards", "dones", "last_values"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.episodes == b.episodes
    assert a.extras.keys() == b.extras.keys()
    for name in a.extras:
        np.testing.assert_array_equal(a.extras[name], b.extras[name], err_msg=name)


def test_a_worker_killed_mid_collect_returns_the_fragments_and_draws_of_an_uninterrupted_one(local_ray):
    """Worker B is killed while it collects fragment 2 (a pid probe queued behind the collect goes
    unanswered, and is later answered by the restarted process), and again idle before fragment 4. Ray
    restarts it and retries the call; the job replays from its start, so every fragment (arrays, finished
    episodes and their partners) and the partner draws equal those of worker A, never interrupted."""
    job, weights = _job()
    a, b = RolloutWorkerActor.remote(TASK), RolloutWorkerActor.remote(TASK)
    try:
        want = [ray.get(_collect(a, job, weights, u)) for u in range(5)]
        want_drawn = ray.get(a.drawn.remote(job, weights, job.ppo.rollout_steps))
        assert sum(want_drawn.values()) > job.num_envs  # episodes ended and new partners were drawn
        assert {p for profile in want_drawn for p in profile.split("|")} == {"greedy", "vicsek"}

        got = [ray.get(_collect(b, job, weights, u)) for u in range(2)]
        first_pid = ray.get(b.pid.remote())
        pending = _collect(b, job, weights, 2)
        deadline = time.monotonic() + 60
        while True:  # the collect has begun once a probe sent after it waits
            probe = b.pid.remote()
            if not ray.wait([probe], timeout=0.3)[0]:
                break
            assert time.monotonic() < deadline, "the collect never seemed to run"
        ray.kill(b, no_restart=False)
        got.append(ray.get(pending, timeout=120))
        second_pid = ray.get(probe, timeout=60)
        assert second_pid != first_pid  # the probe was answered by the restarted worker: the kill hit the collect
        got.append(ray.get(_collect(b, job, weights, 3)))
        ray.kill(b, no_restart=False)  # idle this time: fragment 4 starts on a fresh process
        got.append(ray.get(_collect(b, job, weights, 4), timeout=120))
        assert ray.get(b.pid.remote()) not in (first_pid, second_pid)
        for u, (g, w) in enumerate(zip(got, want, strict=True)):
            try:
                _same_fragment(g, w)
            except AssertionError as exc:
                pytest.fail(f"fragment {u}: {exc}")
        assert ray.get(b.drawn.remote(job, weights, job.ppo.rollout_steps)) == want_drawn
    finally:
        ray.kill(a)
        ray.kill(b, no_restart=True)


def test_a_fresh_worker_replays_a_job_to_the_fragment_it_is_asked_for(local_ray):
    """Fragment 3 asked of a worker that never saw the job equals the fragment 3 of a worker that collected 0-2;
    asked without the earlier weights it is refused (it could not be the same fragment)."""
    job, weights = _job()
    a, b = RolloutWorkerActor.remote(TASK), RolloutWorkerActor.remote(TASK)
    try:
        for u in range(3):
            ray.get(_collect(a, job, weights, u))
        _same_fragment(ray.get(_collect(b, job, weights, 3)), ray.get(_collect(a, job, weights, 3)))
        with pytest.raises(ray.exceptions.RayTaskError, match="needs the weights of its 3 earlier updates"):
            ray.get(b.collect.remote(job, weights[3], job.ppo.rollout_steps, 3, []))
    finally:
        ray.kill(a)
        ray.kill(b)


def test_a_worker_dead_past_its_restarts_fails_the_updates_naming_it(local_ray, monkeypatch):
    """A rollout worker that has died once more than its restarts allow ends run_updates with WorkerFailed naming
    the worker's index and the cap, instead of Ray retrying (or the coordinator waiting) for ever. The cap is 1
    here (the actor's options and WORKER_RESTARTS alike) so that two kills spend it."""
    from atdrone.service import actors

    monkeypatch.setattr(actors, "WORKER_RESTARTS", 1)
    job, _ = _job()
    learner = actors.LearnerActor.remote(LearnerSpec(ppo=job.ppo, num_e=2, num_p=4, seed=0, total_updates=2))
    healthy = RolloutWorkerActor.remote(TASK)
    doomed = RolloutWorkerActor.options(max_restarts=1, max_task_retries=1).remote(TASK)
    try:
        first = ray.get(doomed.pid.remote())
        ray.kill(doomed, no_restart=False)  # the one restart
        deadline = time.monotonic() + 60
        while ray.get(doomed.pid.remote(), timeout=60) == first:  # a probe may beat the kill to the old process
            assert time.monotonic() < deadline, "the worker was never restarted"
            time.sleep(0.2)
        ray.kill(doomed, no_restart=False)  # past the cap: dead for good
        with pytest.raises(actors.WorkerFailed, match=r"rollout worker 1 died and was restarted 1 times, the cap"):
            actors.run_updates(learner, [healthy, doomed], [job, job], 2, 64)
    finally:
        for actor in (learner, healthy, doomed):
            ray.kill(actor)


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


# ------------------------------------------------------------------ a rollout worker that keeps dying
class _EndsItsReader:
    """Unpickled, it ends the process reading it (os._exit): a worker handed it as its job dies before the call
    runs, and so does every restart of it that Ray retries the call on."""

    def __reduce__(self) -> tuple[Any, tuple[int]]:
        return os._exit, (3,)


def test_a_worker_that_keeps_dying_fails_the_training_naming_it_and_the_cap_instead_of_hanging(local_ray, monkeypatch):
    """Worker 1's job kills every process it reaches; Ray restarts the worker as often as its cap allows and then
    gives up, so run_updates (a generation's training) ends with an error naming worker 1 and the cap, in bounded
    time. Without a cap (max_restarts=-1) the worker restarts forever and the training never ends: the test fails.
    The workers here are capped at 2 restarts (each costs a process start); the service's class is capped at
    WORKER_RESTARTS, checked on its options."""
    import threading

    from atdrone.service import actors
    from atdrone.service.actors import WORKER_RESTARTS, LearnerActor, run_updates

    assert RolloutWorkerActor._default_options["max_restarts"] == WORKER_RESTARTS > 0
    assert RolloutWorkerActor._default_options["max_task_retries"] == WORKER_RESTARTS
    cap = 2
    monkeypatch.setattr(actors, "WORKER_RESTARTS", cap)  # what the error names
    job, _ = _job()
    spec = LearnerSpec(ppo=job.ppo, num_e=2, num_p=4, seed=0, total_updates=1)
    learner = LearnerActor.remote(spec)
    workers = [RolloutWorkerActor.options(max_restarts=cap, max_task_retries=cap).remote(TASK) for _ in range(2)]
    outcome: list[BaseException | None] = []

    def train() -> None:
        try:
            run_updates(learner, workers, [job, _EndsItsReader()], 1, 8)
            outcome.append(None)
        except BaseException as exc:  # handed to the test's thread
            outcome.append(exc)

    thread = threading.Thread(target=train, daemon=True)
    try:
        thread.start()
        thread.join(timeout=150)  # 8 restarts took 39 s on a 2-core machine under a load of 20; 2 take a quarter
        assert not thread.is_alive(), "the training still waits on a worker that keeps dying: restarts not capped"
    finally:
        for actor in (*workers, learner):
            ray.kill(actor, no_restart=True)
    (error,) = outcome
    assert error is not None
    message = str(error)
    assert "rollout worker 1" in message and f"restarted {cap} times" in message, message


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
