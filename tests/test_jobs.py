"""The Ray job entrypoints (jobs/) and the cluster configs (cluster/).

The last test starts a real Ray head (``ray start --head --block``, ports picked free,
its own temp dir, token auth disabled), submits jobs/evaluate.py and a one-generation
jobs/train.py with JobSubmissionClient, as ``ray job submit --working-dir .`` does, and
stops the head by signalling the process it started (never ``ray stop``, which would end
every Ray on the machine).
"""

from __future__ import annotations

import json
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import pandas as pd
import pytest
import yaml

REPO = Path(__file__).resolve().parents[1]
PY = sys.executable
EVALUATE = REPO / "jobs" / "evaluate.py"
TRAIN = REPO / "jobs" / "train.py"
EXCLUDES = [".venv", "runs", "*.db", ".git", "mlruns", "demo_out", "eval_out"]
# a one-generation HOLA-Drone V2 run small enough for a 2-core machine
TINY_TRAIN = (
    "--generations 1 --updates-per-generation 2 --num-workers 1 "
    '--ppo \'{"epochs": 2, "num_envs": 4, "rollout_steps": 16}\' '
    "--eval-episodes 2 --final-episodes 2 --final-zoo zoo1 --no-gif"
)


def _run(*args: str | Path, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([PY, *map(str, args)], cwd=REPO, capture_output=True, text=True, timeout=timeout)


# ------------------------------------------------------------- the scripts
def test_evaluate_script_writes_its_outputs(tmp_path: Path) -> None:
    out = tmp_path / "eval"
    args = ("--policy", "greedy", "--task", "4p2e1o", "--zoo", "zoo1", "--episodes", "20", "--out-dir", out)
    proc = _run(EVALUATE, *args)
    assert proc.returncode == 0, proc.stderr
    assert "jobs/evaluate.py: greedy evaluated on 1 of 1 task x zoo cells, 20 episodes" in proc.stdout
    assert "SUC %" in proc.stdout  # the table, as `atdrone evaluate` prints it
    report = json.loads((out / "greedy_4p2e1o_zoo1.json").read_text())
    (cell,) = report["cells"]
    assert cell["status"] == "ok" and cell["task"] == "4p2e1o" and cell["zoo"] == "zoo1"
    assert cell["summary"]["episodes"] == 20 and 0 <= cell["summary"]["SUC"] <= 100
    assert [row["seed"] for row in cell["per_seed"]] == [0]
    episodes = pd.read_csv(out / "greedy_4p2e1o_zoo1.csv")
    assert len(episodes) == 20 and {"success", "collided", "length", "return"} <= set(episodes.columns)


def test_bad_task_exits_non_zero_with_one_line(tmp_path: Path) -> None:
    proc = _run(EVALUATE, "--policy", "greedy", "--task", "4p9e9o", "--episodes", "5", "--out-dir", tmp_path)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("jobs/evaluate.py: error:") and "4p9e9o" in lines[0]
    assert not any(tmp_path.iterdir())


@pytest.fixture
def keep_signal_handlers() -> Iterator[None]:
    """The test process's SIGTERM and SIGINT handlers restored after a script's main installed its own."""
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGINT)}
    yield
    for s, h in handlers.items():
        signal.signal(s, h)


@pytest.mark.parametrize(("signum", "code"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)], ids=["sigterm", "sigint"])
def test_a_stop_signal_ends_the_evaluate_script_in_one_line_with_the_signals_status(
    signum: signal.Signals,
    code: int,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    load_script: Callable[[Path], Any],
    keep_signal_handlers: None,
) -> None:
    """`ray job stop` (SIGTERM) or Ctrl-C while the cells play: no traceback, no report, one line with the command
    that runs it again, and the shell's status for that signal."""
    from atdrone.teams import evaluation

    def stopped(*args: Any, **kwargs: Any) -> None:
        os.kill(os.getpid(), signum)
        time.sleep(30)  # the handler raises in this frame long before
        raise AssertionError("the signal was not handled")

    def not_handled(signum: int, frame: Any) -> None:
        raise AssertionError(f"{signal.Signals(signum).name} reached the test's handler: the script installed none")

    signal.signal(signum, not_handled)  # what the script must replace (the fixture restores the test's own)
    monkeypatch.setattr(evaluation, "evaluate_grid", stopped)
    args = ["--policy", "greedy", "--episodes", "5", "--out-dir", str(tmp_path / "eval")]
    assert load_script(EVALUATE).main(args) == code
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == [
        "jobs/evaluate.py: interrupted; the report is written once every cell has played; run it again with: "
        f"python jobs/evaluate.py {' '.join(args)}"
    ]
    assert not (tmp_path / "eval").exists()


@pytest.mark.parametrize(
    ("script", "args", "needle"),
    [
        (EVALUATE, ["--policy", "no_such_policy.pt", "--episodes", "5"], "no_such_policy.pt"),
        (EVALUATE, ["--policy", "greedy", "--zoo", "zoo9", "--episodes", "5"], "zoo9"),
        (TRAIN, ["configs/experiments/hola_quick.json", "--final-zoo", "zoo9"], "final_zoo"),
        (TRAIN, ["configs/experiments/hola_quick.json", "--updates_per_generation", "0"], "updates_per_generation"),
        (TRAIN, ["configs/experiments/no_such.json"], "no_such"),
    ],
)
def test_bad_input_is_refused_in_one_line(
    script: Path,
    args: list[str],
    needle: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    load_script: Callable[[Path], Any],
    keep_signal_handlers: None,
) -> None:
    main = load_script(script).main
    assert main([*args, "--out" if script == EVALUATE else "--out-dir", str(tmp_path)]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"jobs/{script.name}: error:") and needle in lines[0], lines
    assert not any(tmp_path.iterdir())


# ---------------------------------------------------------- cluster configs
@pytest.mark.parametrize("name", ["onprem.yaml", "aws.yaml"])
def test_launcher_configs_pass_rays_schema(name: str) -> None:
    from ray.autoscaler._private.util import prepare_config, validate_config

    config = yaml.safe_load((REPO / "cluster" / name).read_text())
    assert config["provider"]["type"] == ("local" if name == "onprem.yaml" else "aws")
    validate_config(prepare_config(config))
    setup = " ".join(config["setup_commands"])
    assert setup.index("torch==2.13.0") < setup.index("-e ~/atdrone")
    assert config["file_mounts"] == {"~/atdrone": ".", "~/.ray/auth_token": "~/.ray/auth_token"}  # one token
    assert any("ray start --head" in c for c in config["head_start_ray_commands"])
    assert any("ray start --address" in c for c in config["worker_start_ray_commands"])
    if name == "aws.yaml":
        types = config["available_node_types"]
        assert types["learner_gpu"]["resources"] == {"GPU": 1}
        assert config["head_node_type"] in types


def test_rayjob_manifest_runs_a_script_that_exists() -> None:
    manifest = yaml.safe_load((REPO / "cluster" / "rayjob.yaml").read_text())
    assert manifest["apiVersion"] == "ray.io/v1" and manifest["kind"] == "RayJob"
    spec = manifest["spec"]
    argv = shlex.split(spec["entrypoint"])
    assert argv[:3] == ["python", "jobs/train.py", "configs/experiments/hola_quick.json"]
    assert (REPO / argv[1]).is_file() and (REPO / argv[2]).is_file()
    assert "working_dir" in yaml.safe_load(spec["runtimeEnvYAML"])
    cluster = spec["rayClusterSpec"]
    assert cluster["headGroupSpec"]["template"]["spec"]["containers"]
    assert all(g["template"]["spec"]["containers"] for g in cluster["workerGroupSpecs"])


def _head_commands(name: str) -> str:
    return " ".join(yaml.safe_load((REPO / "cluster" / name).read_text())["head_start_ray_commands"])


@pytest.mark.parametrize("name", ["onprem.yaml", "aws.yaml"])
def test_launcher_heads_keep_the_job_api_on_loopback_with_token_auth(name: str) -> None:
    """The dashboard / job API runs whatever it is sent: the heads bind it to 127.0.0.1 (reached through
    `ray dashboard`, an SSH tunnel) and start with token authentication on."""
    head = _head_commands(name)
    assert "--dashboard-host=127.0.0.1" in head and "0.0.0.0" not in head
    assert "RAY_AUTH_MODE=token" in head


def test_rayjob_keeps_the_job_api_on_loopback_the_registry_local_and_mlflow_on_a_server() -> None:
    """KubeRay: the head's dashboard on 127.0.0.1 with token auth, the submitter a sidecar of the head pod
    (the only way to reach it); the registry on a claim only the head pod mounts (the driver and the
    registry actor run there; sqlite's WAL does not work on NFS / EFS), checkpoints on the shared claim
    every pod mounts; MLflow a tracking server on the head's 127.0.0.1 with its store in a database."""
    text = (REPO / "cluster" / "rayjob.yaml").read_text()
    manifest = yaml.safe_load(text)
    spec = manifest["spec"]
    cluster = spec["rayClusterSpec"]
    head = cluster["headGroupSpec"]
    assert head["rayStartParams"]["dashboard-host"] == "127.0.0.1" and "0.0.0.0" not in text
    assert cluster["authOptions"] == {"mode": "token"} and spec["submissionMode"] == "SidecarMode"
    job_env = yaml.safe_load(spec["runtimeEnvYAML"])["env_vars"]

    def claim(template: dict, folder: str) -> str | None:
        """The claim behind the mount of ``folder`` in the Ray container of a pod template (None: none)."""
        pod = template["spec"]
        ray_container = pod["containers"][0]
        mounts = [m for m in ray_container["volumeMounts"] if folder.startswith(m["mountPath"])]
        if not mounts:
            return None
        volume = next(v for v in pod["volumes"] if v["name"] == mounts[0]["name"])
        return volume["persistentVolumeClaim"]["claimName"]

    assert head["template"]["spec"]["containers"][0]["name"] == "ray-head"
    assert claim(head["template"], job_env["ATDRONE_OUT_DIR"]) == "atdrone-shared"
    assert claim(head["template"], job_env["ATDRONE_REGISTRY_DIR"]) == "atdrone-registry"
    for group in cluster["workerGroupSpecs"]:
        assert claim(group["template"], job_env["ATDRONE_OUT_DIR"]) == "atdrone-shared"
        assert claim(group["template"], job_env["ATDRONE_REGISTRY_DIR"]) is None, group["groupName"]
    assert job_env["MLFLOW_TRACKING_URI"] == "http://127.0.0.1:5000"
    (server,) = [c for c in head["template"]["spec"]["containers"] if c["name"] == "mlflow"]
    argv = server["command"]
    assert argv[:2] == ["mlflow", "server"] and argv[argv.index("--host") + 1] == "127.0.0.1"
    assert argv[argv.index("--port") + 1] == "5000" and "sqlite" not in argv[argv.index("--backend-store-uri") + 1]
    assert any(
        g["template"]["spec"]["containers"][0]["resources"]["limits"].get("nvidia.com/gpu")
        for g in cluster["workerGroupSpecs"]
    )


def _guide_commands() -> list[list[str]]:
    """Every command of the cluster guide's code blocks as argv (continued lines joined, comments dropped)."""
    text = (REPO / "cluster" / "README.md").read_text()
    commands = []
    for block in re.findall(r"^```[^\n]*\n(.*?)^```", text, flags=re.M | re.S):
        for line in block.replace("\\\n", " ").splitlines():
            if argv := shlex.split(line, comments=True):
                commands.append(argv)
    return commands


def _parse(parser: Any, argv: list[str], command: list[str]) -> Any:
    """``parser``'s reading of ``argv``, or a failure naming the guide's command it refused."""
    try:
        return parser.parse_args(argv)
    except SystemExit:
        pytest.fail(f"the cluster guide's command is refused: {shlex.join(command)}")


def test_the_cluster_guides_job_commands_are_what_the_scripts_take(load_script: Callable[[Path], Any]) -> None:
    """Every `python jobs/*.py ...` of the guide's code blocks parses with the script's own parser, names a config,
    task and zoo that load, and gives the run directory and the registry absolute paths (the guide's storage
    rule); every flag of the guide's script table is an option of the script; the GPU section's
    `--learner-gpus 1` and `"learner_gpus": 1` reach the experiment config."""
    from atdrone.config import load_task
    from atdrone.policies.zoo import load_zoo
    from atdrone.service.experiment import load_experiment

    scripts = {"jobs/train.py": load_script(TRAIN), "jobs/evaluate.py": load_script(EVALUATE)}
    ran = {name: 0 for name in scripts}
    for command in _guide_commands():
        for name, script in scripts.items():
            if name not in command:
                continue
            args = _parse(script.build_parser(), command[command.index(name) + 1 :], command)
            ran[name] += 1
            absolute = ("/", "$PWD/")
            if name == "jobs/train.py":
                assert load_experiment(args.config).name
                assert args.out_dir.startswith(absolute), command
                assert args.registry_dir is None or args.registry_dir.startswith(absolute), command
            else:
                load_task(args.task), load_zoo(args.zoo)
                assert str(args.out_dir).startswith(absolute), command
    assert ran == {"jobs/train.py": 2, "jobs/evaluate.py": 1}  # sections 1 and 3 train, section 1 evaluates
    guide = (REPO / "cluster" / "README.md").read_text()
    for name, script in scripts.items():
        (row,) = [line for line in guide.splitlines() if line.startswith(f"| `{name} ")]
        flags = set(re.findall(r"(?<![\w-])--[a-z][a-z-]*", row))
        assert len(flags) >= 5 and flags <= set(script.build_parser()._option_string_actions), (name, flags)
    args = _parse(scripts["jobs/train.py"].build_parser(), ["c.json", "--learner-gpus", "1"], ["--learner-gpus"])
    assert args.learner_gpus == 1.0 and '"learner_gpus": 1' in guide and "--learner-gpus 1` overrides it" in guide
    config = REPO / "configs" / "experiments" / "hola_quick.json"
    assert load_experiment(config, learner_gpus=1).learner_gpus == 1
    assert load_experiment(config).learner_gpus == 0  # the guide: "default 0: learners run on CPUs"


def test_the_cluster_guides_ray_and_mlflow_commands_are_options_of_those_tools() -> None:
    """The guide's `ray start` and `mlflow server` lines parse as those commands (their click parsers) and keep
    the job API and the tracking server on 127.0.0.1; the tracking server's store is a database, not sqlite."""
    import click
    from mlflow.cli import cli as mlflow_cli
    from ray.scripts.scripts import start as ray_start

    seen = set()
    for command in _guide_commands():
        argv = [word for word in command if "=" not in word or word.startswith("-")]  # env assignments dropped
        if argv[:2] == ["ray", "start"]:
            tool: click.Command = ray_start
        elif argv[:2] == ["mlflow", "server"]:
            tool = mlflow_cli.commands["server"]
        else:
            continue
        seen.add(argv[1])
        with tool.make_context(argv[1], argv[2:], resilient_parsing=True) as context:
            params = context.params
        unknown = [w.split("=")[0] for w in argv[2:] if w.startswith("--")]
        known = {opt for p in tool.params for opt in p.opts}
        assert set(unknown) <= known, (command, set(unknown) - known)
        if argv[1] == "start":
            assert params["head"] and params["dashboard_host"] == "127.0.0.1", command
        else:
            assert params["host"] == "127.0.0.1" and params["backend_store_uri"].startswith("postgresql://"), command
    assert seen == {"start", "server"}


def test_a_damaged_service_state_or_another_registry_dir_is_one_line_and_status_2(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    load_script: Callable[[Path], Any],
) -> None:
    from atdrone.service.experiment import load_experiment

    monkeypatch.setenv("ATDRONE_REGISTRY_DIR", "")  # unset, and restored after main sets it for --registry-dir
    main = load_script(TRAIN).main
    args = ["configs/experiments/hola_quick.json", "--resume", "--out-dir", str(tmp_path)]
    run_dir = tmp_path / "hola_quick"
    run_dir.mkdir()
    (run_dir / "service_state.json").write_text("{not json")
    assert main(args) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and "unreadable service state" in lines[0] and lines[0].startswith("jobs/train.py: error:")
    cfg = load_experiment("configs/experiments/hola_quick.json", out_dir=str(tmp_path))
    (run_dir / "config.json").write_text(json.dumps(cfg.to_dict()))
    state = {"coordinator": {"generation": 1}, "registry": str(run_dir / "registry.db")}
    (run_dir / "service_state.json").write_text(json.dumps(state))
    assert main([*args, "--registry-dir", str(tmp_path / "local")]) == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and f"keeps its registry at {run_dir / 'registry.db'}" in lines[0], lines


# ------------------------------------------------------------ a real head
def _free_ports(n: int) -> list[int]:
    with ExitStack() as stack:
        socks = [stack.enter_context(socket.socket()) for _ in range(n)]
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [s.getsockname()[1] for s in socks]


@pytest.fixture(scope="module")
def ray_head() -> Iterator[str]:
    """A Ray head with the dashboard (job API) on a free port; yields its address."""
    from ray.job_submission import JobSubmissionClient

    names = (
        "port",
        "dashboard-port",
        "ray-client-server-port",
        "dashboard-agent-listen-port",
        "dashboard-agent-grpc-port",
        "metrics-export-port",
        "node-manager-port",
        "object-manager-port",
        "runtime-env-agent-port",
    )
    ports = dict(zip(names, _free_ports(len(names)), strict=True))
    temp_dir = tempfile.mkdtemp(prefix="atdr-ray-", dir="/tmp")  # short: Ray's socket paths have a length limit
    env = {k: v for k, v in os.environ.items() if k != "RAY_ADDRESS"}
    # ~/.ray/auth_token, once any local ray.init made it, switches a new head to token auth; this test
    # head opts out so the client needs no token. The entrypoints' `python` is this venv's.
    env.update(RAY_AUTH_MODE="disabled", PATH=f"{Path(PY).parent}{os.pathsep}{env.get('PATH', '')}")
    cmd = [
        str(Path(PY).parent / "ray"),
        "start",
        "--head",
        "--block",
        "--num-cpus=2",
        "--include-dashboard=true",
        "--dashboard-host=127.0.0.1",
        "--disable-usage-stats",
        f"--temp-dir={temp_dir}",
        *(f"--{k}={v}" for k, v in ports.items()),
    ]
    log_path = Path(temp_dir + ".log")
    with open(log_path, "w") as log:
        head = subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
    address = f"http://127.0.0.1:{ports['dashboard-port']}"
    try:
        deadline = time.monotonic() + 60
        while True:
            if head.poll() is not None:
                pytest.fail(f"ray start --head exited with {head.returncode}:\n{log_path.read_text()[-3000:]}")
            try:
                JobSubmissionClient(address).list_jobs()
                break
            except Exception as exc:
                if time.monotonic() > deadline:
                    pytest.fail(f"the Ray head's job API did not answer in 60 s: {exc}")
                time.sleep(0.5)
        yield address
    finally:
        head.send_signal(signal.SIGTERM)  # `ray start --block` stops the processes it started
        try:
            head.wait(timeout=40)
        except subprocess.TimeoutExpired:
            os.killpg(head.pid, signal.SIGKILL)  # the session this test created for the head
            head.wait(timeout=10)
        shutil.rmtree(temp_dir, ignore_errors=True)
        log_path.unlink(missing_ok=True)


def _wait(client, job_id: str, timeout: float) -> str:
    deadline = time.monotonic() + timeout
    while not (status := client.get_job_status(job_id)).is_terminal():
        if time.monotonic() > deadline:
            client.stop_job(job_id)
            return f"TIMEOUT after {timeout:.0f}s ({status})"
        time.sleep(0.5)
    return str(status)


NO_AGENT = "No available agent to submit job"  # Ray's job API, its head node's job agent not yet registered


def _submit(client, timeout: float = 120.0, **job: Any) -> str:
    """Submit a job, again while the head says its job agent is not up yet: the job API answers before the agent
    registers, and the head waits only 10 s for it (Ray's WAIT_AVAILABLE_AGENT_TIMEOUT), which a starved host's
    agent start can outlast (2026-12-01: the suite's submission was refused so). Any other refusal raises."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            return str(client.submit_job(**job))
        except RuntimeError as exc:
            if NO_AGENT not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(1.0)


def test_a_submission_is_made_again_only_while_the_head_has_no_job_agent(monkeypatch) -> None:
    monkeypatch.setattr(time, "sleep", lambda _s: None)

    class Head:  # answers as Ray's job API does: refused twice while its agent starts, then the job's id
        def __init__(self, refusal: str) -> None:
            self.calls, self.refusal = 0, refusal

        def submit_job(self, **job: Any) -> str:
            self.calls += 1
            if self.calls <= 2:
                raise RuntimeError(f"Request failed with status code 500: {self.refusal}.")
            return "raysubmit_1"

    starting = Head(f"{NO_AGENT}, please try again later.")
    assert _submit(starting, entrypoint="true") == "raysubmit_1" and starting.calls == 3
    broken = Head("Traceback: runtime_env invalid")
    with pytest.raises(RuntimeError, match="runtime_env invalid"):
        _submit(broken, entrypoint="true")
    assert broken.calls == 1


def test_jobs_submitted_to_a_ray_head_succeed(ray_head: str, tmp_path: Path) -> None:
    from ray.job_submission import JobSubmissionClient

    client = JobSubmissionClient(ray_head)
    runtime_env = {"working_dir": str(REPO), "excludes": EXCLUDES}
    evaluate = _submit(
        client,
        entrypoint="python jobs/evaluate.py --policy greedy --task 4p2e1o --zoo zoo1 --episodes 10 "
        f"--out-dir {tmp_path}",
        runtime_env=runtime_env,
    )
    train = _submit(
        client,
        entrypoint=f"python jobs/train.py configs/experiments/hola_quick.json --name jobtest {TINY_TRAIN} "
        f"--out-dir {tmp_path / 'runs'} --tracking-uri sqlite:///{tmp_path / 'mlflow.db'}",
        runtime_env=runtime_env,
    )
    # a deadline for a hung job, not a speed check: on a starved host the train job alone took over 75 s
    outcomes = {job: _wait(client, job, timeout=300) for job in (evaluate, train)}
    logs = {job: client.get_job_logs(job) for job in (evaluate, train)}
    for job, outcome in outcomes.items():
        assert outcome == "SUCCEEDED", f"{job}: {outcome}\n{logs[job][-3000:]}"

    assert "greedy evaluated on 1 of 1 task x zoo cells, 10 episodes" in logs[evaluate]
    assert json.loads((tmp_path / "greedy_4p2e1o_zoo1.json").read_text())["cells"][0]["summary"]["episodes"] == 10

    assert "population of jobtest (hola, 4p2e1o)" in logs[train] and "jobs/train.py: done" in logs[train]
    run_dir = tmp_path / "runs" / "jobtest"
    population = pd.read_csv(run_dir / "population.csv")
    # one generation: hola_quick's Pi_0, two self-play seeds at two skill levels
    assert list(population["member"]) == [f"hola-g0-{i}" for i in range(4)] and "zoo1_SUC" in population.columns
    assert (run_dir / "registry.db").is_file() and (tmp_path / "mlflow.db").is_file()
    assert json.loads((run_dir / "service_state.json").read_text())["coordinator"]["generation"] == 1
