"""Learner actors kept between the runs of one driver process.

A learner actor is a process that imports torch and builds an Adam optimiser (which imports
``torch._dynamo``): about 3 CPU-seconds to start. Within a run the coordinator already reuses
its learners (:meth:`LearnerActor.reset` with the next spec gives what a new actor would
hold); this pool carries them over to the driver's next run, so a process that runs many
experiments (``benchmarks/hola_report.py``, a test session, a benchmark cell's Ray worker that
Ray reuses for the next cell) starts one learner, not one per run.

The driver creates the pooled learners, so they belong to the driver process and outlive
each run's coordinator; they end with the driver's Ray connection. A learner handed back is
kept only while it answers and only for the Ray session it was made in (a handle from an
earlier ``ray.init`` is dropped).
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import ray

from atdrone.service.actors import LearnerActor

PING_TIMEOUT_S = 10.0


def _session() -> tuple[str, str]:
    """The Ray session this process is connected to: its driver node's id (random per cluster) and job id."""
    context = ray.get_runtime_context()
    return context.get_node_id(), context.get_job_id()


class LearnerPool:
    """Idle learner actors of this process, by GPU request; :meth:`take` one for a run, :meth:`give_back` after."""

    def __init__(self) -> None:
        self._session: tuple[str, str] | None = None
        self._idle: dict[float, list[Any]] = {}
        self.created = 0  # learners this pool made (for tests and logs)

    def _current(self) -> dict[float, list[Any]]:
        session = _session()
        if session != self._session:  # a new Ray session: the old handles point at nothing
            self._session, self._idle = session, {}
        return self._idle

    def take(self, gpus: float = 0.0) -> Any:
        """An idle learner asking ``gpus`` GPUs (one that answers), else a new one."""
        pools = self._current()
        for other in [g for g in pools if g != float(gpus)]:
            del pools[other]  # learners asking other GPUs would hold what this run's needs (Ray ends them)
        idle = pools.setdefault(float(gpus), [])
        while idle:
            learner = idle.pop()
            try:
                ray.get(learner.ping.remote(), timeout=PING_TIMEOUT_S)
            except (ray.exceptions.RayActorError, ray.exceptions.GetTimeoutError):
                continue  # killed or stuck: left to Ray
            return learner
        self.created += 1
        return LearnerActor.options(num_gpus=gpus).remote()

    def give_back(self, learners: Iterable[Any], gpus: float = 0.0) -> None:
        """Keep ``learners`` for this process's next run (checked when taken again)."""
        idle = self._current().setdefault(float(gpus), [])
        for learner in learners:
            try:  # its model and optimiser freed while it waits; a dead or stuck one is dropped (Ray ends it)
                ray.get(learner.release.remote(), timeout=PING_TIMEOUT_S)
            except (ray.exceptions.RayActorError, ray.exceptions.GetTimeoutError):
                continue
            idle.append(learner)

    def idle(self, gpus: float = 0.0) -> int:
        """How many learners wait for the next run."""
        return len(self._current().get(float(gpus), []))


LEARNERS = LearnerPool()
"""This process's pool: the driver takes the run's first learner from it and gives it back when the run ends."""
