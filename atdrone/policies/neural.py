"""A trained network as a policy: acts on observations with per-drone memory.

The policy needs no simulator: it acts on an observation array with (env, key) memory
keys, and the task shape (pursuers, evaders) comes from the checkpoint header.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from atdrone.envs.core import ENTITY_FEATURES
from atdrone.envs.streams import normal
from atdrone.models.architectures import PolicyModel
from atdrone.models.checkpoint import load_checkpoint
from atdrone.models.history import DroneMemory
from atdrone.policies.base import DroneBatch, PolicyError

# The network runs on batches padded to a multiple of this many rows: BLAS kernels round
# the rows of a batch's ragged tail (and of batches of 1-3 rows) differently, so a
# drone's action would otherwise depend on how many drones shared its batch.
PAD_ROWS = 64


class NeuralPolicy:
    """A trained actor as a zoo policy: batched, mean action by default.

    ``num_p`` and ``num_e`` are the task shape the network was trained on (from the
    checkpoint header; the default is the paper's 4p2e tasks), ``task`` its name. The network pools
    evaders, so it also flies a task with the same team and another number of evaders:
    the evader count is read off the observation width, 4 * (num_p + num_e).
    Per-drone memory (``model.memory``) is keyed by (env, key), grows with the keys it
    is handed, and forgets an environment's drones when its episode ends (:meth:`reset`).
    """

    def __init__(
        self,
        model: PolicyModel,
        name: str = "neural",
        deterministic: bool = True,
        seed: int = 0,
        num_p: int = 4,
        num_e: int = 2,
        task: str = "",
    ) -> None:
        self.model = model
        self.name = name
        self.deterministic = deterministic
        self.num_p = num_p
        self.num_e = num_e
        self.task = task  # the task it was trained on ("" when unknown)
        self.generator = torch.Generator().manual_seed(seed)
        self.memory: DroneMemory | None = None
        self._obs_dim = 0
        # the pre-squash Gaussian (mean, std), each (M,), of the last act: what a teammate model reconstructs
        self.last_dist: tuple[np.ndarray, np.ndarray] | None = None

    def evaders(self, obs_dim: int) -> int:
        """Evaders in an observation of width ``obs_dim`` for this policy's team of ``num_p``."""
        blocks, rest = divmod(obs_dim, ENTITY_FEATURES)
        if rest or blocks <= self.num_p:
            raise PolicyError(
                f"policy {self.name!r} ({self.num_p} pursuers, trained with {self.num_e} evaders) cannot read "
                f"observations of width {obs_dim} (expected {ENTITY_FEATURES * (self.num_p + self.num_e)})"
            )
        return blocks - self.num_p

    def reset(self, done: np.ndarray) -> None:
        """Forget the memory of the environments where ``done`` (one entry per environment row) is true."""
        if self.memory is None:
            return
        done = np.asarray(done, dtype=bool)
        if done.all():  # nothing left to remember: the next batch may be another size
            self.memory = None
        else:
            self.memory.reset(done)

    def forget(self, env: np.ndarray, slot: np.ndarray) -> None:
        """Forget the drones (env (M,), slot (M,)) alone: another drone took their slot mid-episode."""
        if self.memory is not None:
            self.memory.forget(env, slot)

    def inputs_of(self, obs: np.ndarray, env: np.ndarray, key: np.ndarray) -> np.ndarray:
        """Network inputs (M, input_dim) of observations (M, D) of drones (env, key), from their memory."""
        env, key = np.asarray(env), np.asarray(key)
        D = obs.shape[-1]
        if self.memory is None or self._obs_dim != D:
            size = (int(env.max()) + 1, int(key.max()) + 1) if len(env) else (0, 0)
            self.memory, self._obs_dim = self.model.memory(*size, D), D
        return self.memory.inputs(obs, env, key)

    def inputs(self, batch: DroneBatch) -> np.ndarray:
        """Network inputs of ``batch``: its observations, with past frames when the network reads them."""
        return self.inputs_of(batch.obs, batch.env, batch.slot)

    @torch.no_grad()
    def act_obs(
        self,
        obs: np.ndarray,
        env: np.ndarray,
        key: np.ndarray,
        noise_keys: np.ndarray | None = None,
        num_e: int | None = None,
    ) -> np.ndarray:
        """Actions (M,) in [-1, 1] for observations (M, D) of drones with memory keys (env (M,), key (M,)).

        When sampling, the noise comes from ``noise_keys`` (M,) (one counter-based draw per
        drone) if given, else from the policy's generator. ``num_e``: evaders in the observation (default:
        read off its width for this policy's team size; given, the network acts in a team of another size).
        """
        M = len(obs)
        if M == 0:
            return np.zeros(0)
        env, key = np.asarray(env), np.asarray(key)
        inputs = self.inputs_of(obs, env, key)
        padded = np.zeros((-M // PAD_ROWS * -PAD_ROWS, inputs.shape[1]), inputs.dtype)
        padded[:M] = inputs
        dist = self.model.dist(torch.from_numpy(padded), num_e or self.evaders(obs.shape[-1]))
        mean, std = dist.mean, dist.stddev
        self.last_dist = (mean[:M].numpy().astype(np.float64), std[:M].numpy().astype(np.float64))
        u = mean
        if not self.deterministic:
            eps = torch.zeros_like(u)
            if noise_keys is None:
                eps[:M] = torch.randn((M, *u.shape[1:]), generator=self.generator)
            else:
                eps[:M] = torch.from_numpy(normal(noise_keys)).to(u.dtype).reshape(M, *u.shape[1:])
            u = u + std * eps
        actions = torch.tanh(u)[:M].numpy().astype(np.float64)
        assert self.memory is not None  # made by inputs_of
        self.memory.record(obs, env, key, actions)
        return actions

    def act(self, batch: DroneBatch) -> np.ndarray:
        """Actions (M,) for the drones of ``batch``: its observations, keyed by (env, slot); noise from its keys.

        With poses the evader count is the arena's, so the network (which pools teammates and evaders) acts in
        a team of any size."""
        num_e = batch.poses.arena.num_e if batch.poses is not None else None
        return self.act_obs(batch.obs, batch.env, batch.slot, batch.keys, num_e)


def load_policy(path: str | Path, deterministic: bool = True) -> NeuralPolicy:
    """A checkpoint as a policy in the zoo interface, with the task shape of its header."""
    model, header = load_checkpoint(path)
    return NeuralPolicy(
        model,
        name=header.get("name", Path(path).stem),
        deterministic=deterministic,
        num_p=int(header["num_p"]),
        num_e=int(header["num_e"]),
        task=str(header.get("task", "")),
    )
