"""Rollout collection on the batched simulator: learners (a torch actor) + partners.

A :class:`RolloutWorker` owns a BatchedPursuit and a Match that fills the learner
slots with the current network and the rest with partner policies drawn per
environment and per episode by the sampler it is given (and keeps the learners'
per-drone memory). ``collect`` returns a :class:`Fragment` of plain arrays (no torch
objects), so fragments can travel between processes; weights come in as a state_dict.
Besides observations, actions and rewards a fragment carries ``extras`` for algorithms
that need more (the learners' slots, the partners' member indices and the turns the
partners actually executed); every finished episode names its partners, and the
profiles drawn for the episodes started are counted (:attr:`RolloutWorker.drawn`), so
what was drawn is what is reported. With team events (``events``, a protocol's plan)
every episode draws its swaps, drops and joins, and a learner drone an event replaces
starts with an empty memory. With a ``split`` (a protocol's ``learners`` range) every
episode draws how many of its slots the learner flies; partners fly the others
(:class:`~atdrone.teams.match.Match`), and those drone-steps are left out of the
update (``Fragment.own``).
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from atdrone.config import TaskConfig
from atdrone.envs.core import DONE_REASONS, TIMEOUT, BatchedPursuit
from atdrone.envs.events import EventPlan
from atdrone.learn.ppo import PPOConfig, gae
from atdrone.models import build_model
from atdrone.models.networks import global_state, squash_log_prob, training_kernels
from atdrone.policies.base import Policy
from atdrone.policies.neural import NeuralPolicy
from atdrone.teams.match import Match, PartnerSampler
from atdrone.teams.partners import LEARNER_COPY


@dataclass
class Fragment:
    """T steps of B environments with k learner drones each (arrays, time-major).

    ``extras``: per environment step (T, B, ...) arrays an algorithm may need beyond
    PPO's: ``learner_slots`` (T, B, k), and with partners ``partner_members`` and
    ``partner_actions`` (T, B, num_partners), the member index and executed turn of
    every partner slot.
    """

    obs: np.ndarray  # (T, B, k, D) float32 network inputs (with the drones' memory when the network reads it)
    u: np.ndarray  # (T, B, k) pre-squash actions
    logp: np.ndarray  # (T, B, k)
    values: np.ndarray  # (T, B, k)
    rewards: np.ndarray  # (T, B, k), timeouts include gamma * V(final obs)
    dones: np.ndarray  # (T, B)
    last_values: np.ndarray  # (B, k)
    state: np.ndarray | None = None  # (T, B, S) global state for a centralised critic
    # (T, B, k, P - 1, 3) for a teammate model: each teammate's executed turn and pre-squash (mean, std)
    mates: np.ndarray | None = None
    episodes: list[dict[str, Any]] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    own: np.ndarray | None = None  # (T, B, k) bool: the learner flew the slot (None: everywhere); else not trained on
    num_p: int = 0  # the team's pursuers (0: not said)

    @property
    def samples(self) -> int:
        """Learner drone-steps in the fragment (that the learner flew)."""
        return int(np.prod(self.u.shape)) if self.own is None else int(self.own.sum())

    def batch(self, gamma: float, lam: float, extras: bool = False) -> dict[str, np.ndarray]:
        """Flat PPO batch (N = T * B * k) with advantages and returns.

        With ``extras`` every extra array is broadcast to each learner of its environment
        step and flattened to (N, ...), under its own name.
        """
        dones = np.broadcast_to(self.dones[..., None], self.rewards.shape).astype(np.float32)
        adv, ret = gae(self.rewards, self.values, dones, self.last_values, gamma, lam)
        out = {
            "obs": self.obs.reshape(-1, self.obs.shape[-1]),
            "u": self.u.reshape(-1),
            "logp": self.logp.reshape(-1),
            "adv": adv.reshape(-1),
            "ret": ret.reshape(-1),
        }
        if self.mates is not None:
            out["mates"] = self.mates.reshape(-1, *self.mates.shape[3:])
        per_env = {"state": self.state} if self.state is not None else {}
        if extras:
            per_env.update(self.extras)
        T, B, k = self.u.shape
        for name, value in per_env.items():
            wide = np.broadcast_to(value[:, :, None], (T, B, k, *value.shape[2:]))
            out[name] = wide.reshape(T * B * k, *value.shape[2:])
        if self.own is not None:  # advantages above ran over every slot; the slots partners flew are dropped here
            keep = self.own.reshape(-1)
            out = {name: value[keep] for name, value in out.items()}
        return out


def concat_fragments(fragments: Sequence[Fragment]) -> Fragment:
    """Join fragments of equal length and team size along the environment axis."""
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
        mates=cat("mates", 1) if fragments[0].mates is not None else None,
        episodes=[e for f in fragments for e in f.episodes],
        timings={k: sum(f.timings.get(k, 0.0) for f in fragments) for k in fragments[0].timings},
        extras={k: np.concatenate([f.extras[k] for f in fragments], 1) for k in fragments[0].extras},
        own=None if fragments[0].own is None else cat("own", 1),
        num_p=fragments[0].num_p,
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
    """Collects fragments for the learners of one BatchedPursuit (see the module docstring).

    ``architecture``: the learners' model header (weights arrive by :meth:`set_weights`);
    ``ppo``: num_envs (unless ``num_envs`` is given: a service worker's share), gamma,
    collision_credit and collision_scale; ``partners`` and ``sampler``: the partner
    policies and how each episode draws them (default uniform per slot); without
    partners the learners fill every slot (self-play). A partner given as None is a
    copy of the learner (:data:`~atdrone.teams.partners.LEARNER_COPY`) that samples the
    current weights: a slot of an episode with fewer partners, not trained on.
    """

    def __init__(
        self,
        task: TaskConfig | str,
        seed: int,
        architecture: dict[str, Any],
        ppo: PPOConfig,
        partners: Sequence[Policy | None] = (),
        num_ctrl: int | None = None,
        sampler: PartnerSampler | None = None,
        num_envs: int | None = None,
        events: EventPlan | None = None,
        split: tuple[int, int] | None = None,
    ) -> None:
        B = ppo.num_envs if num_envs is None else num_envs
        self.core = BatchedPursuit(task, num_envs=B, seed=seed, events=events)
        if num_ctrl is None:
            num_ctrl = self.core.cfg.players.num_ctrl if partners else self.core.num_p
        self.model = build_model(dict(architecture))
        self.model.eval()
        copy = NeuralPolicy(
            self.model, LEARNER_COPY, False, seed + 3, self.core.num_p, self.core.num_e
        )  # flies partner slots given as None, sampling the current weights
        policies = [copy if p is None else p for p in partners]
        if split is not None and not policies:  # self-play: the slots the learner does not fly go to its copy
            policies = [copy]
        self.match = Match(self.core, policies, seed=seed + 1, num_ctrl=num_ctrl, sampler=sampler, split=split)
        self.ppo = ppo
        self.generator = torch.Generator().manual_seed(seed + 2)
        self.obs = self.match.reset(seed=seed)
        self.num_e = self.core.num_e
        B, k = self.obs.shape[:2]
        self._rows = np.repeat(np.arange(B), k)
        self._keys = np.tile(np.arange(k), B)
        self.memory = self.model.memory(B, k, self.core.obs_dim)
        self.models_teammates = bool(getattr(self.model, "models_teammates", False))

    def mate_targets(
        self,
        slots: np.ndarray,
        actions: np.ndarray,
        dists: np.ndarray,
        mean: np.ndarray,
        std: np.ndarray,
        lent: np.ndarray | None = None,
    ) -> np.ndarray:
        """(B, k, P - 1, 3): for each learner (in ``slots`` (B, k)), each teammate in the observation's
        order (the other slots, ascending) with its executed turn (``actions`` (B, P)) and pre-squash
        (mean, std): the learners' own (``mean``, ``std`` (B, k)) but in slots ``lent`` (B, k) to partners, a
        trained partner's from ``dists`` (B, P, 2), NaN for a rule-based partner."""
        P = self.core.num_p
        rows = np.arange(len(slots))[:, None]
        both = dists.copy()
        if lent is not None:
            mean, std = np.where(lent, dists[rows, slots, 0], mean), np.where(lent, dists[rows, slots, 1], std)
        both[rows, slots, 0], both[rows, slots, 1] = mean, std
        table = np.vstack([np.delete(np.arange(P), s) for s in range(P)])  # (P, P - 1)
        others = table[slots]  # (B, k, P - 1)
        r = rows[:, :, None]
        return np.stack([actions[r, others], both[r, others, 0], both[r, others, 1]], -1).astype(np.float32)

    @property
    def drawn(self) -> Counter[str]:
        """Partner profiles ("a|b", ids sorted) drawn for the episodes started so far (the Match's count)."""
        return self.match.drawn

    def inputs(self, obs: np.ndarray, rows: np.ndarray | None = None) -> np.ndarray:
        """Network inputs (n, k, input_dim) of learner observations (n, k, D) of envs ``rows`` (default all)."""
        n, k, D = obs.shape
        if rows is None:
            env, key = self._rows, self._keys
        else:
            env, key = np.repeat(rows, k), np.tile(np.arange(k), n)
        return self.memory.inputs(obs.reshape(n * k, D), env, key).reshape(n, k, -1)

    def set_weights(self, state_dict: dict[str, torch.Tensor]) -> None:
        self.model.load_state_dict(state_dict)

    def _state(self) -> np.ndarray | None:
        if not self.model.centralised:
            return None
        return global_state(self.core.state, self.core.geometry, self.core.num_p)

    @torch.no_grad()
    def _values(self, obs: np.ndarray, state: np.ndarray | None) -> np.ndarray:
        st = None
        if state is not None:
            st = torch.from_numpy(np.broadcast_to(state[:, None], (*obs.shape[:2], state.shape[-1])).copy())
        return self.model.value(torch.from_numpy(obs), self.num_e, st, self.core.num_p).numpy()

    def _record_episodes(self, info: dict[str, Any], idx: np.ndarray, episodes: list[dict[str, Any]]) -> None:
        team = info["team"]
        for i in idx:
            partners = tuple(str(p) for p in team["partners"][i])
            episodes.append(
                {
                    "outcome": DONE_REASONS[info["done_reason"][i]],
                    "length": int(info["episode_length"][i]),
                    "return": float(info["episode_return"][i]),
                    "collided": bool(info["episode_collided"][i]),
                    "partners": partners,
                }
            )

    @training_kernels()
    @torch.no_grad()
    def collect(self, steps: int) -> Fragment:
        """Step every environment ``steps`` times with the current weights (numpy's tanh: only training
        reads a fragment)."""
        B, k, D = self.obs.shape
        u_num = self.match.num_unctrl
        ppo = self.ppo
        collision = self.core.cfg.task.reward.collision
        recredit = ppo.collision_credit != "team" or ppo.collision_scale != 1.0
        obs: np.ndarray | None = None
        u = np.empty((steps, B, k), np.float32)
        logp = np.empty((steps, B, k), np.float32)
        values = np.empty((steps, B, k), np.float32)
        rewards = np.empty((steps, B, k), np.float32)
        dones = np.empty((steps, B), bool)
        extras = {"learner_slots": np.empty((steps, B, k), np.int8)}
        own = np.empty((steps, B, k), bool) if self.match.split is not None else None
        if u_num:
            extras["partner_members"] = np.empty((steps, B, u_num), np.int16)
            extras["partner_actions"] = np.empty((steps, B, u_num), np.float32)
        episodes: list[dict[str, Any]] = []
        t_inf = t_sim = 0.0
        state = self._state()
        states = np.empty((steps, B, state.shape[-1]), np.float32) if state is not None else None
        mates = np.empty((steps, B, k, self.core.num_p - 1, 3), np.float32) if self.models_teammates else None
        for t in range(steps):
            t0 = time.perf_counter()
            inputs = self.inputs(self.obs)
            if obs is None:
                obs = np.empty((steps, *inputs.shape), np.float32)
            dist = self.model.dist(torch.from_numpy(inputs), self.num_e)
            ut = dist.mean + dist.stddev * torch.randn(dist.mean.shape, generator=self.generator)
            lp = squash_log_prob(dist, ut)
            v = self._values(inputs, state)
            actions = torch.tanh(ut).numpy()
            t1 = time.perf_counter()
            slots = self.match.learner_slots.copy()  # the teams of this step, before resets
            extras["learner_slots"][t] = slots
            if own is not None:
                own[t] = ~self.match.lent
            if u_num:
                extras["partner_members"][t] = self.match.members
                partner_slots = self.match.partner_slots.copy()
            next_obs, r, d, info = self.match.step(actions)
            if recredit:
                r = credited_rewards(r, info, collision, ppo.collision_credit, ppo.collision_scale)
            t2 = time.perf_counter()
            obs[t], u[t], logp[t], values[t], rewards[t], dones[t] = inputs, ut.numpy(), lp.numpy(), v, r, d
            if u_num:
                extras["partner_actions"][t] = np.take_along_axis(info["actions"], partner_slots, axis=1)
            if mates is not None:
                mates[t] = self.mate_targets(
                    slots,
                    info["actions"],
                    info["dists"],
                    dist.mean.numpy(),
                    dist.stddev.numpy(),
                    None if own is None else ~own[t],
                )
            self.memory.record(self.obs.reshape(B * k, D), self._rows, self._keys, actions.reshape(-1))
            if "team_changed" in info:  # a new learner drone knows nothing of the episode so far
                self.memory.forget(*self.match.changed_learners(info["team_changed"]))
            if states is not None:
                states[t] = state
            if d.any():
                idx = np.flatnonzero(d)
                timeout = idx[info["done_reason"][idx] == TIMEOUT]
                if len(timeout):
                    fs = None
                    if states is not None:
                        assert self.core.final_state is not None  # set by the core at every episode end
                        fs = global_state(self.core.final_state, self.core.geometry, self.core.num_p)[timeout]
                    final = self.inputs(info["final_obs"][timeout], timeout)
                    rewards[t, timeout] += ppo.gamma * self._values(final, fs)
                self._record_episodes(info, idx, episodes)
                self.memory.reset(d)
            self.obs = next_obs
            state = self._state()
            t3 = time.perf_counter()
            t_inf += (t1 - t0) + (t3 - t2)
            t_sim += t2 - t1
        assert obs is not None
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
            mates=mates,
            episodes=episodes,
            timings={"simulation": t_sim, "inference": t_inf},
            extras=extras,
            own=own,
            num_p=self.core.num_p,
        )
