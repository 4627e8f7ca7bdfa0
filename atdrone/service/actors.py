"""Ray actors of the training service: thin wrappers around the rollout worker and the Learner.

A rollout worker actor runs one training job at a time (:meth:`RolloutWorkerActor.start`
builds a fresh :class:`~atdrone.learn.rollout.RolloutWorker` from the job's seed,
partners and sampler, so a job repeats exactly wherever and whenever it runs) and plays
evaluation matches. Every call carries everything it needs, so a worker that dies is
restarted by Ray and the call redone (max_restarts / max_task_retries). The learner
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
from atdrone.learn.learner import Learner, LearnerSpec
from atdrone.learn.ppo import PPOConfig
from atdrone.learn.rollout import Fragment, RolloutWorker
from atdrone.models.checkpoint import save_checkpoint
from atdrone.policies.base import Policy
from atdrone.policies.zoo import MemberSpec, build_policy
from atdrone.teams.evaluation import metrics, run_episodes
from atdrone.teams.partners import PartnerDistribution, as_sampler


class PolicyCache:
    """Partner policies built once per member spec (checkpoints are read once)."""

    def __init__(self) -> None:
        self._cache: dict[tuple, Policy] = {}

    def get(self, spec: MemberSpec) -> Policy:
        key = (spec.name, spec.kind, spec.checkpoint, tuple(sorted(spec.params.items())))
        if key not in self._cache:
            self._cache[key] = build_policy(spec)
        return self._cache[key]


@dataclass(frozen=True)
class RolloutJob:
    """One worker's part of training a learner: its seed, environments and partners.

    ``partners``: the specs of ``distribution.members`` in order (empty for self-play).
    """

    seed: int
    ppo: PPOConfig
    num_envs: int
    num_ctrl: int
    architecture: dict[str, Any]
    partners: tuple[MemberSpec, ...] = ()
    distribution: PartnerDistribution | None = None


@ray.remote(num_cpus=1, max_restarts=-1, max_task_retries=-1)
class RolloutWorkerActor:
    """Collects fragments for one training job at a time, and plays evaluation matches."""

    def __init__(self, task: TaskConfig) -> None:
        torch.set_num_threads(1)
        self.task = task
        self.policies = PolicyCache()
        self.worker: RolloutWorker | None = None
        self.job: RolloutJob | None = None

    def pid(self) -> int:
        return os.getpid()

    def start(self, job: RolloutJob) -> None:
        """Begin a training job: fresh environments, seeded by the job."""
        self.job = job
        sampler = None
        if job.distribution is not None:
            sampler = as_sampler(job.distribution, self.task.players.num_p - job.num_ctrl)
        self.worker = RolloutWorker(
            self.task,
            job.seed,
            job.architecture,
            job.ppo,
            partners=[None if s.kind == "learner" else self.policies.get(s) for s in job.partners],
            num_ctrl=job.num_ctrl,
            sampler=sampler,
            num_envs=job.num_envs,
        )

    def collect(self, job: RolloutJob, weights: dict[str, torch.Tensor], steps: int) -> Fragment:
        """A fragment of ``steps`` steps of ``job`` (started here when new) with the learner ``weights``.

        Each call names its job, so a restarted worker (Ray retries the call) picks it up again.
        """
        if self.worker is None or self.job is None or job.seed != self.job.seed:  # a job is known by its seed
            self.start(job)
        assert self.worker is not None
        self.worker.set_weights(weights)
        return self.worker.collect(steps)

    def drawn(self) -> dict[str, int]:
        """Partner profiles of the current job's finished episodes, as drawn."""
        return dict(self.worker.drawn) if self.worker is not None else {}

    def evaluate(self, learner: MemberSpec, profile: Sequence[MemberSpec], episodes: int, seed: int) -> dict[str, Any]:
        """SUC/COL/AST/REW of ``learner`` in the learner slots with exactly ``profile`` as partners.

        Also ``REW_var`` (the per-episode returns' sample variance, for standard errors)
        and ``steps`` (environment steps of the episodes).
        """
        policy = self.policies.get(learner)
        partners = [self.policies.get(s) for s in profile]
        fixed = np.arange(len(partners))
        records = run_episodes(
            policy, self.task, partners, episodes, seed=seed, sampler=lambda rng, n: np.tile(fixed, (n, 1))
        )
        returns = records["return"].to_numpy(np.float64)
        var = float(returns.var(ddof=1)) if len(returns) > 1 else 0.0
        return {**metrics(records), "REW_var": var, "steps": int(records["length"].sum())}

    def evaluate_zoo(self, learner: MemberSpec, zoo: Sequence[MemberSpec], episodes: int, seed: int) -> dict:
        """SUC/COL/AST/REW of ``learner`` with partners drawn uniformly from ``zoo``."""
        records = run_episodes(
            self.policies.get(learner), self.task, [self.policies.get(s) for s in zoo], episodes, seed=seed
        )
        return metrics(records)


@ray.remote(num_cpus=0, max_restarts=0)
class LearnerActor:
    """A :class:`~atdrone.learn.learner.Learner` behind Ray: the same object as the local trainer's."""

    def __init__(self, spec: LearnerSpec, threads: int = 1) -> None:
        torch.set_num_threads(threads)  # the rollout workers are idle while a learner updates
        self.learner = Learner(spec)

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


def run_updates(
    learner: Any,
    workers: Sequence[Any],
    jobs: Sequence[Any],
    updates: int,
    steps: int,
    on_update: Callable[[int], None] | None = None,
) -> list[dict[str, float]]:
    """``updates`` learner updates, each on one fragment of ``steps`` steps per worker (worker i runs jobs[i]).

    Each worker starts its job afresh first, so the same jobs give the same fragments.
    ``on_update(n)`` is called after the n-th update (progress).

    The weights go out once per update as one object ref shared by every worker; the
    fragments go to the learner as refs, joined in worker order.
    """
    ray.get([w.start.remote(job) for w, job in zip(workers, jobs, strict=True)])  # fresh environments per job
    history = []
    for _ in range(updates):
        t0 = time.perf_counter()
        weights = learner.get_weights.remote()
        fragments = [w.collect.remote(job, weights, steps) for w, job in zip(workers, jobs, strict=True)]
        stats = ray.get(learner.update.remote(*fragments))
        stats["perf/pursuer_steps_per_s"] = stats["train/samples"] / (time.perf_counter() - t0)
        history.append(stats)
        if on_update is not None:
            on_update(len(history))
    return history
