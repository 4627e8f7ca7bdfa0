"""The benchmark job through the real service on the session's Ray: a driver SIGKILLed after its first cell
is finished by a second invocation that runs only the missing cells, and reports what an uninterrupted run
of the same grid reports."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import mlflow
import pandas as pd
from conftest import tiny_benchmark

from atdrone.benchmark.cells import load_benchmark
from atdrone.benchmark.job import STATE_FILE, run_benchmark

REPO = Path(__file__).resolve().parent.parent
CSVS = ("evaluations", "table", "paired", "normalised", "aggregate", "improvement")


def _driver(doc: dict[str, Any], tmp_path: Path, address: str, uri: str) -> subprocess.Popen[bytes]:
    """``atdrone benchmark`` in a process of its own, joined to the session's Ray."""
    path = tmp_path / f"{doc['name']}.json"
    path.write_text(json.dumps(doc))
    command = [sys.executable, "-m", "atdrone.cli", "benchmark", str(path), "--address", address]
    command += ["--tracking-uri", uri, "--no-progress"]
    return subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)


def _report(results: Path, name: str) -> dict[str, Any]:
    """What must be equal between two runs of one grid: the text (CPU-seconds aside) and the CSVs."""
    text = (results / "report.md").read_text().replace(name, "NAME")
    text = re.sub(r"\| [\d,]+ \|\n", "| CPU |\n", text)  # the budget table's last column: timings
    frames = {n: (results / f"{n}.csv").read_bytes() for n in CSVS}  # exactly, byte for byte
    budget = pd.read_csv(results / "budget.csv").drop(columns="cpu_s")
    return {"text": text, "budget": budget, **frames}


def test_a_killed_benchmark_finishes_only_its_missing_cells_and_reports_as_an_uninterrupted_one(
    local_ray, tmp_path, mlflow_store, capsys
):
    uri = mlflow_store(tmp_path / "mlflow.db")
    whole, killed = tiny_benchmark(tmp_path, "whole"), tiny_benchmark(tmp_path, "killed")
    reference = _driver(whole, tmp_path, local_ray, uri)  # beside the killed one: one CPU each
    victim = _driver(killed, tmp_path, local_ray, uri)
    folder = tmp_path / "bench" / "killed"
    first = folder / "cells" / "sp-4p2e1o-s0.json"
    deadline = time.monotonic() + 240
    while not first.exists():
        assert victim.poll() is None, victim.communicate()[0].decode()[-3000:]
        assert time.monotonic() < deadline, "the first cell never finished"
        time.sleep(0.2)
    os.kill(victim.pid, signal.SIGKILL)
    victim.wait()
    kept = first.read_bytes()
    assert sorted(p.name for p in (folder / "cells").glob("*.json")) == ["sp-4p2e1o-s0.json"]  # killed mid-way
    parent = json.loads((folder / STATE_FILE).read_text())["mlflow_run_id"]

    capsys.readouterr()  # no wait for the dead driver's cells to go: the resumed one queues for a CPU
    summary = run_benchmark(load_benchmark(killed), address=local_ray, tracking_uri=uri)
    out, _ = reference.communicate(timeout=300)
    assert reference.returncode == 0, out.decode()[-3000:]
    assert "3 cells: 1 done, 2 to run" in capsys.readouterr().out
    assert first.read_bytes() == kept  # the finished cell was not run again
    assert summary["mlflow_run_id"] == parent  # the same parent run, continued
    assert mlflow.MlflowClient(uri).get_run(parent).info.status == "FINISHED"

    got = _report(Path(killed["results_dir"]), "killed")
    want = _report(Path(whole["results_dir"]), "whole")
    assert got["text"] == want["text"]
    pd.testing.assert_frame_equal(got["budget"], want["budget"])
    for name in CSVS:
        assert got[name] == want[name], name
    manifests = [
        json.loads((Path(d["results_dir"]) / "weights" / "sp" / "4p2e1o.json").read_text()) for d in (killed, whole)
    ]
    for m in manifests:  # the file's own digest covers its header (creation time, run name): not compared
        m.pop("benchmark"), m.pop("sha256")
    assert manifests[0] == manifests[1]
