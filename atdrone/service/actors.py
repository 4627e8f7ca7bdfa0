"""Ray actors of the training service: rollout workers and PPO learners.

Rollout workers own a BatchedPursuit each, fill the learner slots with the weights
they are sent (an object ref put once per update) and the partner slots with
population or zoo members, and return whole fragments as arrays. Every call carries
everything it needs (weights, partner specs, probabilities), so a worker that dies
is restarted by Ray and the call redone (max_restarts / max_task_retries).
Learners hold a model and its optimizer and run the PPO update, on a GPU when the
actor was given one.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import numpy as np
import ray
import torch

from atdrone.config import TaskConfig
from atdrone.learn.ppo import PPOConfig, ppo_update
from atdrone.learn.rollout import Fragment, RolloutWorker
from atdrone.models.checkpoint import save_checkpoint
from atdrone.models.networks import ActorCritic, NetConfig
from atdrone.policies.base import Policy
from atdrone.policies.zoo import MemberSpec, build_policy
from atdrone.teams.evaluation import metrics, run_episodes


class PolicyCache:
    """Partner policies built once per member spec (checkpoints are read once)."""

    def __init__(self) -> None:
        self._cache: dict[tuple, Policy] = {}

    def get(self, spec: MemberSpec) -> Policy:
        key = (spec.name, spec.kind, spec.checkpoint, tuple(sorted(spec.params.items())))
        if key not in self._cache:
            self._cache[key] = build_policy(spec)
        return self._cache[key]


@ray.remote(num_cpus=1, max_restarts=-1, max_task_retries=-1)
class RolloutWorkerActor:
    """One BatchedPursuit of ``num_envs`` environments collecting for learners."""

    def __init__(self, task: TaskConfig, num_envs: int, seed: int, net: NetConfig, gamma: float) -> None:
        torch.set_num_threads(1)
        self.task, self.num_envs, self.seed, self.net, self.gamma = task, num_envs, seed, net, gamma
        self.policies = PolicyCache()
        self.worker: RolloutWorker | None = None
        self.key: tuple | None = None
        self.rebuilds = 0

    def pid(self) -> int:
        return os.getpid()

    def _worker(self, partners: Sequence[MemberSpec], probs: Sequence[float] | None, num_ctrl: int) -> RolloutWorker:
        key = (tuple((s.name, s.checkpoint) for s in partners), tuple(probs) if probs is not None else None, num_ctrl)
        if self.worker is None or key != self.key:
            sampler = None
            if probs is not None and partners:
                p = np.asarray(probs, dtype=np.float64) / np.sum(probs)
                num_unctrl = self.task.players.num_p - num_ctrl
                sampler = lambda rng, n: rng.choice(len(p), size=(n, num_unctrl), p=p)
            self.worker = RolloutWorker(
                self.task,
                self.num_envs,
                seed=int(np.random.SeedSequence([self.seed, self.rebuilds]).generate_state(1)[0] % 2**31),
                net=self.net,
                partners=[self.policies.get(s) for s in partners],
                num_ctrl=num_ctrl,
                sampler=sampler,
                gamma=self.gamma,
            )
            self.key = key
            self.rebuilds += 1
        return self.worker

    def collect(
        self,
        weights: dict[str, torch.Tensor],
        partners: Sequence[MemberSpec],
        probs: Sequence[float] | None,
        num_ctrl: int,
        steps: int,
    ) -> Fragment:
        """A fragment of ``steps`` steps with the learner ``weights`` and these partners."""
        worker = self._worker(partners, probs, num_ctrl)
        worker.set_weights(weights)
        return worker.collect(steps)

    def evaluate(self, learner: MemberSpec, profile: Sequence[MemberSpec], episodes: int, seed: int) -> dict[str, Any]:
        """SUC/COL/AST/REW of ``learner`` in the learner slots with exactly ``profile`` as partners."""
        policy = self.policies.get(learner)
        partners = [self.policies.get(s) for s in profile]
        fixed = np.arange(len(partners))
        records = run_episodes(
            policy, self.task, partners, episodes, seed=seed, sampler=lambda rng, n: np.tile(fixed, (n, 1))
        )
        return metrics(records)

    def evaluate_zoo(self, learner: MemberSpec, zoo: Sequence[MemberSpec], episodes: int, seed: int) -> dict:
        """SUC/COL/AST/REW of ``learner`` with partners drawn uniformly from ``zoo``."""
        records = run_episodes(
            self.policies.get(learner), self.task, [self.policies.get(s) for s in zoo], episodes, seed=seed
        )
        return metrics(records)


@ray.remote(num_cpus=0, max_restarts=0)
class LearnerActor:
    """A PPO learner: the model, its optimizer and the update."""

    def __init__(self, net: NetConfig, ppo: PPOConfig, num_e: int, num_p: int, seed: int, device: str = "auto"):
        if device == "auto":
            device = "cuda" if torch.cuda.is_available() else "cpu"
        torch.set_num_threads(1)
        torch.manual_seed(seed)
        self.device = torch.device(device)
        self.net, self.ppo, self.num_e, self.num_p = net, ppo, num_e, num_p
        self.model = ActorCritic(net).to(self.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=ppo.lr, eps=1e-5)
        self.generator = torch.Generator().manual_seed(seed)
        self.lr, self.ent_coef = ppo.lr, ppo.ent_coef

    def get_weights(self) -> dict[str, torch.Tensor]:
        return {k: v.detach().cpu().clone() for k, v in self.model.state_dict().items()}

    def set_weights(self, weights: dict[str, torch.Tensor]) -> None:
        self.model.load_state_dict(weights)

    def hparams(self) -> dict[str, float]:
        return {"lr": self.lr, "ent_coef": self.ent_coef}

    def set_hparams(self, lr: float | None = None, ent_coef: float | None = None) -> None:
        self.lr = lr if lr is not None else self.lr
        self.ent_coef = ent_coef if ent_coef is not None else self.ent_coef

    def update(self, *fragments: Fragment) -> dict[str, float]:
        """One PPO update over the fragments (passed as object refs, resolved by Ray)."""
        from dataclasses import replace

        from atdrone.learn.rollout import concat_fragments

        frag = concat_fragments(fragments)
        cfg = replace(self.ppo, ent_coef=self.ent_coef)
        stats = ppo_update(
            self.model,
            self.optimizer,
            frag.batch(cfg.gamma, cfg.gae_lambda),
            cfg,
            self.num_e,
            self.num_p,
            self.generator,
            lr=self.lr,
        )
        eps = frag.episodes
        out = {f"train/{k}": v for k, v in stats.items()}
        out["train/samples"] = frag.samples
        if eps:
            out["train/success"] = float(np.mean([e["outcome"] == "captured" for e in eps]))
            out["train/collision"] = float(np.mean([e["collided"] for e in eps]))
            out["train/episode_return"] = float(np.mean([e["return"] for e in eps]))
        out["perf/simulation_s"] = frag.timings.get("simulation", 0.0)
        out["perf/inference_s"] = frag.timings.get("inference", 0.0)
        return out

    def save(self, path: str, header: dict[str, Any]) -> dict[str, Any]:
        """Write the current weights as a checkpoint; returns the full header (with sha256)."""
        return save_checkpoint(path, self.model, header)
