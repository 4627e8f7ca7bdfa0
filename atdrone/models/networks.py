"""Actor-critic networks of SPEC section 10, in torch.

Every (mask, distance, sin, cos) entity block of the observation (layout of
:mod:`atdrone.envs.core`) goes through an encoder for its kind (evader, obstacle,
teammate) as (distance, sin, cos) plus a proximity feature exp(-d / proximity), d in
metres (0.15 m by default): the observation's distance / 5 barely changes between a
safe 0.15 m and a colliding 0.1 m, and without this feature self-play policies kept
flying into the obstacle. Evaders and teammates are mean-pooled over the visible ones,
so one network serves any number of them (4p2e and 4p3e alike). Two hidden layers of 128
follow. The actor outputs the mean of a Gaussian over the pre-squash action u; the
action is tanh(u) in [-1, 1]; the log-std is a free parameter. The critic is a
separate network of the same shape. The MAPPO critic adds the global state, pooled
the same way (pursuers and evaders in absolute arena coordinates).

With ``history`` h > 0 (:mod:`atdrone.models.history`) the input also holds the drone's
last h observations and actions: each entity's encoder then reads its features in
every frame (past ones times their mask, plus the mask), so it can see how the entity
moved, and the hidden layers read the past actions. New inputs always come last, so
:meth:`ActorCritic.widen_from` can start a wider network from a narrower one.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from contextvars import ContextVar
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from atdrone.envs.core import DIST_SCALE, ENTITY_FEATURES, PursuitState
from atdrone.envs.geometry import Geometry
from atdrone.models.history import DroneMemory, ObsHistory, StatelessMemory

if TYPE_CHECKING:
    from atdrone.models.architectures import PolicyModel

GLOBAL_PURSUER_FEATURES = 4  # x / width, y / height, sin heading, cos heading
GLOBAL_EVADER_FEATURES = 3  # x / width, y / height, active


@dataclass(frozen=True)
class NetConfig:
    """Architecture: entity embedding width, hidden width, initial log-std, proximity scale (m; 0 = off),
    past frames read (history)."""

    entity_dim: int = 64
    hidden: int = 128
    init_log_std: float = -0.5
    centralised_critic: bool = False
    proximity: float = 0.15
    history: int = 0

    def __post_init__(self) -> None:
        """Sizes within :data:`NET_LIMITS`: a header cannot make the loader allocate a huge network."""
        for name, (low, high) in NET_LIMITS.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"{name} must be an integer between {low} and {high}, got {value!r}")


# the sizes a network may have (the paper's uses entity_dim 64, hidden 128): at most ~2e7 parameters
NET_LIMITS = {"entity_dim": (1, 1024), "hidden": (1, 4096), "history": (0, 64)}


class _NumpyTanh(torch.autograd.Function):
    """tanh by numpy's SIMD kernel (float32 on the CPU: ~7x faster than torch 2.13's, within two ulps of it);
    the gradient is torch's own tanh_backward of the saved output."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor) -> torch.Tensor:
        y = torch.from_numpy(np.tanh(x.detach().numpy()))
        ctx.save_for_backward(y)
        return y

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> torch.Tensor:
        (y,) = ctx.saved_tensors
        return torch.ops.aten.tanh_backward(grad, y)


_TRAINING_KERNELS: ContextVar[bool] = ContextVar("atdrone_training_kernels", default=False)


@contextmanager
def training_kernels() -> Iterator[None]:
    """Within it, :func:`tanh` is numpy's also without gradients: for a learner's rollouts, which only
    training reads (evaluation, deployment and published numbers stay on torch's own kernel)."""
    token = _TRAINING_KERNELS.set(True)
    try:
        yield
    finally:
        _TRAINING_KERNELS.reset(token)


def tanh(x: torch.Tensor) -> torch.Tensor:
    """The networks' activation: :func:`torch.tanh`, by numpy's kernel when training on the CPU.

    torch 2.13's CPU tanh took a quarter of a PPO update and a third of a rollout's inference (2.6 ns per
    float32 element against numpy's 0.37; issue 26). numpy's runs in an update's autograd pass and in
    rollouts (:func:`training_kernels`), within two ulps of torch's. Elsewhere (evaluation, deployment,
    the Zoo and published weights) torch's own runs, so every evaluated number is reproduced bit for bit.
    """
    if x.device.type == "cpu" and x.dtype == torch.float32:
        if x.requires_grad and torch.is_grad_enabled():
            return _NumpyTanh.apply(x)
        if _TRAINING_KERNELS.get():
            return torch.from_numpy(np.tanh(x.numpy()))
    return torch.tanh(x)


class Tanh(nn.Module):
    """:class:`torch.nn.Tanh` by :func:`tanh` (no parameters: state dicts are unchanged)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return tanh(x)


class _LinearFn(torch.autograd.Function):
    """F.linear whose weight gradient is computed as (x^T g)^T: MKL runs that 1.5-5x faster than autograd's
    g^T x for the networks' shapes (4,096-12,288 rows into 4-194 inputs; issue 26)."""

    @staticmethod
    def forward(ctx: Any, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        return F.linear(x, weight, bias)

    @staticmethod
    def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
        x, weight = ctx.saved_tensors
        g = grad.reshape(-1, grad.shape[-1])
        grad_x = (g @ weight).reshape(x.shape) if ctx.needs_input_grad[0] else None
        grad_w = x.reshape(-1, x.shape[-1]).t().mm(g).t().contiguous() if ctx.needs_input_grad[1] else None
        grad_b = g.sum(0) if ctx.needs_input_grad[2] else None
        return grad_x, grad_w, grad_b


class Linear(nn.Linear):
    """:class:`torch.nn.Linear` (same parameters and forward) with a faster weight gradient (:class:`_LinearFn`)."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.is_grad_enabled() and (self.weight.requires_grad or x.requires_grad):
            return _LinearFn.apply(x, self.weight, self.bias)
        return F.linear(x, self.weight, self.bias)


def _layer(n_in: int, n_out: int, gain: float = math.sqrt(2)) -> nn.Linear:
    layer = Linear(n_in, n_out)
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


def split_entities(obs: torch.Tensor, num_e: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(..., obs_dim) -> evader (..., E, 4), obstacle (..., 4), teammate (..., P-1, 4) blocks."""
    blocks = obs.reshape(*obs.shape[:-1], -1, ENTITY_FEATURES)
    return blocks[..., :num_e, :], blocks[..., num_e, :], blocks[..., num_e + 1 :, :]


def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of x (..., M, F) over the M entities where mask (..., M) is 1; zeros when none."""
    m = mask.unsqueeze(-1)
    return (x * m).sum(-2) / m.sum(-2).clamp(min=1.0)


class EntityTrunk(nn.Module):
    """Per-entity encoders, pooling and two hidden layers: obs -> features (hidden)."""

    def __init__(self, cfg: NetConfig, extra: int = 0) -> None:
        super().__init__()
        d = cfg.entity_dim
        self.proximity = cfg.proximity
        self.history = cfg.history
        per_frame = 4 if cfg.proximity > 0 else 3
        n_in = per_frame + cfg.history * (per_frame + 1)
        self.evader = nn.Sequential(_layer(n_in, d), Tanh())
        self.obstacle = nn.Sequential(_layer(n_in, d), Tanh())
        self.mate = nn.Sequential(_layer(n_in, d), Tanh())
        self.body = nn.Sequential(
            _layer(3 * d + 2 + extra + cfg.history, cfg.hidden), Tanh(), _layer(cfg.hidden, cfg.hidden), Tanh()
        )

    def _features(self, block: torch.Tensor) -> torch.Tensor:
        """(..., 4) [mask, d / 5, sin, cos] -> encoder input (d / 5, sin, cos[, mask * exp(-d / proximity)])."""
        x = block[..., 1:]
        if self.proximity > 0:
            near = torch.exp(-block[..., 1:2] * (DIST_SCALE / self.proximity)) * block[..., :1]
            x = torch.cat([x, near], -1)
        return x

    def _with_past(self, block: torch.Tensor, past: torch.Tensor | None) -> torch.Tensor:
        """Encoder input of entity blocks (..., [M,] 4), past ones (h, ..., [M,] 4) appended per frame."""
        x = self._features(block)
        if past is None:
            return x
        frames = [x]
        for p in past:
            frames += [self._features(p) * p[..., :1], p[..., :1]]
        return torch.cat(frames, -1)

    def forward(self, obs: torch.Tensor, num_e: int, extra: torch.Tensor | None = None) -> torch.Tensor:
        h = self.history
        past_acts = None
        past: tuple[torch.Tensor | None, ...] = (None, None, None)
        if h:
            D = (obs.shape[-1] - h) // (h + 1)
            frames = obs[..., D : D * (h + 1)].reshape(*obs.shape[:-1], h, D)
            past = tuple(p.movedim(obs.dim() - 1, 0) for p in split_entities(frames, num_e))  # frame axis first
            past_acts = obs[..., D * (h + 1) :]
            obs = obs[..., :D]
        ev, ob, tm = split_entities(obs, num_e)
        parts = [
            masked_mean(self.evader(self._with_past(ev, past[0])), ev[..., 0]),
            self.obstacle(self._with_past(ob, past[1])),
            masked_mean(self.mate(self._with_past(tm, past[2])), tm[..., 0]),
        ]
        parts.append(torch.stack([ev[..., 0].mean(-1), tm[..., 0].mean(-1)], -1))  # visible fractions
        if extra is not None:
            parts.append(extra)
        if past_acts is not None:
            parts.append(past_acts)
        return self.body(torch.cat(parts, -1))


class GlobalEncoder(nn.Module):
    """Pooled encoding of the global state for the MAPPO critic."""

    def __init__(self, cfg: NetConfig) -> None:
        super().__init__()
        self.pursuer = nn.Sequential(_layer(GLOBAL_PURSUER_FEATURES, cfg.entity_dim), Tanh())
        self.evader = nn.Sequential(_layer(GLOBAL_EVADER_FEATURES - 1, cfg.entity_dim), Tanh())
        self.out_dim = 2 * cfg.entity_dim

    def forward(self, state: torch.Tensor, num_p: int) -> torch.Tensor:
        p = state[..., : num_p * GLOBAL_PURSUER_FEATURES].reshape(*state.shape[:-1], num_p, GLOBAL_PURSUER_FEATURES)
        e = state[..., num_p * GLOBAL_PURSUER_FEATURES :].reshape(*state.shape[:-1], -1, GLOBAL_EVADER_FEATURES)
        pooled_p = self.pursuer(p).mean(-2)
        pooled_e = masked_mean(self.evader(e[..., :2]), e[..., 2])
        return torch.cat([pooled_p, pooled_e], -1)


def global_state(state: PursuitState, geometry: Geometry, num_p: int) -> np.ndarray:
    """(B, state_dim) float32: every pursuer's (x, y, sin, cos) then every evader's (x, y, active)."""
    s, P = state, num_p
    scale = np.array([geometry.width, geometry.height])
    pur = np.concatenate(
        [s.pos[:, :P] / scale, np.sin(s.heading[:, :P])[..., None], np.cos(s.heading[:, :P])[..., None]], -1
    )
    eva = np.concatenate([s.pos[:, P:] / scale, (~s.captured)[..., None]], -1)
    B = s.pos.shape[0]
    return np.concatenate([pur.reshape(B, -1), eva.reshape(B, -1)], -1).astype(np.float32)


class ActorCritic(nn.Module):
    """Tanh-Gaussian actor and separate critic over the entity observation."""

    def __init__(self, cfg: NetConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg or NetConfig()
        self.actor = EntityTrunk(self.cfg)
        self.mu = _layer(self.cfg.hidden, 1, gain=0.01)
        self.log_std = nn.Parameter(torch.full((1,), self.cfg.init_log_std))
        self.global_encoder = GlobalEncoder(self.cfg) if self.cfg.centralised_critic else None
        extra = self.global_encoder.out_dim if self.global_encoder is not None else 0
        self.critic = EntityTrunk(self.cfg, extra=extra)
        self.value_head = _layer(self.cfg.hidden, 1, gain=1.0)

    @classmethod
    def from_architecture(cls, config: Mapping[str, Any]) -> ActorCritic:
        """The network of a header's architecture entry (NetConfig fields; absent ones take defaults)."""
        return cls(NetConfig(**config))

    @property
    def centralised(self) -> bool:
        return self.global_encoder is not None

    def architecture(self) -> dict[str, Any]:
        return self.header(self.cfg)

    @staticmethod
    def header(cfg: NetConfig) -> dict[str, Any]:
        """The checkpoint header's architecture entry of an ActorCritic with ``cfg``."""
        return {"class": "ActorCritic", **asdict(cfg)}

    def memory(self, num_envs: int, num_keys: int, obs_dim: int) -> DroneMemory:
        """Past frames and actions when the network reads them (``history`` > 0), else the observation alone."""
        if self.cfg.history:
            return ObsHistory(self.cfg.history, num_envs, num_keys, obs_dim)
        return StatelessMemory(obs_dim)

    def widen_from(self, other: PolicyModel) -> None:
        """Take a narrower model's weights: a decentralised critic, fewer past frames.

        Every parameter is copied; where this model has more inputs (the global state
        of a centralised critic, past frames and actions) they come last and get zero
        weights, so actions and values start exactly as ``other``'s and the new inputs
        are learned from there.
        """
        if not isinstance(other, ActorCritic):
            raise ValueError(f"widen_from takes an ActorCritic, not {type(other).__name__}")
        if other.global_encoder is not None and self.global_encoder is None:
            raise ValueError("widen_from cannot drop a centralised critic")
        if other.cfg.history > self.cfg.history:
            raise ValueError(f"widen_from cannot drop past frames ({other.cfg.history} > {self.cfg.history})")
        if replace(other.cfg, centralised_critic=self.cfg.centralised_critic, history=self.cfg.history) != self.cfg:
            raise ValueError(f"architecture {other.cfg} does not match {self.cfg} beyond the critic and history")
        own = self.state_dict()
        for name, value in other.state_dict().items():
            if own[name].shape == value.shape:
                own[name] = value.clone()
            else:  # a first layer (out, inputs): the old inputs lead, the new ones are zero
                wide = torch.zeros_like(own[name])
                wide[:, : value.shape[1]] = value
                own[name] = wide
        self.load_state_dict(own)

    def parameter_groups(self) -> tuple[list[nn.Parameter], list[nn.Parameter]]:
        """(actor parameters, critic parameters), clipped separately by PPO."""
        critic = {
            id(p) for m in (self.critic, self.value_head, self.global_encoder) if m is not None for p in m.parameters()
        }
        params = list(self.parameters())
        return [p for p in params if id(p) not in critic], [p for p in params if id(p) in critic]

    def dist(self, obs: torch.Tensor, num_e: int) -> torch.distributions.Normal:
        """Gaussian over the pre-squash action u, shape (...)."""
        mu = self.mu(self.actor(obs, num_e)).squeeze(-1)
        return torch.distributions.Normal(mu, self.log_std.exp().expand_as(mu))

    def value(self, obs: torch.Tensor, num_e: int, state: torch.Tensor | None = None, num_p: int = 0) -> torch.Tensor:
        extra = None
        if self.global_encoder is not None:
            if state is None:
                raise ValueError("the centralised critic needs the global state")
            extra = self.global_encoder(state, num_p)
        return self.value_head(self.critic(obs, num_e, extra)).squeeze(-1)


def squash_log_prob(dist: torch.distributions.Normal, u: torch.Tensor) -> torch.Tensor:
    """log pi(a) of a = tanh(u): the Gaussian log-density of u minus log(1 - tanh(u)^2)."""
    log_det = 2.0 * (math.log(2.0) - u - F.softplus(-2.0 * u))  # = log(1 - tanh(u)^2), stable
    return dist.log_prob(u) - log_det


def action_log_prob(dist: torch.distributions.Normal, action: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """log pi(a) for an action given in [-1, 1] (e.g. from another policy), clamped off the bounds."""
    a = action.clamp(-1.0 + eps, 1.0 - eps)
    return squash_log_prob(dist, torch.atanh(a))
