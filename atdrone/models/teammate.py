"""NAHT-D's network (the paper's appendix "NAHT-D algorithm"): MAPPO plus a teammate model.

The teammate model reads the drone's last ``history`` = k steps besides the current one
(the per-drone memory of :mod:`atdrone.models.history`: observations and own actions)
as three streams, each through its own fully connected layer:

- evaders: the evader blocks of the k + 1 frames;
- own state: the nearest-obstacle block of the k + 1 frames and the last k own turns;
- teammates: the teammate blocks (relative positions) of the k + 1 frames.

The three stream features are combined by a learned weighted average (softmax weights)
into one ``embed_dim`` (16) embedding. The actor reads the current observation (the
entity trunk of :mod:`atdrone.models.networks`) plus the embedding; the critic is
MAPPO's centralised critic over the global state, plus the embedding when
``critic_embedding``. The decoder (absent when ``decoder`` is false: "w/o Dec") maps
the embedding to a Gaussian over each teammate's pre-squash action, teammates in the
observation's slot order; :meth:`TeammateActorCritic.decoder_loss` scores it against
what the teammates did (see that method). ``detach_embedding`` keeps the policy and
value losses out of the encoder (it then learns from the decoder alone, as POAM does).

Streams keep every entity (no pooling), so the encoder is built for the task shape
(``num_p``, ``num_e``) of its config. In a team of another size (the trunks pool, so the
actor and critic read any size) the encoder reads the entities it was built for: with
fewer, the missing blocks are masked, as an entity beyond reception range is; with more,
it reads the nearest in range at the current step (in index order), the same ones in
every past frame. The decoder predicts the teammates the encoder reads, so its targets
are fitted the same way (:meth:`TeammateActorCritic.fit_mates`), and NAHT-D trains at
drawn team sizes (:mod:`atdrone.learn.sizes`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import torch
from torch import nn

from atdrone.envs.core import ENTITY_FEATURES
from atdrone.models.history import DroneMemory, ObsHistory
from atdrone.models.networks import NET_LIMITS, EntityTrunk, GlobalEncoder, NetConfig, Tanh, _layer

if TYPE_CHECKING:
    from atdrone.models.architectures import PolicyModel

LOG_STD_RANGE = (-5.0, 2.0)  # the decoder's predicted log-std, clamped
MATE_TARGETS = 3  # per teammate: executed turn in [-1, 1], mean and std of its pre-squash Gaussian (NaN: a rule)


@dataclass(frozen=True)
class TeammateConfig:
    """The network: the actor-critic's sizes (entity_dim, hidden, init_log_std, proximity), the task
    shape, past steps read (history >= 1), the embedding width, the decoder's hidden width, and the
    choices the paper leaves open (decoder on, critic_embedding, detach_embedding)."""

    num_p: int = 4
    num_e: int = 2
    history: int = 1
    embed_dim: int = 16
    decoder_hidden: int = 64
    decoder: bool = True
    critic_embedding: bool = True
    detach_embedding: bool = False
    entity_dim: int = 64
    hidden: int = 128
    init_log_std: float = -0.5
    proximity: float = 0.15

    def __post_init__(self) -> None:
        limits = {
            **NET_LIMITS,
            "history": (1, NET_LIMITS["history"][1]),
            "num_p": (2, 64),
            "num_e": (1, 64),
            "embed_dim": (1, 1024),
            "decoder_hidden": (1, 4096),
        }
        for name, (low, high) in limits.items():
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
                raise ValueError(f"{name} must be an integer between {low} and {high}, got {value!r}")
        if self.detach_embedding and not self.decoder:
            raise ValueError("detach_embedding needs the decoder: without it nothing would train the encoder")

    def net(self) -> NetConfig:
        """The entity trunk's config: the current observation only (the encoder reads the past)."""
        return NetConfig(
            entity_dim=self.entity_dim,
            hidden=self.hidden,
            init_log_std=self.init_log_std,
            centralised_critic=True,
            proximity=self.proximity,
            history=0,
        )


class TeammateEncoder(nn.Module):
    """Three streams of the last k + 1 frames -> one embedding (learned weighted average)."""

    def __init__(self, cfg: TeammateConfig) -> None:
        super().__init__()
        frames, F = cfg.history + 1, ENTITY_FEATURES
        self.cfg = cfg
        self.evaders = nn.Sequential(_layer(frames * cfg.num_e * F, cfg.embed_dim), Tanh())
        self.own = nn.Sequential(_layer(frames * F + cfg.history, cfg.embed_dim), Tanh())
        self.mates = nn.Sequential(_layer(frames * (cfg.num_p - 1) * F, cfg.embed_dim), Tanh())
        self.stream_logits = nn.Parameter(torch.zeros(3))

    def weights(self) -> torch.Tensor:
        """The weighted average's weights over (evaders, own state, teammates)."""
        return torch.softmax(self.stream_logits, 0)

    def forward(self, inputs: torch.Tensor, num_e: int | None = None) -> torch.Tensor:
        """The embedding of inputs (..., input width) of a team with ``num_e`` evaders (default: the config's)."""
        cfg, h = self.cfg, self.cfg.history
        D = obs_width(inputs, h)
        E = cfg.num_e if num_e is None else num_e
        lead = inputs.shape[:-1]
        frames = inputs[..., : D * (h + 1)].reshape(*lead, h + 1, D // ENTITY_FEATURES, ENTITY_FEATURES)
        past_actions = inputs[..., D * (h + 1) :]
        streams = torch.stack(
            [
                self.evaders(fit_blocks(frames[..., :E, :], cfg.num_e).reshape(*lead, -1)),
                self.own(torch.cat([frames[..., E, :].reshape(*lead, -1), past_actions], -1)),
                self.mates(fit_blocks(frames[..., E + 1 :, :], cfg.num_p - 1).reshape(*lead, -1)),
            ],
            -1,
        )
        return (streams * self.weights()).sum(-1)


def obs_width(inputs: torch.Tensor, history: int) -> int:
    """The observation width D of network inputs (..., (history + 1) * D + history)."""
    D, rest = divmod(inputs.shape[-1] - history, history + 1)
    if rest or D <= 0 or D % ENTITY_FEATURES:
        raise ValueError(f"inputs of width {inputs.shape[-1]} are not {history + 1} observation frames and actions")
    return D


def fit_blocks(blocks: torch.Tensor, n: int) -> torch.Tensor:
    """Entity blocks (..., frames, m, F), newest frame first, as n blocks: masked ones added when m < n; when
    m > n, the n nearest in range in the newest frame (masked ones last, index order kept), in every frame."""
    m = blocks.shape[-2]
    if m == n:
        return blocks
    if m < n:
        pad = blocks.new_zeros(*blocks.shape[:-2], n - m, blocks.shape[-1])
        return torch.cat([blocks, pad], -2)
    order = nearest(blocks[..., 0, :, :], n)
    index = order[..., None, :, None].expand(*blocks.shape[:-2], n, blocks.shape[-1])
    return torch.gather(blocks, -2, index)


def nearest(blocks: torch.Tensor, n: int) -> torch.Tensor:
    """(..., n) indices of the n nearest in range of entity blocks (..., m, F), m >= n, in index order (masked
    ones last among equals: they count as infinitely far)."""
    distance = torch.where(blocks[..., 0] > 0, blocks[..., 1], torch.full_like(blocks[..., 1], math.inf))
    return torch.sort(torch.sort(distance, stable=True, dim=-1).indices[..., :n], -1).values


class TeammateActorCritic(nn.Module):
    """NAHT-D: the teammate encoder's embedding feeds the actor (and the centralised critic); see the module."""

    models_teammates = True  # the rollout records the teammates' actions and distributions for it

    def __init__(self, cfg: TeammateConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg or TeammateConfig()
        net = self.cfg.net()
        E = self.cfg.embed_dim
        self.encoder = TeammateEncoder(self.cfg)
        self.actor = EntityTrunk(net, extra=E)
        self.mu = _layer(net.hidden, 1, gain=0.01)
        self.log_std = nn.Parameter(torch.full((1,), net.init_log_std))
        self.global_encoder = GlobalEncoder(net)
        self.critic = EntityTrunk(net, extra=self.global_encoder.out_dim + (E if self.cfg.critic_embedding else 0))
        self.value_head = _layer(net.hidden, 1, gain=1.0)
        self.decoder = (
            nn.Sequential(
                _layer(E, self.cfg.decoder_hidden),
                Tanh(),
                _layer(self.cfg.decoder_hidden, 2 * (self.cfg.num_p - 1), gain=0.01),
            )
            if self.cfg.decoder
            else None
        )

    @classmethod
    def from_architecture(cls, config: Mapping[str, Any]) -> TeammateActorCritic:
        return cls(TeammateConfig(**config))

    @property
    def centralised(self) -> bool:
        return True

    def architecture(self) -> dict[str, Any]:
        return self.header(self.cfg)

    @staticmethod
    def header(cfg: TeammateConfig) -> dict[str, Any]:
        """The checkpoint header's architecture entry of a network with ``cfg``."""
        return {"class": "TeammateActorCritic", **asdict(cfg)}

    def memory(self, num_envs: int, num_keys: int, obs_dim: int) -> DroneMemory:
        return ObsHistory(self.cfg.history, num_envs, num_keys, obs_dim)

    def widen_from(self, other: PolicyModel) -> None:
        raise ValueError("a NAHT-D network starts from its own architecture only (no widening)")

    def parameter_groups(self) -> tuple[list[nn.Parameter], list[nn.Parameter]]:
        """(actor, encoder and decoder parameters; critic parameters), clipped separately by PPO."""
        critic = {id(p) for m in (self.critic, self.value_head, self.global_encoder) for p in m.parameters()}
        params = list(self.parameters())
        return [p for p in params if id(p) not in critic], [p for p in params if id(p) in critic]

    def embedding(self, inputs: torch.Tensor, for_policy: bool = True, num_e: int | None = None) -> torch.Tensor:
        """The teammate embedding (..., embed_dim); detached for the policy when ``detach_embedding``."""
        z = self.encoder(inputs, num_e)
        return z.detach() if for_policy and self.cfg.detach_embedding else z

    def dist(self, inputs: torch.Tensor, num_e: int) -> torch.distributions.Normal:
        obs = inputs[..., : obs_width(inputs, self.cfg.history)]
        mu = self.mu(self.actor(obs, num_e, self.embedding(inputs, num_e=num_e))).squeeze(-1)
        return torch.distributions.Normal(mu, self.log_std.exp().expand_as(mu))

    def value(
        self, inputs: torch.Tensor, num_e: int, state: torch.Tensor | None = None, num_p: int = 0
    ) -> torch.Tensor:
        if state is None:
            raise ValueError("the centralised critic needs the global state")
        extra = [self.global_encoder(state, num_p or self.cfg.num_p)]
        if self.cfg.critic_embedding:
            extra.append(self.embedding(inputs, num_e=num_e))
        obs = inputs[..., : obs_width(inputs, self.cfg.history)]
        return self.value_head(self.critic(obs, num_e, torch.cat(extra, -1))).squeeze(-1)

    def decode(self, inputs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Each teammate's predicted pre-squash Gaussian: mean and log-std, (..., num_p - 1) each."""
        if self.decoder is None:
            raise ValueError("this network has no decoder (NAHT-D w/o Dec)")
        out = self.decoder(self.embedding(inputs, for_policy=False))
        mean, log_std = out.reshape(*out.shape[:-1], self.cfg.num_p - 1, 2).unbind(-1)
        return mean, log_std.clamp(*LOG_STD_RANGE)

    def decoder_loss(self, inputs: torch.Tensor, mates: torch.Tensor) -> torch.Tensor:
        """Mean reconstruction loss of the teammates' current actions.

        ``mates`` (..., m, 3): each of the m teammates' executed turn a, and the mean and
        std of its pre-squash action Gaussian (NaN for a rule-based partner). A learned
        teammate scores KL(its Gaussian || the prediction), in pre-squash units; a
        rule-based one, which is deterministic (a KL to a point mass is degenerate), the
        Gaussian negative log-likelihood of the turn it executed, a in [-1, 1], under the
        prediction's squashed mean tanh(mean) and its std (turn units: a turn at the
        limit stays a bounded target). In a team of another size (m != num_p - 1) the
        targets are the teammates the encoder reads (:meth:`fit_mates`); the mean is then
        over those present.
        """
        mean, log_std = self.decode(inputs)
        mates = self.fit_mates(inputs, mates)
        turn, m_p, s_p = mates.unbind(-1)
        learned = torch.isfinite(s_p)
        var = torch.exp(2 * log_std)
        m_safe, s_safe = torch.where(learned, m_p, 0.0), torch.where(learned, s_p, 1.0)
        kl = log_std - torch.log(s_safe) + (s_safe**2 + (m_safe - mean) ** 2) / (2 * var) - 0.5
        nll = log_std + (torch.nan_to_num(turn) - torch.tanh(mean)) ** 2 / (2 * var) + 0.5 * math.log(2 * math.pi)
        loss = torch.where(learned, kl, nll)
        present = torch.isfinite(turn)
        if bool(present.all()):
            return loss.mean()
        return torch.where(present, loss, 0.0).sum() / present.sum().clamp(min=1)

    def fit_mates(self, inputs: torch.Tensor, mates: torch.Tensor) -> torch.Tensor:
        """Decoder targets (..., m, 3) of a team with m teammates as the num_p - 1 the encoder reads
        (:func:`fit_blocks`): absent ones (all NaN) added when m is smaller; when larger, the nearest in range in
        the current observation (``inputs``' newest frame), in index order."""
        n, m = self.cfg.num_p - 1, mates.shape[-2]
        if m == n:
            return mates
        if m < n:
            return torch.cat([mates, mates.new_full((*mates.shape[:-2], n - m, mates.shape[-1]), math.nan)], -2)
        D = obs_width(inputs, self.cfg.history)
        current = inputs[..., :D].reshape(*inputs.shape[:-1], D // ENTITY_FEATURES, ENTITY_FEATURES)
        order = nearest(current[..., self.cfg.num_e + 1 :, :], n)
        return torch.gather(mates, -2, order[..., None].expand(*order.shape, mates.shape[-1]))
