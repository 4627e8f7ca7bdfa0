"""The benchmark job through the real service: a driver on the session's Ray stopped by SIGTERM while its first
cell trains (one last line, exit 143), resumed and SIGKILLed after its first cell, is finished by a third
invocation that runs only the missing cells and reports byte for byte what an uninterrupted run of the same grid
reports. That reference (``atdrone benchmark`` too) runs on a local two-node Ray cluster
(ray.cluster_utils.Cluster, one CPU per node), where its two training cells run at once, one on each node."""

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
import pytest
from conftest import tiny_benchmark

from atdrone.benchmark.cells import load_benchmark
from atdrone.benchmark.job import STATE_FILE, run_benchmark
from atdrone.benchmark.weights import replay
from atdrone.hostinfo import float_kernels
from atdrone.resolve import WEIGHTS_ENV

REPO = Path(__file__).resolve().parent.parent
CSVS = ("evaluations", "table", "paired", "normalised", "aggregate", "improvement", "protocols")


TWO_NODES = """
import os, sys
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # loopback only, as the service's local Ray
from ray._private import ray_constants
ray_constants.ENABLE_RAY_CLUSTER = False
from ray.cluster_utils import Cluster
from atdrone.cli import main

cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
cluster.add_node(num_cpus=1)
cluster.wait_for_nodes()
try:
    print("NODES " + " ".join(n.node_id for n in cluster.list_all_nodes()), flush=True)
    code = main(["benchmark", *sys.argv[1:], "--address", cluster.address])
finally:
    import ray
    ray.shutdown()
    cluster.shutdown()
sys.exit(code)
"""


def _benchmark(doc: dict[str, Any], tmp_path: Path, uri: str, address: str = "") -> subprocess.Popen[str]:
    """``atdrone benchmark`` of ``doc`` in a process of its own: joined to the Ray at ``address``, else on a local
    Ray cluster of two nodes with one CPU each (:data:`TWO_NODES`)."""
    path = tmp_path / f"{doc['name']}.json"
    path.write_text(json.dumps(doc))
    args = [str(path), "--tracking-uri", uri, "--no-progress"]
    if address:
        command = [sys.executable, "-m", "atdrone.cli", "benchmark", *args, "--address", address]
    else:
        command = [sys.executable, "-c", TWO_NODES, *args]
    return subprocess.Popen(command, cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def _report(results: Path, name: str) -> dict[str, Any]:
    """What must be equal between two runs of one grid: the text (CPU-seconds aside) and the CSVs."""
    text = (results / "report.md").read_text().replace(name, "NAME")
    timings = r"\| [\d,]+ \| [\d,]+ \| [\d,]+ \| \d+ \|\n"  # the budget table's CPU-s, wall-s, its median, stalls
    text = re.sub(timings, "| CPU | WALL | MEDIAN | STALLED |\n", text)
    totals = r"[\d,]+ CPU-s, [\d,]+ s of cell wall time as measured; [\d,]+ s with each of the \d+ stalled"
    text = re.sub(totals, "CPU-s, wall time", text)  # and their totals
    frames = {n: (results / f"{n}.csv").read_bytes() for n in CSVS}  # exactly, byte for byte
    timing_columns = ["cpu_s", "wall_s", "wall_median_s", "steady_wall_s", "stalled"]
    budget = pd.read_csv(results / "budget.csv").drop(columns=timing_columns, errors="ignore")
    return {"text": text, "budget": budget, **frames}


# four benchmark runs (one on a two-node cluster of its own) beside the other worker's Ray tests: 490-570 s on a
# slow 2-core host with the flights' busy loop on one core (2026-11-30)
@pytest.mark.timeout(1800)
def test_a_stopped_then_killed_benchmark_finishes_only_its_missing_cells_and_reports_as_an_uninterrupted_one(
    local_ray, tmp_path, mlflow_store, capsys, monkeypatch
):
    uri = mlflow_store(tmp_path / "mlflow.db")
    whole, killed = tiny_benchmark(tmp_path, "whole"), tiny_benchmark(tmp_path, "killed")
    del whole["max_parallel"]  # cells as many at once as the cluster's CPUs allow: one on each node
    reference = _benchmark(whole, tmp_path, uri)  # on two nodes, beside the killed one
    folder = tmp_path / "bench" / "killed"
    first = folder / "cells" / "sp-4p2e1o-s0.json"

    def stop_when(victim: subprocess.Popen[str], ready: Any, sig: int) -> str:
        deadline = time.monotonic() + 900  # a hang guard: beside the reference's two-node cluster at the start
        while not ready():
            assert victim.poll() is None, victim.communicate()[0][-3000:]
            assert time.monotonic() < deadline, "never got there"
            time.sleep(0.2)
        os.kill(victim.pid, sig)
        return victim.communicate(timeout=180)[0]

    # SIGTERM (`ray job stop`) while the first cell trains: one last line (cells kept, the resume command), 143
    victim = _benchmark(killed, tmp_path, uri, address=local_ray)
    out = stop_when(victim, lambda: any(folder.rglob("service_state.json")), signal.SIGTERM)
    assert victim.returncode == 143, out[-3000:]
    assert "Traceback" not in out and "SIGTERM received" not in out, out[-3000:]
    last = out.strip().splitlines()[-1]
    assert re.fullmatch(
        r"atdrone benchmark: interrupted; kept 0 finished cell\(s\) of 3 .* resume with: atdrone benchmark \S+ .*",
        last,
    ), last
    assert not first.exists()
    # resumed, then SIGKILLed once its first cell is finished
    victim = _benchmark(killed, tmp_path, uri, address=local_ray)
    stop_when(victim, first.exists, signal.SIGKILL)
    kept = first.read_bytes()
    assert sorted(p.name for p in (folder / "cells").glob("*.json")) == ["sp-4p2e1o-s0.json"]  # killed mid-way
    parent = json.loads((folder / STATE_FILE).read_text())["mlflow_run_id"]

    capsys.readouterr()  # no wait for the dead driver's cells to go: the resumed one queues for a CPU
    summary = run_benchmark(load_benchmark(killed), address=local_ray, tracking_uri=uri)
    out, _ = reference.communicate(timeout=400)
    assert reference.returncode == 0, out[-4000:]
    assert "whole: 3 cells; report " in out and "weights:sp/4p2e1o (seed " in out  # the command's last lines
    nodes = set(next(x for x in out.splitlines() if x.startswith("NODES ")).split()[1:])
    cells = tmp_path / "bench" / "whole" / "cells"
    trained = {json.loads((cells / f"sp-4p2e1o-s{s}.json").read_text())["timing"]["node"] for s in (0, 1)}
    assert len(nodes) == 2 and trained == nodes  # the reference ran one training cell on each node
    for path in sorted(cells.glob("*.json")):  # per zoo, episode summaries that add up to the record's metrics
        rec = json.loads(path.read_text())
        assert set(rec["episodes"]) == set(rec["metrics"]), path.name
        for zoo, got in rec["episodes"].items():
            metrics = rec["metrics"][zoo]
            assert got["learner_crash"] + got["partner_only_crash"] == pytest.approx(metrics["COL"])
            assert got["return_capture"] + got["return_collision"] + got["return_rest"] == pytest.approx(metrics["REW"])
    assert "3 cells: 1 done, 2 to run" in capsys.readouterr().out
    assert first.read_bytes() == kept  # the finished cell was not run again
    assert summary["mlflow_run_id"] == parent  # the same parent run, continued
    client = mlflow.MlflowClient(uri)
    assert client.get_run(parent).info.status == "FINISHED"
    # one experiment per benchmark, the cells' runs nested under its run; the only models: its published weights
    assert {e.name for e in client.search_experiments()} <= {"Default", "killed", "whole"}
    experiment = client.get_experiment_by_name("killed").experiment_id
    nested = client.search_runs([experiment], f"tags.`mlflow.parentRunId` = '{parent}'")
    assert {r.info.run_name for r in nested} >= {"killed-sp-4p2e1o-s0-sp", "killed-sp-4p2e1o-s1-sp"}
    assert {m.name for m in client.search_registered_models()} == {"atdrone-killed", "atdrone-whole"}
    versions = client.search_model_versions("name = 'atdrone-killed'")
    assert {v.tags.get("alias") for v in versions} == {"sp-4p2e1o"}  # no cell's own best member among them
    published = client.get_model_version_by_alias("atdrone-killed", "sp-4p2e1o")
    assert published.tags["method"] == "sp" and published.tags["task"] == "4p2e1o"

    got = _report(Path(killed["results_dir"]), "killed")
    want = _report(Path(whole["results_dir"]), "whole")
    assert got["text"] == want["text"]
    pd.testing.assert_frame_equal(got["budget"], want["budget"])
    for name in CSVS:
        assert got[name] == want[name], name
    manifests = [
        json.loads((Path(d["results_dir"]) / "weights" / "sp" / "4p2e1o.json").read_text()) for d in (killed, whole)
    ]
    # the published weight names the float kernels that measured it and, on them, plays its metrics bit for bit
    monkeypatch.setenv(WEIGHTS_ENV, killed["results_dir"])
    assert manifests[0]["measured_on"] == float_kernels()
    for zoo, metrics in manifests[0]["metrics"].items():
        played = replay(manifests[0], zoo, killed["eval_episodes"])
        assert played == pytest.approx(metrics, rel=0, abs=0, nan_ok=True), zoo
    for m in manifests:  # the file's own digest covers its header (creation time, run name): not compared
        m.pop("benchmark"), m.pop("sha256"), m.pop("reproduce")  # the commands name the benchmark
    assert manifests[0] == manifests[1]
