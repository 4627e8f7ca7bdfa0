"""A trained network as a policy: acts on observations with per-drone memory."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from atdrone.models.checkpoint import load_checkpoint
from atdrone.models.history import ObsHistory
from atdrone.models.networks import ActorCritic
from atdrone.policies.base import DroneBatch


class NeuralPolicy:
    """A trained actor as a zoo policy: batched, mean action by default.

    A network that reads past frames (``history`` > 0) keeps them per (env, slot) and
    forgets an environment's drones when its episode ends (:meth:`reset`).
    """

    def __init__(self, model: ActorCritic, name: str = "neural", deterministic: bool = True, seed: int = 0) -> None:
        self.model = model
        self.name = name
        self.deterministic = deterministic
        self.generator = torch.Generator().manual_seed(seed)
        self.memory: ObsHistory | None = None

    def reset(self, done: np.ndarray) -> None:
        """Forget the past frames of the environments where ``done`` is true."""
        if self.memory is not None:
            if len(done) == self.memory.shape[0]:
                self.memory.reset(done)
            else:  # a new batch of environments
                self.memory = None

    def inputs(self, batch: DroneBatch) -> np.ndarray:
        """Network inputs of ``batch``: its observations, with past frames when the network reads them."""
        h = self.model.cfg.history
        if not h:
            return np.ascontiguousarray(batch.obs)
        core = batch.core
        if self.memory is None or self.memory.shape != (core.num_envs, core.num_p, core.obs_dim):
            self.memory = ObsHistory(h, core.num_envs, core.num_p, core.obs_dim)
        return self.memory.augment(batch.obs, batch.env, batch.slot)

    @torch.no_grad()
    def act(self, batch: DroneBatch) -> np.ndarray:
        if len(batch) == 0:
            return np.zeros(0)
        dist = self.model.dist(torch.from_numpy(self.inputs(batch)), batch.core.num_e)
        u = dist.mean
        if not self.deterministic:
            u = u + dist.stddev * torch.randn(u.shape, generator=self.generator)
        actions = torch.tanh(u).numpy().astype(np.float64)
        if self.memory is not None:
            self.memory.record(batch.obs, batch.env, batch.slot, actions)
        return actions


def load_policy(path: str | Path, deterministic: bool = True) -> NeuralPolicy:
    """A checkpoint as a policy in the zoo interface."""
    model, header = load_checkpoint(path)
    return NeuralPolicy(model, name=header.get("name", Path(path).stem), deterministic=deterministic)
