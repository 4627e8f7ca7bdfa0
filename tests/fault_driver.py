"""A service driver that SIGKILLs itself at one named point of its run (for tests/test_faults.py).

    python tests/fault_driver.py '{"doc": {...}, "uri": ..., "address": ..., "side": ..., "target": ...,
                                   "when": "before"|"after", "nth": N}'
    python tests/fault_driver.py --serve    (one such JSON per stdin line, each a forked driver)

It runs (or resumes) the experiment ``doc`` joined to the Ray at ``address``, after wrapping one kind of step:

- side "coordinator" or "driver", target a registry method (add_member, add_match, start_generation,
  finish_generation, update_member, discard_generations): the registry actor's handle is wrapped so that
  the nth call of that method made from that process kills the driver before the call is sent, or after
  its write has committed;
- side "driver", target ``tracker.<method>`` (a :class:`atdrone.tracking.Tracker` method: log_metrics,
  log_dict, log_artifact, register_checkpoint, ...): the nth call, before or after it returns;
- side "driver", target ``file:<name>`` (service_state.json, summary.json): the nth atomic write of it.

The kill is SIGKILL to the driver process: nothing of it runs afterwards (no finally, no atexit). A point
never reached lets the run finish; the exit status tells (-9: killed).
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from collections import Counter
from pathlib import Path
from typing import Any

WRITES = {"add_member", "add_match", "start_generation", "finish_generation", "update_member", "discard_generations"}


def _die(pid: int) -> None:
    os.kill(pid, signal.SIGKILL)
    time.sleep(60)  # in another process (the coordinator): Ray ends it with its dead driver


class _Call:
    def __init__(self, registry: KillingRegistry, name: str) -> None:
        self.registry, self.name = registry, name

    def remote(self, *args: Any, **kwargs: Any) -> Any:
        import ray

        reg = self.registry
        side = "driver" if os.getpid() == reg.driver else "coordinator"
        method = getattr(reg.handle, self.name)
        if self.name not in WRITES or (side, self.name) != (reg.spec["side"], reg.spec["target"]):
            return method.remote(*args, **kwargs)
        reg.calls[self.name] += 1
        hit = reg.calls[self.name] == reg.spec["nth"]
        if hit and reg.spec["when"] == "before":
            _die(reg.driver)
        ref = method.remote(*args, **kwargs)
        if hit:
            ray.get(ref)  # committed
            _die(reg.driver)
        return ref


class KillingRegistry:
    """The registry actor's handle, with one write method that kills the driver (see the module docstring)."""

    def __init__(self, handle: Any, spec: dict[str, Any]) -> None:
        self.handle, self.spec, self.driver = handle, spec, os.getpid()
        self.calls: Counter[str] = Counter()

    def __getattr__(self, name: str) -> Any:
        if name.startswith("__"):
            raise AttributeError(name)
        return _Call(self, name)


def _wrap(owner: Any, name: str, spec: dict[str, Any], matches: Any = lambda *a, **k: True) -> None:
    real = getattr(owner, name)
    count = Counter[str]()

    def wrapped(*args: Any, **kwargs: Any) -> Any:
        if not matches(*args, **kwargs):
            return real(*args, **kwargs)
        count[name] += 1
        hit = count[name] == spec["nth"]
        if hit and spec["when"] == "before":
            _die(os.getpid())
        result = real(*args, **kwargs)
        if hit:
            _die(os.getpid())
        return result

    setattr(owner, name, wrapped)


def attempt(spec: dict[str, Any]) -> None:
    """One driver: the kill point of ``spec`` wrapped, then the run resumed (or started)."""
    import atdrone.registry_ray
    import atdrone.service.driver as driver
    from atdrone.service.experiment import load_experiment
    from atdrone.tracking import Tracker

    target = spec["target"]
    if spec["side"] == "coordinator" or target in WRITES:
        make, release = atdrone.registry_ray.registry_actor, driver._release
        atdrone.registry_ray.registry_actor = lambda *a, **k: KillingRegistry(make(*a, **k), spec)  # type: ignore[assignment]
        driver._release = lambda c, r, n, *a: release(c, getattr(r, "handle", r), n, *a)  # type: ignore[assignment]
    elif target.startswith("tracker."):
        _wrap(Tracker, target.removeprefix("tracker."), spec)
    elif target.startswith("file:"):
        import atdrone.service.results as results
        import atdrone.service.runstate as runstate

        name = target.removeprefix("file:")
        for module in (runstate, results):
            _wrap(module, "write_json", spec, lambda path, data: Path(path).name == name)
    else:
        raise SystemExit(f"unknown target {target!r}")
    cfg = load_experiment(spec["doc"])
    driver.run_experiment(cfg, address=spec["address"], resume=True, tracking_uri=spec["uri"], progress=False)


# what a driver imports, lazily, in a run: imported once by the server, not in every forked driver
PRELOAD = (
    "atdrone.population",
    "atdrone.service.coordinator",
    "atdrone.service.driver",
    "atdrone.tracking",
    "mlflow.store.model_registry.sqlalchemy_store",
    "mlflow.store.tracking.sqlalchemy_store",
    "matplotlib.pyplot",
    "networkx",
)


def serve() -> None:
    """Import once, then run each spec read from stdin (one JSON line) as a forked driver; print its exit status.

    The fork skips the seconds a fresh interpreter spends importing torch, Ray, MLflow with its sqlite stores,
    pyplot and networkx (:data:`PRELOAD`); Ray itself is first initialised in the child (the parent never
    connects), so nothing of it crosses the fork.
    """
    import importlib
    import traceback

    import matplotlib

    matplotlib.use("Agg")  # as atdrone.population.plots does: each generation draws its hypergraph
    for module in PRELOAD:
        importlib.import_module(module)

    for line in sys.stdin:
        pid = os.fork()
        if pid == 0:
            os.dup2(2, 1)  # the driver's own output (Ray's, MLflow's) to stderr: stdout carries exit statuses only
            code = 0
            try:
                attempt(json.loads(line))
            except BaseException:
                traceback.print_exc()
                code = 1
            finally:
                sys.stderr.flush()
                os._exit(code)
        _, status = os.waitpid(pid, 0)
        print(os.waitstatus_to_exitcode(status), flush=True)


if __name__ == "__main__":
    serve() if sys.argv[1:] == ["--serve"] else attempt(json.loads(sys.argv[1]))
