"""Ray actors of the training service: thin wrappers around the rollout worker and the Learner.

A rollout worker actor runs one training job at a time (:meth:`RolloutWorkerActor.start`
builds a fresh :class:`~atdrone.learn.rollout.RolloutWorker` from the job's seed,
partners and sampler, so a job repeats exactly wherever and whenever it runs) and plays
evaluation matches. Fragment u of a job draws its action noise from a seed of (job, u)
and names u and the weights of the updates before it, so a worker that dies is
restarted by Ray, the call redone, and the job replayed to exactly that fragment (same
arrays, same partner draws). Restarts are bounded (:data:`WORKER_RESTARTS`): a worker
that keeps dying fails the generation instead of being retried forever. The learner
actor is a :class:`~atdrone.learn.learner.Learner`, on a GPU when the actor was given one.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import ray
import torch

from atdrone.config import TaskConfig
from atdrone.envs.events import EventPlan
from atdrone.learn.learner import Learner, LearnerSpec
from atdrone.learn.ppo import PPOConfig
from atdrone.learn.rollout import Fragment, RolloutWorker
from atdrone.learn.sizes import MixedSizeWorker, make_worker
from atdrone.models.checkpoint import save_checkpoint
from atdrone.policies.base import Policy
from atdrone.policies.zoo import MemberSpec, build_policy
from atdrone.teams.evaluation import metrics, run_episodes
from atdrone.teams.lineups import evaluate_lineups
from atdrone.teams.partners import PartnerDistribution


class PolicyCache:
    """Partner policies built once per member spec (checkpoints are read once)."""

    def __init__(self) -> None:
        self._cache: dict[tuple, Policy] = {}

    def get(self, spec: MemberSpec, copy: int = 0) -> Policy:
        """The policy of ``spec``; another ``copy`` number gets a policy of its own (one per team size)."""
        key = (spec.name, spec.kind, spec.checkpoint, tuple(sorted(spec.params.items())), copy)
        if key not in self._cache:
            self._cache[key] = build_policy(spec)
        return self._cache[key]


@dataclass(frozen=True)
class RolloutJob:
    """One worker's part of training a learner: its seed, environments and partners.

    ``partners``: the specs of ``distribution.members`` in order (empty for self-play); ``events``, ``split``
    and ``sizes``: the run's protocol's team events, split of the team and team sizes (None: none).
    """

    seed: int
    ppo: PPOConfig
    num_envs: int
    num_ctrl: int
    architecture: dict[str, Any]
    partners: tuple[MemberSpec, ...] = ()
    distribution: PartnerDistribution | None = None
    events: EventPlan | None = None
    split: tuple[int, int] | None = None
    sizes: tuple[int, int] | None = None  # pursuers per team, drawn per rollout (self-play only)


WORKER_RESTARTS = 8  # restarts of one rollout worker in a run, and retries of one call, before the run fails
ANSWER_TIMEOUT_S = 10.0


def answers(method: Any, timeout_s: float = ANSWER_TIMEOUT_S) -> bool:
    """Whether an actor's ``method`` (no arguments: ``ping``, ``release``) returns within ``timeout_s`` (False: the
    actor died or hangs)."""
    try:
        ray.get(method.remote(), timeout=timeout_s)
    except (ray.exceptions.RayActorError, ray.exceptions.GetTimeoutError):
        return False
    return True


@ray.remote(num_cpus=0, max_restarts=WORKER_RESTARTS, max_task_retries=WORKER_RESTARTS)
class RolloutWorkerActor:
    """Collects fragments for one training job at a time, and plays evaluation matches, on its task.

    It asks Ray for no CPU itself: the coordinator reserves one per worker for the run (a placement
    group bundle) and places the worker on that bundle's node, so a worker kept idle between runs
    holds no CPU. A restarted worker is made with the task it was first made with: a worker serves
    one task for life."""

    def __init__(self, task: TaskConfig) -> None:
        torch.set_num_threads(1)
        self.task = task
        self.release()

    def release(self) -> tuple[int, str]:
        """Drop the run's job, environments and partner policies (what a new worker holds); (pid, node id): a
        restart changes the pid."""
        self.policies = PolicyCache()
        self.worker: RolloutWorker | MixedSizeWorker | None = None
        self.job: RolloutJob | None = None
        self.done = 0  # fragments of the job collected by this process
        return os.getpid(), ray.get_runtime_context().get_node_id()

    def pid(self) -> int:
        return os.getpid()

    def start(self, job: RolloutJob) -> None:
        """Begin a training job: fresh environments, seeded by the job."""
        self.job = job
        self.done = 0

        def partners(task: TaskConfig) -> list[Policy | None]:  # each other team size its own policies (memory)
            copy = 0 if task.players.num_p == self.task.players.num_p else task.players.num_p
            return [None if s.kind == "learner" else self.policies.get(s, copy) for s in job.partners]

        self.worker = make_worker(
            self.task,
            job.seed,
            job.architecture,
            job.ppo,
            sizes=job.sizes,
            partners=partners,
            num_ctrl=job.num_ctrl,
            distribution=job.distribution,
            num_envs=job.num_envs,
            events=job.events,
            split=job.split,
        )

    def _next(self, weights: dict[str, torch.Tensor], steps: int) -> Fragment:
        """The job's next fragment: its update index seeds the learners' action noise."""
        assert self.worker is not None and self.job is not None
        self.worker.set_weights(weights)
        self.worker.generator.manual_seed(update_seed(self.job.seed, self.done))
        self.done += 1
        return self.worker.collect(steps)

    def _reach(self, job: RolloutJob, update: int, earlier: Sequence[Any], steps: int) -> None:
        """Be at fragment ``update`` of ``job``: where this process is, else replayed from the job's start.

        A restarted worker (or one that ran another job since) starts the job afresh and
        collects fragments 0 .. update-1 again with their learner weights (``earlier``,
        object refs), so the environments, the partner draws and :meth:`drawn` are exactly
        where the dead worker left them.
        """
        if update and self.job is not None and self.job.seed == job.seed and self.done == update:  # known by its seed
            return
        if len(earlier) != update:
            raise ValueError(f"fragment {update} of a job needs the weights of its {update} earlier updates")
        self.start(job)
        for weights in earlier:
            self._next(ray.get(weights), steps)

    def collect(
        self,
        job: RolloutJob,
        weights: dict[str, torch.Tensor],
        steps: int,
        update: int | None = None,
        earlier: Sequence[Any] = (),
    ) -> Fragment:
        """Fragment ``update`` (0, 1, ...) of ``job``: ``steps`` steps with the learner ``weights``.

        ``earlier``: the refs of the weights of the job's updates before ``update``, so a
        restarted worker (Ray retries the call on it) replays the job up to this fragment
        and returns exactly the fragment the dead one would have (:meth:`_reach`).
        Without ``update``: the next fragment of the current job, a new job started afresh
        (no replay).
        """
        if update is None:
            if self.job is None or job.seed != self.job.seed:
                self.start(job)
        else:
            self._reach(job, update, earlier, steps)
        return self._next(weights, steps)

    def drawn(self, job: RolloutJob | None = None, earlier: Sequence[Any] = (), steps: int = 0) -> dict[str, int]:
        """Partner profiles of the job's episodes started so far, as drawn.

        With ``job``: after its fragments with the weights ``earlier`` (replayed when this
        worker was restarted since, as in :meth:`collect`); without: the current job's.
        """
        if job is not None:
            self._reach(job, len(earlier), earlier, steps)
        return dict(self.worker.drawn) if self.worker is not None else {}

    def evaluate_lineups(
        self,
        learner: MemberSpec,
        partners: Sequence[MemberSpec],
        lineups: Sequence[Sequence[int]],
        episodes: Sequence[int],
        seed: int,
    ) -> list[dict[str, Any]]:
        """SUC/COL/AST/REW of ``learner`` in the learner slots with each lineup of ``partners`` (their indices),
        ``episodes[i]`` episodes of lineup i, all in one batch of environments
        (:func:`~atdrone.teams.lineups.evaluate_lineups`); with ``REW_var`` and ``steps`` per lineup."""
        return evaluate_lineups(
            self.policies.get(learner), self.task, [self.policies.get(s) for s in partners], lineups, episodes, seed
        )

    def evaluate_zoo(
        self,
        learner: MemberSpec,
        zoo: Sequence[MemberSpec],
        episodes: int,
        seed: int,
        events: EventPlan | None = None,
    ) -> dict:
        """SUC/COL/AST/REW of ``learner`` with partners drawn uniformly from ``zoo`` (and, with a protocol's
        ``events``, its team events played and their metrics)."""
        records = run_episodes(
            self.policies.get(learner),
            self.task,
            [self.policies.get(s) for s in zoo],
            episodes,
            seed=seed,
            events=events,
        )
        return metrics(records)


@ray.remote(num_cpus=0, max_restarts=0)
class LearnerActor:
    """A :class:`~atdrone.learn.learner.Learner` behind Ray: the same object as the local trainer's.

    One actor serves one training after another (:meth:`reset` with the next spec), so a
    run pays for starting a process that imports torch once, not once per learner (and a
    driver once for all its runs: :mod:`atdrone.service.pool`).
    """

    def __init__(self, spec: LearnerSpec | None = None, threads: int = 1) -> None:
        self.learner: Learner
        if spec is not None:
            self.reset(spec, threads)

    def reset(self, spec: LearnerSpec, threads: int = 1) -> None:
        """A fresh learner of ``spec``: what a new actor made with it would hold."""
        torch.set_num_threads(threads)  # the rollout workers are idle while a learner updates
        self.learner = Learner(spec)

    def release(self) -> None:
        """Drop the learner (model, optimiser): the actor waits for its next :meth:`reset` (a pooled learner)."""
        self.__dict__.pop("learner", None)

    def ping(self) -> bool:
        """True: the actor answers."""
        return True

    def pid(self) -> int:
        return os.getpid()

    def get_weights(self) -> dict[str, torch.Tensor]:
        return self.learner.get_weights()

    def set_weights(self, weights: dict[str, torch.Tensor]) -> None:
        self.learner.set_weights(weights)

    def hparams(self) -> dict[str, float]:
        return dict(self.learner.hparams)

    def set_hparams(self, lr: float | None = None, ent_coef: float | None = None) -> None:
        self.learner.set_hparams(lr=lr, ent_coef=ent_coef)

    def update(self, *fragments: Fragment) -> dict[str, float]:
        """One update over the fragments (object refs, resolved by Ray)."""
        return self.learner.update(fragments)

    def get_state(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        return self.learner.get_state()

    def save(self, path: str, header: dict[str, Any]) -> dict[str, Any]:
        """Write the current weights as a checkpoint; returns the full header (with sha256)."""
        return save_checkpoint(path, self.learner.model, header)


class WorkerFailed(RuntimeError):
    """A rollout worker died once more than its :data:`WORKER_RESTARTS` restarts allow: the generation fails."""


def _name_a_spent_worker(fragments: Sequence[Any], exc: Exception) -> None:
    """Raise :class:`WorkerFailed` naming the first worker whose fragment failed because the worker is dead for good
    (Ray's own error names neither the worker's index nor the cap, and blames memory); else return."""
    for i, fragment in enumerate(fragments):
        if not ray.wait([fragment], timeout=0)[0]:
            continue
        try:
            ray.get(fragment)
        except ray.exceptions.RayActorError as died:
            raise WorkerFailed(
                f"rollout worker {i} died and was restarted {WORKER_RESTARTS} times, the cap "
                f"(WORKER_RESTARTS): the generation fails; its last death: {str(died).splitlines()[0]}"
            ) from exc


def update_seed(job_seed: int, update: int) -> int:
    """The seed of the learners' action noise in fragment ``update`` of the job seeded ``job_seed``."""
    return int(np.random.SeedSequence([int(job_seed), int(update)]).generate_state(1)[0])


def run_updates(
    learner: Any,
    workers: Sequence[Any],
    jobs: Sequence[Any],
    updates: int,
    steps: int,
    on_update: Callable[[int], None] | None = None,
) -> tuple[list[dict[str, float]], list[dict[str, int]]]:
    """``updates`` learner updates, each on one fragment of ``steps`` steps per worker (worker i runs jobs[i]).

    Returns the updates' statistics and each worker's partner draws. Each job starts
    afresh, so the same jobs give the same fragments; fragment u of a job is named by u
    and carries the weights of the updates before it, so a worker restarted mid-job
    replays it to exactly where it was (:meth:`RolloutWorkerActor.collect`). ``on_update(n)``
    is called after the n-th update (progress).

    The weights go out once per update as one object ref shared by every worker; the
    fragments go to the learner as refs, joined in worker order.
    """
    history: list[dict[str, float]] = []
    sent: list[Any] = []  # the weights of every update so far (refs, kept for replays)
    for u in range(updates):
        t0 = time.perf_counter()
        weights = learner.get_weights.remote()
        fragments = [w.collect.remote(job, weights, steps, u, sent) for w, job in zip(workers, jobs, strict=True)]
        sent.append(weights)
        try:
            stats = ray.get(learner.update.remote(*fragments))
        except ray.exceptions.RayError as exc:
            _name_a_spent_worker(fragments, exc)
            raise
        stats["perf/pursuer_steps_per_s"] = stats["train/samples"] / (time.perf_counter() - t0)
        history.append(stats)
        if on_update is not None:
            on_update(len(history))
    drawn = ray.get([w.drawn.remote(job, sent, steps) for w, job in zip(workers, jobs, strict=True)])
    return history, drawn
