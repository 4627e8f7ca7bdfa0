"""Rollout collection on the batched simulator: learners (a torch actor) + partners.

A :class:`RolloutWorker` owns a BatchedPursuit and a Match that fills the learner
slots with the current network and the rest with partner policies (and keeps the
learners' past frames when the network reads them). ``collect``
returns a :class:`Fragment` of plain arrays (no torch objects), so fragments can
travel between processes; weights come in as a state_dict.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from atdrone.config import TaskConfig
from atdrone.envs.core import DONE_REASONS, TIMEOUT, BatchedPursuit
from atdrone.learn.ppo import gae
from atdrone.models.history import ObsHistory, input_dim
from atdrone.models.networks import ActorCritic, NetConfig, global_state, squash_log_prob
from atdrone.policies.base import Policy
from atdrone.teams.match import Match, PartnerSampler


@dataclass
class Fragment:
    """T steps of B environments with k learner drones each (arrays, time-major)."""

    obs: np.ndarray  # (T, B, k, D) float32 network inputs (with past frames when the network reads them)
    u: np.ndarray  # (T, B, k) pre-squash actions
    logp: np.ndarray  # (T, B, k)
    values: np.ndarray  # (T, B, k)
    rewards: np.ndarray  # (T, B, k), timeouts include gamma * V(final obs)
    dones: np.ndarray  # (T, B)
    last_values: np.ndarray  # (B, k)
    state: np.ndarray | None = None  # (T, B, S) global state for a centralised critic
    episodes: list[dict[str, Any]] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)

    @property
    def samples(self) -> int:
        """Learner drone-steps in the fragment."""
        return int(np.prod(self.u.shape))

    def batch(self, gamma: float, lam: float) -> dict[str, np.ndarray]:
        """Flat PPO batch (N = T * B * k) with advantages and returns."""
        dones = np.broadcast_to(self.dones[..., None], self.rewards.shape).astype(np.float32)
        adv, ret = gae(self.rewards, self.values, dones, self.last_values, gamma, lam)
        out = {
            "obs": self.obs.reshape(-1, self.obs.shape[-1]),
            "u": self.u.reshape(-1),
            "logp": self.logp.reshape(-1),
            "adv": adv.reshape(-1),
            "ret": ret.reshape(-1),
        }
        if self.state is not None:
            k = self.u.shape[-1]
            st = np.broadcast_to(self.state[:, :, None, :], (*self.state.shape[:2], k, self.state.shape[-1]))
            out["state"] = st.reshape(-1, self.state.shape[-1])
        return out


def concat_fragments(fragments: Sequence[Fragment]) -> Fragment:
    """Join fragments of equal length along the environment axis."""
    if len(fragments) == 1:
        return fragments[0]
    cat = lambda name, axis: np.concatenate([getattr(f, name) for f in fragments], axis)
    return Fragment(
        obs=cat("obs", 1),
        u=cat("u", 1),
        logp=cat("logp", 1),
        values=cat("values", 1),
        rewards=cat("rewards", 1),
        dones=cat("dones", 1),
        last_values=cat("last_values", 0),
        state=cat("state", 1) if fragments[0].state is not None else None,
        episodes=[e for f in fragments for e in f.episodes],
        timings={k: sum(f.timings.get(k, 0.0) for f in fragments) for k in fragments[0].timings},
    )


def credited_rewards(
    rewards: np.ndarray, info: dict[str, Any], collision: float, credit: str, scale: float
) -> np.ndarray:
    """Learner rewards (B, k) with the shared collision term re-credited for training.

    The task pays ``collision`` to every pursuer when any pursuer collides. "team"
    keeps that, times ``scale``; "own" pays ``scale * collision`` only to the learners
    in a collision (info["collided"] at their slots, info["team"]["learner_slots"]).
    """
    collided = info["collided"]  # (B, P)
    shared = collision * collided.any(-1, keepdims=True)
    if credit == "team":
        return (rewards + (scale - 1.0) * shared).astype(np.float32)
    if credit != "own":
        raise ValueError(f"collision credit must be 'team' or 'own', got {credit!r}")
    slots = info["team"]["learner_slots"]
    own = np.take_along_axis(collided, slots, axis=1)
    return (rewards - shared + scale * collision * own).astype(np.float32)


class RolloutWorker:
    """Collects fragments for the learners of one BatchedPursuit (see the module docstring)."""

    def __init__(
        self,
        task: TaskConfig | str,
        num_envs: int,
        seed: int,
        net: NetConfig,
        partners: Sequence[Policy] = (),
        num_ctrl: int | None = None,
        sampler: PartnerSampler | None = None,
        gamma: float = 0.99,
        collision_credit: str = "team",
        collision_scale: float = 1.0,
    ) -> None:
        self.core = BatchedPursuit(task, num_envs=num_envs, seed=seed)
        if num_ctrl is None:
            num_ctrl = self.core.cfg.players.num_ctrl if partners else self.core.num_p
        self.match = Match(self.core, partners, seed=seed + 1, num_ctrl=num_ctrl, sampler=sampler)
        self.model = ActorCritic(net)
        self.model.eval()
        self.gamma = gamma
        self.collision_credit = collision_credit
        self.collision_scale = collision_scale
        self.generator = torch.Generator().manual_seed(seed + 2)
        self.obs = self.match.reset(seed=seed)
        self.num_e = self.core.num_e
        B, k = self.obs.shape[:2]
        self._rows = np.repeat(np.arange(B), k)
        self._keys = np.tile(np.arange(k), B)
        self.memory = ObsHistory(net.history, B, k, self.core.obs_dim) if net.history else None

    def inputs(self, obs: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Network inputs (n, k, input_dim) of learner observations (n, k, D) of envs ``rows`` (default all)."""
        if self.memory is None:
            return obs
        n, k, D = obs.shape
        env = self._rows if rows is None else np.repeat(rows, k)
        key = np.tile(np.arange(k), n)
        return self.memory.augment(obs.reshape(n * k, D), env, key).reshape(n, k, -1)

    def set_weights(self, state_dict: dict[str, torch.Tensor]) -> None:
        self.model.load_state_dict(state_dict)

    def _state(self) -> np.ndarray | None:
        if self.model.global_encoder is None:
            return None
        return global_state(self.core.state, self.core.geometry, self.core.num_p)

    @torch.no_grad()
    def _values(self, obs: np.ndarray, state: np.ndarray | None) -> np.ndarray:
        st = None
        if state is not None:
            st = torch.from_numpy(np.broadcast_to(state[:, None], (*obs.shape[:2], state.shape[-1])).copy())
        return self.model.value(torch.from_numpy(obs), self.num_e, st, self.core.num_p).numpy()

    @torch.no_grad()
    def collect(self, steps: int) -> Fragment:
        """Step every environment ``steps`` times with the current weights."""
        B, k, D = self.obs.shape
        obs = np.empty((steps, B, k, input_dim(D, self.model.cfg.history)), np.float32)
        u = np.empty((steps, B, k), np.float32)
        logp = np.empty((steps, B, k), np.float32)
        values = np.empty((steps, B, k), np.float32)
        rewards = np.empty((steps, B, k), np.float32)
        dones = np.empty((steps, B), bool)
        episodes: list[dict[str, Any]] = []
        t_inf = t_sim = 0.0
        state = self._state()
        central = state is not None
        states = np.empty((steps, B, state.shape[-1]), np.float32) if state is not None else None
        for t in range(steps):
            t0 = time.perf_counter()
            inputs = self.inputs(self.obs)
            dist = self.model.dist(torch.from_numpy(inputs), self.num_e)
            ut = dist.mean + dist.stddev * torch.randn(dist.mean.shape, generator=self.generator)
            lp = squash_log_prob(dist, ut)
            v = self._values(inputs, state)
            actions = torch.tanh(ut).numpy()
            t1 = time.perf_counter()
            next_obs, r, d, info = self.match.step(actions)
            if self.collision_credit != "team" or self.collision_scale != 1.0:
                r = credited_rewards(
                    r, info, self.core.cfg.task.reward.collision, self.collision_credit, self.collision_scale
                )
            t2 = time.perf_counter()
            obs[t], u[t], logp[t], values[t], rewards[t], dones[t] = inputs, ut.numpy(), lp.numpy(), v, r, d
            if self.memory is not None:
                self.memory.record(self.obs.reshape(B * k, D), self._rows, self._keys, actions.reshape(-1))
            if states is not None:
                states[t] = state
            if d.any():
                idx = np.flatnonzero(d)
                timeout = idx[info["done_reason"][idx] == TIMEOUT]
                if len(timeout):
                    fs = None
                    if central:
                        assert self.core.final_state is not None  # set by the core at every episode end
                        fs = global_state(self.core.final_state, self.core.geometry, self.core.num_p)[timeout]
                    final = self.inputs(info["final_obs"][timeout], timeout)
                    rewards[t, timeout] += self.gamma * self._values(final, fs)
                for i in idx:
                    episodes.append(
                        {
                            "outcome": DONE_REASONS[info["done_reason"][i]],
                            "length": int(info["episode_length"][i]),
                            "return": float(info["episode_return"][i]),
                            "collided": bool(info["episode_collided"][i]),
                        }
                    )
                if self.memory is not None:
                    self.memory.reset(d)
            self.obs = next_obs
            state = self._state()
            t3 = time.perf_counter()
            t_inf += (t1 - t0) + (t3 - t2)
            t_sim += t2 - t1
        last = self._values(self.inputs(self.obs), state)
        return Fragment(
            obs=obs,
            u=u,
            logp=logp,
            values=values,
            rewards=rewards,
            dones=dones,
            last_values=last,
            state=states,
            episodes=episodes,
            timings={"simulation": t_sim, "inference": t_inf},
        )
