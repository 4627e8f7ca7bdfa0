"""A local Ray outlives its raylet starved of CPU (stopped, here) for longer than Ray's own health checks allow;
with Ray's check timeout (the control) the same stall ends the node and the driver with it."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap

import pytest

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_getaffinity"), reason="needs Linux signals to stop a raylet")

# a driver with a local Ray of its own: runs a task, stops its raylet STALL seconds, then runs another
DRIVER = textwrap.dedent(
    """
    import os, signal, sys, time
    from atdrone.service.driver import init_ray
    import ray
    init_ray(None, num_cpus=1)
    raylet = ray._private.worker._global_node.all_processes["raylet"][0].process.pid

    @ray.remote
    def one():
        return 1

    assert ray.get(one.remote()) == 1
    os.kill(raylet, signal.SIGSTOP)
    time.sleep(float(sys.argv[1]))
    os.kill(raylet, signal.SIGCONT)
    time.sleep(3)  # the node's fate settles (a node taken for dead ends its raylet)
    print("after the stall:", ray.get(one.remote(), timeout=60), flush=True)
    ray.shutdown()
    """
)
STALL_S = 18  # with one check allowed to fail: Ray's 10 s timeout takes the node for dead after about 11 s of it


def test_a_local_ray_outlives_a_starved_raylet_that_rays_own_timeout_would_end():
    # one missed check ends a node (Ray's defaults: 5, 3 s apart), so the stall can be short
    checks = {
        "RAY_health_check_period_ms": "1000",
        "RAY_health_check_initial_delay_ms": "1000",
        "RAY_health_check_failure_threshold": "1",
    }
    base = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "RAY_health_check_timeout_ms")}
    tolerant = {**base, **checks}  # init_ray's own timeout: a minute per check
    control = {**base, **checks, "RAY_health_check_timeout_ms": "10000"}  # Ray's default, set by the user: kept
    runs = {
        name: subprocess.Popen(
            [sys.executable, "-c", DRIVER, str(STALL_S)], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE
        )
        for name, env in (("tolerant", tolerant), ("control", control))
    }
    out = {name: proc.communicate(timeout=240) for name, proc in runs.items()}
    assert runs["tolerant"].returncode == 0, out["tolerant"][1].decode()[-3000:]
    assert b"after the stall: 1" in out["tolerant"][0]
    assert runs["control"].returncode != 0 and b"after the stall" not in out["control"][0], out["control"]
    assert b"marked dead" in out["control"][1] or b"RayletDied" in out["control"][1], out["control"][1][-3000:]
