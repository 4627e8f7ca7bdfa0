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

from collections.abc import Iterable
from typing import Any

import ray

from atdrone.service.actors import answers
from atdrone.service.coordinator import Coordinator


def _session() -> tuple[str, str]:
    """The Ray session this process is connected to: its driver node's id (random per cluster) and job id."""
    context = ray.get_runtime_context()
    return context.get_node_id(), context.get_job_id()


class CoordinatorPool:
    """Idle coordinators of this process: :meth:`take` one for a run, :meth:`give_back` after."""

    def __init__(self) -> None:
        self._session: tuple[str, str] | None = None
        self._idle: list[Any] = []
        self.created = 0  # coordinators this pool made (for tests and logs)

    def _current(self) -> list[Any]:
        session = _session()
        if session != self._session:  # a new Ray session: the old handles point at nothing
            self._session, self._idle = session, []
        return self._idle

    def take(self) -> Any:
        """An idle coordinator (one that answers; a killed or stuck one is left to Ray), else a new one."""
        idle = self._current()
        while idle:
            coordinator = idle.pop()
            if answers(coordinator.ping):
                return coordinator
        self.created += 1
        return Coordinator.options(max_concurrency=2).remote()  # the 2nd thread answers progress()

    def give_back(self, coordinators: Iterable[Any]) -> None:
        """Keep ``coordinators`` for this process's next run, each released (what its run left freed; a dead or
        stuck one is dropped, Ray ends it)."""
        idle = self._current()
        idle += [c for c in coordinators if answers(c.release)]

    def idle(self) -> int:
        """How many coordinators wait for the next run."""
        return len(self._current())


COORDINATORS = CoordinatorPool()
"""This process's coordinators: the driver takes one for a run and gives it back when the run ends well."""
