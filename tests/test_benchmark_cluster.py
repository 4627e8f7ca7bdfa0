"""A tiny benchmark on a local two-node Ray cluster (ray.cluster_utils.Cluster, one CPU per node): its two
training cells run at once, one on each node, each with its own rollout worker."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from conftest import tiny_benchmark

REPO = Path(__file__).resolve().parent.parent
DRIVER = """
import json, os, sys
os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"  # loopback only, as the service's local Ray
from ray._private import ray_constants
ray_constants.ENABLE_RAY_CLUSTER = False
from ray.cluster_utils import Cluster
from atdrone.benchmark.cells import load_benchmark
from atdrone.benchmark.job import run_benchmark

doc, uri = json.loads(sys.argv[1]), sys.argv[2]
cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
cluster.add_node(num_cpus=1)
cluster.wait_for_nodes()
try:
    summary = run_benchmark(load_benchmark(doc), address=cluster.address, tracking_uri=uri, progress=False)
    nodes = {r["name"]: r["timing"]["node"] for r in summary["records"]}
    print("NODES " + json.dumps({"nodes": nodes, "all": [n.node_id for n in cluster.list_all_nodes()]}))
finally:
    import ray
    ray.shutdown()
    cluster.shutdown()
"""


def test_a_benchmark_on_two_nodes_runs_a_cell_on_each(tmp_path, mlflow_store):
    doc = tiny_benchmark(tmp_path, "two_nodes")
    del doc["max_parallel"]  # cells as many at once as the cluster's CPUs allow: one on each node
    uri = mlflow_store(tmp_path / "mlflow.db")
    done = subprocess.run(
        [sys.executable, "-c", DRIVER, json.dumps(doc), uri], cwd=REPO, capture_output=True, text=True, timeout=400
    )
    assert done.returncode == 0, (done.stdout + done.stderr)[-4000:]
    line = next(x for x in done.stdout.splitlines() if x.startswith("NODES "))
    found = json.loads(line.removeprefix("NODES "))
    trained = {found["nodes"]["sp-4p2e1o-s0"], found["nodes"]["sp-4p2e1o-s1"]}
    assert trained == set(found["all"])  # one training cell on each node
    assert (Path(doc["results_dir"]) / "report.md").is_file()
