"""Actors kept between the runs of one driver process: its learners and its coordinator.

A learner actor is a process that imports torch and builds an Adam optimiser (which imports
``torch._dynamo``): about 3 CPU-seconds to start; a coordinator, a process that imports the
service, torch and pandas: about 2. Within a run the coordinator already reuses its learners
(:meth:`LearnerActor.reset` with the next spec gives what a new actor would hold); these pools
carry both over to the driver's next run (:meth:`Coordinator.start` sets up a run as a new
coordinator would), so a process that runs many experiments (``benchmarks/hola_report.py``, a
test session, a benchmark cell's Ray worker that Ray reuses for the next cell) starts one of
each, not one per run. Only actors that hold no CPU are pooled: an idle rollout worker would
keep its CPU from every other run of the cluster (a coordinator ends its workers when handed
back).

The driver creates the pooled actors, so they belong to the driver process and outlive each
run; they end with the driver's Ray connection. An actor handed back is kept only while it
answers and only for the Ray session it was made in (a handle from an earlier ``ray.init`` is
dropped).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import ray

from atdrone.service.actors import LearnerActor
from atdrone.service.coordinator import Coordinator

PING_TIMEOUT_S = 10.0


def _session() -> tuple[str, str]:
    """The Ray session this process is connected to: its driver node's id (random per cluster) and job id."""
    context = ray.get_runtime_context()
    return context.get_node_id(), context.get_job_id()


class ActorPool:
    """Idle actors of one kind, by GPU request: :meth:`take` one for a run, :meth:`give_back` after.

    ``make(gpus)``: a new actor asking ``gpus`` GPUs. A pooled actor answers ``ping()`` and, handed back,
    ``release()`` (it frees what the run left in it)."""

    def __init__(self, make: Callable[[float], Any]) -> None:
        self._make = make
        self._session: tuple[str, str] | None = None
        self._idle: dict[float, list[Any]] = {}
        self.created = 0  # actors this pool made (for tests and logs)

    def _current(self) -> dict[float, list[Any]]:
        session = _session()
        if session != self._session:  # a new Ray session: the old handles point at nothing
            self._session, self._idle = session, {}
        return self._idle

    def take(self, gpus: float = 0.0) -> Any:
        """An idle actor asking ``gpus`` GPUs (one that answers), else a new one."""
        pools = self._current()
        for other in [g for g in pools if g != float(gpus)]:
            del pools[other]  # actors asking other GPUs would hold what this run's need (Ray ends them)
        idle = pools.setdefault(float(gpus), [])
        while idle:
            actor = idle.pop()
            try:
                ray.get(actor.ping.remote(), timeout=PING_TIMEOUT_S)
            except (ray.exceptions.RayActorError, ray.exceptions.GetTimeoutError):
                continue  # killed or stuck: left to Ray
            return actor
        self.created += 1
        return self._make(float(gpus))

    def give_back(self, actors: Iterable[Any], gpus: float = 0.0) -> None:
        """Keep ``actors`` for this process's next run (checked when taken again)."""
        idle = self._current().setdefault(float(gpus), [])
        for actor in actors:
            try:  # what the run left in it freed while it waits; a dead or stuck one is dropped (Ray ends it)
                ray.get(actor.release.remote(), timeout=PING_TIMEOUT_S)
            except (ray.exceptions.RayActorError, ray.exceptions.GetTimeoutError):
                continue
            idle.append(actor)

    def idle(self, gpus: float = 0.0) -> int:
        """How many actors wait for the next run."""
        return len(self._current().get(float(gpus), []))


def make_learner(gpus: float) -> Any:
    return LearnerActor.options(num_gpus=gpus).remote()


def make_coordinator(gpus: float) -> Any:
    return Coordinator.options(max_concurrency=2).remote()  # the 2nd thread answers progress()


LEARNERS = ActorPool(make_learner)
"""This process's learners: the driver takes the run's first learner from it and gives it back when the run ends."""
COORDINATORS = ActorPool(make_coordinator)
"""This process's coordinators (no GPU: key 0): one per run, handed back when the run ends well."""
