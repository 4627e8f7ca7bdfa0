"""The code blocks of README.md and docs/ run as written.

A fenced block tagged ``sh`` or ``python`` runs in a scratch folder (``configs/`` linked
in, MLflow in the folder) unless the line before it is a marker comment
``<!-- docs-test: KIND -->`` with KIND one of :data:`SKIP` (what CONTRIBUTING.md
documents). A ``json`` block must parse. A block without a language that holds commands
is refused, so a command cannot hide from this test.

After ``make demo``, ``ATDRONE_DOCS_DEMO=1 .venv/bin/python -m pytest tests/test_docs.py``
also runs the ``demo`` blocks, in the repository root where the demo left its run
(``runs/hola_quick``, ``mlflow.db``): what a new user types after the demo.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PAGES = [ROOT / "README.md", ROOT / "CONTRIBUTING.md", *sorted((ROOT / "docs").rglob("*.md"))]
SKIP = {
    "long": "takes minutes (training, make demo)",
    "demo": "needs make demo's outputs",
    "ray": "starts and stops a Ray head of its own, after make demo",
    "hardware": "needs drones, a radio or a Ray cluster",
}
RUN = ("sh", "python")
_FENCE = re.compile(r"^```(\S*)\s*$")
_MARKER = re.compile(r"^<!--\s*docs-test:\s*(\S+)\s*-->\s*$")
_COMMAND = re.compile(r"^(atdrone|ray|mlflow|make|python|\.venv/bin/|kubectl|pip) ")


@dataclass(frozen=True)
class Block:
    page: Path
    line: int
    lang: str
    marker: str | None
    text: str

    @property
    def name(self) -> str:
        return f"{self.page.relative_to(ROOT)}:{self.line}"


def blocks(page: Path) -> list[Block]:
    """The fenced code blocks of a Markdown page, with the marker on the line before each."""
    found, lines = [], page.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        opening = _FENCE.match(lines[i])
        if opening is None:
            i += 1
            continue
        end = next((j for j in range(i + 1, len(lines)) if lines[j].strip() == "```"), None)
        assert end is not None, f"{page.relative_to(ROOT)}:{i + 1}: a code block is not closed"
        marker = _MARKER.match(lines[i - 1]) if i > 0 else None
        text = "\n".join(lines[i + 1 : end]) + "\n"
        found.append(Block(page, i + 1, opening.group(1), marker.group(1) if marker else None, text))
        i = end + 1
    return found


ALL = [b for page in PAGES for b in blocks(page)]
RUNNABLE = [b for b in ALL if b.lang in RUN and b.marker is None]
AFTER_DEMO = [b for b in ALL if b.lang in RUN and b.marker == "demo"]
RAY_JOBS = [b for b in ALL if b.lang == "sh" and b.marker == "ray"]


def test_the_pages_have_blocks_and_some_run() -> None:
    assert ROOT / "docs" / "index.md" in PAGES
    assert len(RUNNABLE) >= 4, [b.name for b in RUNNABLE]


def test_the_user_pages_name_no_issue_numbers() -> None:
    """Users cannot see the project's issue tracker: README.md and docs/ never cite it."""
    cited = re.compile(r"\bissues? #?[0-9]+", re.IGNORECASE)
    hits = [
        f"{page.relative_to(ROOT)}:{n}"
        for page in PAGES
        if page.name != "CONTRIBUTING.md"
        for n, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1)
        if cited.search(line)
    ]
    assert not hits, f"issue numbers in user pages: {hits}"


@pytest.mark.parametrize("block", ALL, ids=lambda b: b.name)
def test_every_block_is_tagged_and_marked_with_a_known_kind(block: Block) -> None:
    if block.marker is not None:
        assert block.marker in SKIP, f"{block.name}: unknown marker {block.marker!r} (known: {', '.join(SKIP)})"
        assert block.lang in RUN, f"{block.name}: only sh and python blocks take a docs-test marker"
    if block.lang == "":
        commands = [line for line in block.text.splitlines() if _COMMAND.match(line)]
        assert not commands, f"{block.name}: commands in a block without a language (tag it sh): {commands}"
    if block.lang == "json":
        json.loads(block.text)


@pytest.fixture
def scratch(tmp_path: Path) -> tuple[Path, dict[str, str]]:
    (tmp_path / "configs").symlink_to(ROOT / "configs")
    env = {
        **os.environ,
        "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
        "MLFLOW_TRACKING_URI": f"sqlite:///{tmp_path / 'mlflow.db'}",
        "COLUMNS": "120",
        # one torch thread: in the suite a block's second thread can land on the core the flights' busy loop holds,
        # at nice +15 against its 0, and every parallel region waits for it (a 5 s block took 73 s); the metrics
        # are the same to the last bit on one thread or two (benchmarks/eval_threads.py)
        "OMP_NUM_THREADS": "1",
    }
    env.pop("ATDRONE_REGISTRY", None)
    return tmp_path, env


@pytest.mark.timeout(310)
@pytest.mark.parametrize("block", RUNNABLE, ids=lambda b: b.name)
def test_block_runs_as_written(block: Block, scratch: tuple[Path, dict[str, str]]) -> None:
    cwd, env = scratch
    if block.lang == "python":
        command = [sys.executable, "-c", block.text]
    else:
        command = ["bash", "-euo", "pipefail", "-c", block.text]
    done = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, (
        f"{block.name} failed ({done.returncode}):\n{done.stdout[-2000:]}\n{done.stderr[-3000:]}"
    )
    assert "Traceback" not in done.stderr, f"{block.name}:\n{done.stderr[-3000:]}"


@pytest.mark.skipif(not os.environ.get("ATDRONE_DOCS_DEMO"), reason="after make demo, with ATDRONE_DOCS_DEMO=1")
@pytest.mark.timeout(600)
@pytest.mark.parametrize("block", AFTER_DEMO, ids=lambda b: b.name)
def test_block_runs_after_the_demo(block: Block, tmp_path: Path) -> None:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    env.pop("MLFLOW_TRACKING_URI", None)
    text = block.text
    if text.startswith("mlflow ui"):  # a server: it must start and answer on /health, then it is stopped
        _serves([*text.splitlines()[0].split("#")[0].split(), "--port", "5999"], env)
        return
    done = subprocess.run(["bash", "-euo", "pipefail", "-c", text], cwd=ROOT, env=env, capture_output=True, text=True)
    output = f"{done.stdout[-3000:]}\n{done.stderr[-3000:]}"
    assert done.returncode == 0, f"{block.name} failed ({done.returncode}):\n{output}"
    assert "Traceback" not in done.stderr and "Warning" not in done.stderr, f"{block.name}:\n{output}"


@pytest.mark.skipif(not os.environ.get("ATDRONE_DOCS_DEMO"), reason="after make demo, with ATDRONE_DOCS_DEMO=1")
@pytest.mark.timeout(900)
@pytest.mark.parametrize("block", RAY_JOBS, ids=lambda b: b.name)
def test_the_ray_job_block_runs_after_the_demo_and_stops_only_its_head(block: Block) -> None:
    """The walkthrough as written, in the repository root after ``make demo``: it starts a Ray head of its own,
    submits a training job under a fresh run name and an evaluation job, and stops that head alone; the
    demo's run and champion are untouched."""
    import shutil
    import time

    import mlflow

    run_dir = ROOT / "runs" / "hola_job"
    shutil.rmtree(run_dir, ignore_errors=True)  # a run of that name from an earlier try: the job starts afresh
    store = f"sqlite:///{ROOT / 'mlflow.db'}"
    champion = mlflow.MlflowClient(store).get_model_version_by_alias("atdrone-hola_quick", "champion").version
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    env.pop("MLFLOW_TRACKING_URI", None)
    env.pop("RAY_ADDRESS", None)
    done = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", block.text], cwd=ROOT, env=env, capture_output=True, text=True
    )
    output = f"{done.stdout[-4000:]}\n{done.stderr[-4000:]}"
    try:
        assert done.returncode == 0, f"{block.name} failed ({done.returncode}):\n{output}"
        assert done.stdout.count("succeeded") >= 2, output  # both jobs
        assert "run: hola_job" in done.stdout and (run_dir / "registry.db").is_file()
        after = mlflow.MlflowClient(store).get_model_version_by_alias("atdrone-hola_quick", "champion").version
        assert after == champion  # the job's run registered atdrone-hola_job, and the demo's champion stayed
        deadline = time.monotonic() + 30  # the head's GCS port closes: the block stopped what it started
        while _listening(6390):
            assert time.monotonic() < deadline, "the block's Ray head still listens on 6390"
            time.sleep(1)
    finally:
        shutil.rmtree(run_dir, ignore_errors=True)
        (ROOT / "ray_head.log").unlink(missing_ok=True)


def _listening(port: int) -> bool:
    import socket

    with socket.socket() as probe:
        return probe.connect_ex(("127.0.0.1", port)) == 0


def _serves(command: list[str], env: dict[str, str]) -> None:
    """Start ``command`` (a web server on port 5999) in its own process group, wait for /health, stop the group."""
    import signal
    import time
    import urllib.request

    server = subprocess.Popen(
        command, cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True
    )
    try:
        deadline = time.monotonic() + 180
        while True:
            assert server.poll() is None, f"{' '.join(command)} exited with {server.returncode}"
            try:
                with urllib.request.urlopen("http://127.0.0.1:5999/health", timeout=5) as answer:
                    assert answer.status == 200
                    return
            except OSError:
                assert time.monotonic() < deadline, f"{' '.join(command)} did not answer within 180 s"
                time.sleep(1)
    finally:
        os.killpg(server.pid, signal.SIGTERM)
        try:
            server.wait(timeout=30)
        except subprocess.TimeoutExpired:
            os.killpg(server.pid, signal.SIGKILL)
            server.wait()
