"""Security and data hardening: nothing unpickled, resumes of the same experiment only, generations all
or nothing, MLflow models without pickle and with one champion across runs, local Ray on loopback only."""

from __future__ import annotations

import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import tempfile
import textwrap
import time
from pathlib import Path

import mlflow
import pytest
import ray

from atdrone.cli import main
from atdrone.learn.trainer import STATE_FILE as LEARNER_STATE
from atdrone.learn.trainer import Trainer, load_train_config, run_training
from atdrone.models.checkpoint import MAGIC, load_checkpoint, save_checkpoint
from atdrone.models.networks import ActorCritic, NetConfig
from atdrone.rundir import RunError, config_changes
from atdrone.service.driver import STATE_FILE, check_schedulable, run_experiment
from atdrone.service.experiment import load_experiment
from atdrone.tracking import CHAMPION, Tracker, model_checkpoint

TINY_TRAIN = {
    "name": "tiny",
    "task": "4p2e1o",
    "seed": 1,
    "total_env_steps": 512,
    "eval_every": 1000,
    "eval_episodes": 4,
    "ppo": {"epochs": 2, "num_envs": 8, "rollout_steps": 32, "minibatch_size": 256, "entity_dim": 16, "hidden": 32},
}
TINY_SERVICE = {
    "task": "4p2e1o",
    "algorithm": "hola",
    "generations": 2,
    "updates_per_generation": 2,
    "num_workers": 1,  # one rollout worker process per run: splitting over workers is tested in test_service.py
    "eval_episodes": 4,
    "final_zoo": "zoo1",
    "final_episodes": 4,
    "gif": False,
    "hola": {"pi0_seeds": 1, "pi0_levels": 2, "min_episodes": 4, "max_episodes": 8},
    "ppo": {"epochs": 2, "entity_dim": 16, "hidden": 32, "minibatch_size": 64, "num_envs": 8, "rollout_steps": 16},
}


class _Marker:
    """Unpickling this touches a file: the harmless stand-in for code a planted pickle would run."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def __reduce__(self):  # type: ignore[no-untyped-def]
        return (Path.touch, (self.path,))


def _write_config(tmp_path: Path, doc: dict) -> Path:
    path = tmp_path / f"{doc['name']}.json"
    path.write_text(json.dumps(doc))
    return path


# ------------------------------------------------------------------ 1. nothing unpickled on resume
@pytest.mark.parametrize("planted", ["trainer_state.pt", LEARNER_STATE])
def test_a_pickle_planted_in_a_run_directory_is_refused_and_never_run(tmp_path, capsys, planted):
    marker = tmp_path / "executed"
    run_dir = tmp_path / "runs" / "tiny"
    run_dir.mkdir(parents=True)
    (run_dir / planted).write_bytes(pickle.dumps({"state": _Marker(marker)}))
    config = _write_config(tmp_path, {**TINY_TRAIN, "out_dir": str(tmp_path / "runs")})
    code = main(["train", str(config), "--resume", "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and not marker.exists()
    assert len(err.splitlines()) == 1 and "Traceback" not in err and str(run_dir) in err


def test_a_learner_state_with_a_changed_byte_is_refused(tmp_path):
    cfg = load_train_config({**TINY_TRAIN, "out_dir": str(tmp_path)})
    trainer = Trainer(cfg)
    trainer.update_once()
    trainer.save()
    path = trainer.run_dir / LEARNER_STATE
    data = bytearray(path.read_bytes())
    data[-3] ^= 0x01  # one bit of one tensor
    path.write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"digest|sha256|corrupt"):
        Trainer(cfg).resume()


# ------------------------------------------------------------------ 4. resume checks the config
def test_config_changes_lists_what_differs_beyond_what_may_change():
    saved = {"task": "4p2e1o", "generations": 3, "hola": {"population_size": 4}}
    new = {"task": "4p2e3o", "generations": 5, "hola": {"population_size": 6}}
    assert config_changes(saved, new, ["generations"]) == [
        "hola.population_size: 4 -> 6",
        "task: '4p2e1o' -> '4p2e3o'",
    ]
    assert config_changes(saved, {**saved, "generations": 9}, ["generations"]) == []


def test_the_local_trainer_refuses_to_resume_a_different_experiment(tmp_path, mlflow_store):
    uri = mlflow_store(tmp_path / "mlflow.db")
    cfg = load_train_config({**TINY_TRAIN, "out_dir": str(tmp_path)})
    run_training(cfg, progress=False, uri=uri)
    saved = (tmp_path / "tiny" / "config.json").read_bytes()
    other = load_train_config({**TINY_TRAIN, "out_dir": str(tmp_path), "task": "4p2e3o"})
    with pytest.raises(RunError, match=r"task: '4p2e1o' -> '4p2e3o'"):
        run_training(other, resume=True, progress=False, uri=uri)
    assert (tmp_path / "tiny" / "config.json").read_bytes() == saved
    longer = load_train_config({**TINY_TRAIN, "out_dir": str(tmp_path), "total_env_steps": 1024})
    assert run_training(longer, resume=True, progress=False, uri=uri).env_steps == 1024  # a longer budget may


def _service(tmp_path: Path, name: str, **kw) -> dict:
    return {**TINY_SERVICE, "name": name, "out_dir": str(tmp_path), **kw}


def test_a_damaged_service_state_is_a_clear_error(local_ray, tmp_path):
    run_dir = tmp_path / "bad"
    run_dir.mkdir()
    (run_dir / STATE_FILE).write_bytes(b"{not json")
    with pytest.raises(RunError, match="unreadable service state"):
        run_experiment(load_experiment(_service(tmp_path, "bad")), resume=True, progress=False)


# ------------------------------------------------------------------ MLflow: no pickle, one champion
def _checkpoint(path: Path, seed: int) -> Path:
    import torch

    torch.manual_seed(seed)
    model = ActorCritic(NetConfig(entity_dim=8, hidden=16))
    save_checkpoint(path, model, {"task": "4p2e1o", "num_p": 4, "num_e": 2})
    return path


def test_models_are_checkpoints_with_one_champion_across_runs(tmp_path, monkeypatch):
    elsewhere = tmp_path / "cwd"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    uri = f"sqlite:///{tmp_path}/store/mlflow.db"
    tracker = Tracker(uri)
    versions = []
    for i, score in enumerate([40.0, 30.0, 55.0]):
        with tracker.run("champ", f"run-{i}"):
            path = _checkpoint(tmp_path / f"m{i}.pt", seed=i)
            versions.append(tracker.register_checkpoint(path, "atdrone-champ", score, {"member": f"m{i}"}))
        client = tracker.mlflow.MlflowClient()
        champion = str(client.get_model_version_by_alias("atdrone-champ", CHAMPION).version)
        assert champion == {0: "1", 1: "1", 2: "3"}[i]  # the best score of every run so far
    assert versions == ["1", "2", "3"]
    local = Path(model_checkpoint("models:/atdrone-champ@champion", tracking=uri, dst=tmp_path / "dl"))
    assert local.read_bytes().startswith(MAGIC) and local.read_bytes() == (tmp_path / "m2.pt").read_bytes()
    _, header = load_checkpoint(local)
    assert header["task"] == "4p2e1o"
    files = [p for p in (tmp_path / "store" / "mlartifacts").rglob("*") if p.is_file()]
    assert files and all(p.read_bytes().startswith(MAGIC) for p in files)  # no MLmodel, no pickle
    assert not (elsewhere / "mlruns").exists() and not list(elsewhere.iterdir())  # nothing in the cwd
    experiment = client.get_experiment_by_name("champ")
    assert experiment.tags["mlflow.experimentKind"] == "custom_model_development"


# ------------------------------------------------------------------ 7. loopback only
LISTENING = textwrap.dedent(
    """
    import json, os, socket, struct, sys
    from atdrone.service.driver import init_ray
    import ray

    def listening():
        found = {}
        for name in ("tcp", "tcp6"):
            with open(f"/proc/net/{name}") as f:
                next(f)
                for line in f:
                    parts = line.split()
                    if parts[3] == "0A":  # LISTEN
                        ip, port = parts[1].split(":")
                        raw = bytes.fromhex(ip)
                        if len(raw) == 4:
                            addr = socket.inet_ntop(socket.AF_INET, raw[::-1])
                        else:
                            addr = socket.inet_ntop(socket.AF_INET6, struct.pack(">4I", *struct.unpack("<4I", raw)))
                        found[int(parts[9])] = (addr, int(port, 16))
        return found

    def descendants(root):
        children = {}
        for p in os.listdir("/proc"):
            if p.isdigit():
                try:
                    with open(f"/proc/{p}/stat") as f:
                        children.setdefault(int(f.read().rsplit(")", 1)[1].split()[1]), []).append(int(p))
                except OSError:
                    pass
        out, todo = [], [root]
        while todo:
            pid = todo.pop()
            out.append(pid)
            todo.extend(children.get(pid, []))
        return out

    init_ray(None, num_cpus=2)

    @ray.remote
    class Probe:
        def pid(self):
            return os.getpid()

    ray.get(Probe.remote().pid.remote())
    sockets = listening()
    found = set()
    for pid in descendants(os.getpid()):
        try:
            fds = os.listdir(f"/proc/{pid}/fd")
        except OSError:
            continue
        for fd in fds:
            try:
                link = os.readlink(f"/proc/{pid}/fd/{fd}")
            except OSError:
                continue
            if link.startswith("socket:[") and int(link[8:-1]) in sockets:
                found.add(sockets[int(link[8:-1])][0])
    print(json.dumps(sorted(found)))
    ray.shutdown()
    """
)


@pytest.mark.skipif(not Path("/proc/net/tcp").exists(), reason="needs Linux /proc")
def test_a_local_run_listens_on_loopback_only_and_never_joins_a_head_ray_start_left():
    env = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER")}
    # a `ray start --head` on this machine leaves its address in <temp>/ray/ray_current_cluster, which a
    # plain ray.init() joins (and refuses to, given num_cpus); a local run must start its own Ray instead
    temp = Path(tempfile.mkdtemp(prefix="atdr-", dir="/tmp"))  # short: Ray's socket paths have a length limit
    (temp / "ray").mkdir()
    (temp / "ray" / "ray_current_cluster").write_text("127.0.0.1:1")
    env["RAY_TMPDIR"] = str(temp)
    try:
        out = subprocess.run([sys.executable, "-c", LISTENING], capture_output=True, text=True, timeout=120, env=env)
    finally:
        shutil.rmtree(temp, ignore_errors=True)
    assert out.returncode == 0, out.stderr[-2000:]
    addresses = json.loads(out.stdout.strip().splitlines()[-1])
    assert addresses, "no listening socket found: the probe is broken"
    assert set(addresses) <= {"127.0.0.1", "::1", "::ffff:127.0.0.1"}, addresses


# ------------------------------------------------------------------ fail early: what cannot be scheduled
def test_a_run_the_cluster_cannot_place_is_refused_at_once(local_ray, tmp_path):
    gpu = load_experiment(_service(tmp_path, "gpu", learner_gpus=1))
    t0 = time.monotonic()
    with pytest.raises(RunError, match=r"learner_gpus 1 per learner, the cluster has 0 GPUs"):
        run_experiment(gpu, progress=False)
    assert time.monotonic() - t0 < 30
    workers = load_experiment(_service(tmp_path, "cpus", num_workers=4))
    with pytest.raises(RunError, match=r"num_workers 4: one CPU per rollout worker, the cluster has 2"):
        check_schedulable(workers)


# ------------------------------------------------------------------ progress within a generation
def test_the_coordinator_reports_what_a_generation_is_doing(local_ray, tmp_path):
    """One PBT generation trains two learners, plays their fitness matches and evaluates them on the zoo."""
    from atdrone.population import ALGORITHMS
    from atdrone.registry_ray import registry_actor
    from atdrone.service.coordinator import Coordinator
    from atdrone.service.experiment import registry_name

    doc = _service(tmp_path, "progress_t", algorithm="pbt", pbt={"population_size": 2}, updates_per_generation=3)
    doc.pop("hola")
    cfg = load_experiment(doc)
    registry = registry_actor(tmp_path / "p.db", name=registry_name(cfg.name))
    coordinator = Coordinator.options(max_concurrency=2).remote(cfg, ALGORITHMS["pbt"], str(tmp_path), None, registry)
    seen: list[str] = []
    ref = coordinator.run_generation.remote()
    while not ray.wait([ref], timeout=0.02)[0]:
        line = ray.get(coordinator.progress.remote())
        if line and (not seen or seen[-1] != line):
            seen.append(line)
    ray.get(ref)
    ray.get(coordinator.release.remote())  # its workers' CPUs (a placement group it made) freed
    ray.kill(coordinator)
    ray.kill(registry)
    assert {"train: learner 2, update 2/3", "train: learner 2, update 3/3"} & set(seen), seen
    assert "evaluate: 2 matches, 8 episodes (0 matches before)" in seen, seen
    assert "zoo: 2 member(s) on zoo1, 4 episodes each" in seen, seen


# ------------------------------------------------------------------ edges: names, signals, fsync, bugs
def test_an_experiment_name_the_mlflow_filters_cannot_hold_is_refused_when_loaded(tmp_path):
    """The experiment name becomes the MLflow experiment and model name (and goes into filter strings): it is
    checked with the run name's rule when the config is loaded, not after every generation has trained."""
    from atdrone.config import ConfigError

    for bad in ("o'brien run", 'say "hi"', "a/b"):
        with pytest.raises(ConfigError, match=r"^experiment: .* is not a run name"):
            load_experiment(_service(tmp_path, "fine", experiment=bad))
    assert load_experiment(_service(tmp_path, "fine", experiment="obrien-run.2")).experiment == "obrien-run.2"


def test_sigterm_ends_the_runs_killed_like_ctrl_c(tmp_path, mlflow_store):
    """`ray job stop` sends SIGTERM: inside run_experiment it raises KeyboardInterrupt, so the parent and the
    nested run end KILLED (not left RUNNING), and the handler is restored afterwards."""
    from atdrone.service.driver import _sigterm_as_interrupt

    uri = mlflow_store(tmp_path / "mlflow.db")
    tracker = Tracker(uri)
    before = signal.getsignal(signal.SIGTERM)
    ids = []
    with (
        pytest.raises(KeyboardInterrupt, match="SIGTERM"),
        _sigterm_as_interrupt(),
        tracker.run("term", "parent") as parent,
        tracker.run("term", "child", nested=True) as child,
    ):
        ids += [parent, child]
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(5)  # the handler raises in this frame long before
    assert signal.getsignal(signal.SIGTERM) == before
    client = mlflow.MlflowClient(tracking_uri=uri)
    assert [client.get_run(i).info.status for i in ids] == ["KILLED", "KILLED"]


def test_atomic_writes_fsync_the_directory_after_the_rename(tmp_path, monkeypatch):
    """The rename is made durable: after os.replace the target's directory is opened and fsynced."""
    import stat

    from atdrone import fileio

    events: list[tuple[str, object]] = []
    real_fsync, real_replace = os.fsync, os.replace

    def fsync(fd: int) -> None:
        mode = os.fstat(fd).st_mode
        events.append(("fsync", "dir" if stat.S_ISDIR(mode) else "file"))
        real_fsync(fd)

    def replace(src, dst) -> None:  # type: ignore[no-untyped-def]
        events.append(("replace", Path(dst).name))
        real_replace(src, dst)

    monkeypatch.setattr(fileio.os, "fsync", fsync)
    monkeypatch.setattr(fileio.os, "replace", replace)
    fileio.atomic_write_text(tmp_path / "sub" / "state.json", "{}")
    assert events == [("fsync", "file"), ("replace", "state.json"), ("fsync", "dir")]
    assert (tmp_path / "sub" / "state.json").read_text() == "{}"


def test_a_key_error_inside_the_deploy_is_reported_as_a_bug_not_a_user_error(tmp_path, monkeypatch, capsys):
    """The deploy turns a missing member or model into its own DeployError; any other KeyError is a bug, so
    the CLI names it an internal error and --debug shows its traceback."""
    import atdrone.deploy.job as job

    def broken(*args, **kwargs):  # type: ignore[no-untyped-def]
        raise KeyError("cf7")

    monkeypatch.setattr(job, "run_deploy", broken)
    assert main(["deploy", "sim_4p2e1o", "--out-dir", str(tmp_path)]) == 1
    assert "internal error: KeyError: cf7" in capsys.readouterr().err
    with pytest.raises(KeyError, match="cf7"):
        main(["--debug", "deploy", "sim_4p2e1o", "--out-dir", str(tmp_path)])


def test_a_best_member_registered_again_by_a_resumed_run_is_the_same_version(tmp_path, mlflow_store):
    """register_checkpoint finds the run's version of the member before making one: a resume that registers
    again gets the same version; another member of the run, or another run, gets a new one."""
    tracker = Tracker(mlflow_store(tmp_path / "mlflow.db"))
    path = _checkpoint(tmp_path / "m.pt", seed=0)
    with tracker.run("again", "run") as run_id:
        first = tracker.register_checkpoint(path, "atdrone-again", 40.0, {"member": "m"})
    with tracker.run("again", "run", run_id=run_id):
        assert tracker.register_checkpoint(path, "atdrone-again", 40.0, {"member": "m"}) == first == "1"
        assert tracker.register_checkpoint(path, "atdrone-again", 30.0, {"member": "n"}) == "2"
    with tracker.run("again", "other"):
        assert tracker.register_checkpoint(path, "atdrone-again", 20.0, {"member": "m"}) == "3"
    versions = tracker.mlflow.MlflowClient().search_model_versions("name = 'atdrone-again'")
    assert len(versions) == 3


def test_metrics_logged_once_per_step_add_no_second_point(tmp_path, mlflow_store):
    tracker = Tracker(mlflow_store(tmp_path / "mlflow.db"))
    with tracker.run("once", "parent") as run_id:
        tracker.log_metrics({"gen/a": 1.0}, step=0, run_id=run_id, once=True)
        tracker.log_metrics({"gen/a": 1.0, "gen/b": 2.0}, step=0, run_id=run_id, once=True)  # b is new at 0
        tracker.log_metrics({"gen/a": 3.0}, step=1, once=True)
        tracker.log_metrics({"gen/a": 3.0}, step=1, once=True)
    client = tracker.mlflow.MlflowClient()
    assert [(m.step, m.value) for m in client.get_metric_history(run_id, "gen/a")] == [(0, 1.0), (1, 3.0)]
    assert [(m.step, m.value) for m in client.get_metric_history(run_id, "gen/b")] == [(0, 2.0)]


def test_two_runs_of_one_name_in_two_out_dirs_keep_their_own_mlflow_runs(tmp_path, mlflow_store):
    """The records of a run are found by its identifier, not its name: resuming b/exp ends and removes b's dead
    nested runs only, never the live ones of a/exp (same name, same store)."""
    from atdrone.rundir import new_run_id
    from atdrone.service.driver import run_tags

    a, b = run_tags("exp", new_run_id()), run_tags("exp", new_run_id())
    assert a["atdrone.run"] == b["atdrone.run"] == "exp" and a["atdrone.run_id"] != b["atdrone.run_id"]
    tracker = Tracker(mlflow_store(tmp_path / "mlflow.db"))
    client = tracker.mlflow.MlflowClient()
    ident = tracker.experiment("exp")
    live = client.create_run(ident, tags={**a, "atdrone.generation": "1"}).info.run_id
    dead = client.create_run(ident, tags={**b, "atdrone.generation": "1"}).info.run_id
    kept = client.create_run(ident, tags={**b, "atdrone.generation": "0"}).info.run_id
    client.set_terminated(kept, "FINISHED")
    assert tracker.forget_runs("exp", b, "atdrone.generation", 1, keep="") == [dead]
    assert tracker.end_stale_runs("exp", b) == []
    assert client.get_run(dead).info.lifecycle_stage == "deleted" and client.get_run(dead).info.status == "KILLED"
    assert client.get_run(live).info.status == "RUNNING" and client.get_run(live).info.lifecycle_stage == "active"
    assert client.get_run(kept).info.status == "FINISHED" and client.get_run(kept).info.lifecycle_stage == "active"
