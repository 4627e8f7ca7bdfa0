"""The coordinator kept between the runs of one driver process, with its learners and rollout workers.

A coordinator is a process that imports the service, torch and pandas (about 2 CPU-seconds
to start); each learner actor it makes, a process that imports torch and builds an Adam
optimiser (which imports ``torch._dynamo``): about 3. Within a run the coordinator reuses
its learners (:meth:`LearnerActor.reset` with the next spec gives what a new actor would
hold); this pool carries the coordinator, and with it its learners and rollout workers,
over to the driver's next run (:meth:`Coordinator.start` sets up a run as a new coordinator
would), so a process that runs many experiments (``benchmarks/hola_report.py``, a test
session, a benchmark cell's Ray worker that Ray reuses for the next cell) starts them once,
not once per run. None of them holds a CPU while idle: a run's CPUs are a placement group
the driver reserves for the run (:func:`~atdrone.service.coordinator.reserve_cpus`).

The driver creates the pooled coordinator, so it belongs to the driver process and outlives
each run; it ends with the driver's Ray connection. A coordinator handed back is kept only
while it answers and only for the Ray session it was made in (a handle from an earlier
``ray.init`` is dropped).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import Any

import ray

from atdrone.service.coordinator import Coordinator

PING_TIMEOUT_S = 10.0


def _session() -> tuple[str, str]:
    """The Ray session this process is connected to: its driver node's id (random per cluster) and job id."""
    context = ray.get_runtime_context()
    return context.get_node_id(), context.get_job_id()


class ActorPool:
    """Idle actors of one kind: :meth:`take` one for a run, :meth:`give_back` after.

    ``make()``: a new actor. A pooled actor answers ``ping()`` and, handed back, ``release()`` (it frees
    what the run left in it)."""

    def __init__(self, make: Callable[[], Any]) -> None:
        self._make = make
        self._session: tuple[str, str] | None = None
        self._idle: list[Any] = []
        self.created = 0  # actors this pool made (for tests and logs)

    def _current(self) -> list[Any]:
        session = _session()
        if session != self._session:  # a new Ray session: the old handles point at nothing
            self._session, self._idle = session, []
        return self._idle

    def take(self) -> Any:
        """An idle actor (one that answers), else a new one."""
        idle = self._current()
        while idle:
            actor = idle.pop()
            try:
                ray.get(actor.ping.remote(), timeout=PING_TIMEOUT_S)
            except (ray.exceptions.RayActorError, ray.exceptions.GetTimeoutError):
                continue  # killed or stuck: left to Ray
            return actor
        self.created += 1
        return self._make()

    def give_back(self, actors: Iterable[Any]) -> None:
        """Keep ``actors`` for this process's next run (checked when taken again)."""
        idle = self._current()
        for actor in actors:
            try:  # what the run left in it freed while it waits; a dead or stuck one is dropped (Ray ends it)
                ray.get(actor.release.remote(), timeout=PING_TIMEOUT_S)
            except (ray.exceptions.RayActorError, ray.exceptions.GetTimeoutError):
                continue
            idle.append(actor)

    def idle(self) -> int:
        """How many actors wait for the next run."""
        return len(self._current())


def make_coordinator() -> Any:
    return Coordinator.options(max_concurrency=2).remote()  # the 2nd thread answers progress()


COORDINATORS = ActorPool(make_coordinator)
"""This process's coordinators: the driver takes one for a run and gives it back when the run ends well."""
