"""PPO for continuous steering: the config schema, GAE and the clipped-surrogate update.

The update is a pure step over plain inputs: a model, its optimizer and a
:class:`~atdrone.learn.rollout.Fragment` of arrays, so it can run in another process (a
Ray learner) than the rollout. It runs on the device of the model (a GPU when given).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from typing import Any, Literal

import numpy as np
import torch
from torch import nn

from atdrone.config import ConfigError, parse_document
from atdrone.models import PolicyModel
from atdrone.models.networks import NET_LIMITS, ActorCritic, NetConfig, squash_log_prob


@dataclass(frozen=True)
class PPOConfig:
    """PPO hyperparameters. Defaults meet the learning and throughput bars on 2 CPU cores.

    num_envs x rollout_steps environment steps per update (each gives one sample per
    learner drone); epochs passes over them in minibatches of minibatch_size samples.
    collision_credit "team" trains on the task's shared reward; "own" hands the
    collision term only to the learners that collided, times collision_scale (a
    training signal: evaluation always reports the task's own reward).
    history: past frames of its own observations and actions a network reads (0 = the
    current observation only; see atdrone.models.history).
    teammate_coef: the weight of a teammate model's decoder loss (NAHT-D) in the update.
    """

    num_envs: int = 64
    rollout_steps: int = 128
    epochs: int = 4  # 2 until issue 26: 4 reaches 70 % SUC on 4p2e1o in 88 s (median of 7 seeds) against 151 s
    minibatch_size: int = 4096
    lr: float = 1e-3  # 3e-4 until issue 26: 1e-3 reaches 70 % SUC on 4p2e1o in fewer env steps (docs/benchmarks.md)
    lr_schedule: Literal["constant", "linear"] = "linear"
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip: float = 0.2
    vf_coef: float = 0.5
    ent_coef: float = 0.003
    max_grad_norm: float = 0.5
    normalize_advantages: bool = True
    entity_dim: int = 64
    hidden: int = 128
    init_log_std: float = -0.5
    proximity: float = 0.15
    collision_credit: Literal["team", "own"] = "team"
    collision_scale: float = 1.0
    history: int = 0
    teammate_coef: float = 1.0


# The presets as they stood while runs saved only their PPO *overrides* (a config.json "ppo" section of the
# keys a user set). Such a run trained with these values, whatever today's presets hold: a resume completes
# its saved section with them (:func:`saved_ppo_document`). Every field is written out, so a later change of
# a PPOConfig default cannot move them.
_DEFAULT_THEN = PPOConfig(
    num_envs=64,
    rollout_steps=128,
    epochs=2,
    minibatch_size=4096,
    lr=3e-4,
    lr_schedule="linear",
    gamma=0.99,
    gae_lambda=0.95,
    clip=0.2,
    vf_coef=0.5,
    ent_coef=0.003,
    max_grad_norm=0.5,
    normalize_advantages=True,
    entity_dim=64,
    hidden=128,
    init_log_std=-0.5,
    proximity=0.15,
    collision_credit="team",
    collision_scale=1.0,
    history=0,
    teammate_coef=1.0,
)
# The paper's values (SPEC section 10): batch 1024 (8 environments x 128 steps), minibatch 256, 20 epochs,
# constant lr 3e-4, value coefficient 1, entropy 0.01; the rest as the default was then. Unchanged since.
_PAPER = replace(
    _DEFAULT_THEN, num_envs=8, epochs=20, minibatch_size=256, lr_schedule="constant", vf_coef=1.0, ent_coef=0.01
)
OVERRIDES_ERA_PRESETS: dict[str, PPOConfig] = {"default": _DEFAULT_THEN, "paper": _PAPER}
PRESETS: dict[str, PPOConfig] = {"default": PPOConfig(), "paper": _PAPER}


# sizes that allocate memory: environments x steps of one update are held at once
MAX_SAMPLES = 2**24
PPO_LIMITS = {"num_envs": (1, 65_536), "rollout_steps": (1, 100_000), "epochs": (1, 1000), "minibatch_size": (1, 2**24)}


def ppo_config(document: dict[str, Any] | None = None, preset: str = "default", path: str = "ppo") -> PPOConfig:
    """A validated PPOConfig: ``preset`` values overridden by ``document``'s keys."""
    if preset not in PRESETS:
        raise ConfigError(f"{path}.preset", f"must be one of {sorted(PRESETS)}, got {preset!r}")
    if not document:
        return PRESETS[preset]
    parse_document(PPOConfig, {**_as_dict(PRESETS[preset]), **document}, path)  # type/unknown-key check
    cfg = replace(PRESETS[preset], **document)
    for name, (low, high) in {**PPO_LIMITS, **NET_LIMITS}.items():
        if not low <= getattr(cfg, name) <= high:
            raise ConfigError(f"{path}.{name}", f"must be between {low} and {high:,}, got {getattr(cfg, name):,}")
    if cfg.num_envs * cfg.rollout_steps > MAX_SAMPLES:
        raise ConfigError(
            f"{path}.num_envs",
            f"num_envs x rollout_steps must be <= {MAX_SAMPLES:,} per update, got {cfg.num_envs:,}"
            f" x {cfg.rollout_steps:,}",
        )
    if cfg.teammate_coef < 0:
        raise ConfigError(f"{path}.teammate_coef", f"must be >= 0, got {cfg.teammate_coef}")
    for name in ("lr", "clip", "max_grad_norm"):
        if getattr(cfg, name) <= 0:
            raise ConfigError(f"{path}.{name}", f"must be > 0, got {getattr(cfg, name)}")
    if cfg.collision_scale < 0:
        raise ConfigError(f"{path}.collision_scale", f"must be >= 0, got {cfg.collision_scale}")
    for name in ("gamma", "gae_lambda"):
        if not 0 <= getattr(cfg, name) <= 1:
            raise ConfigError(f"{path}.{name}", f"must be in [0, 1], got {getattr(cfg, name)}")
    return cfg


def ppo_document(cfg: PPOConfig) -> dict[str, Any]:
    """Every PPO value a config trains with (a resolved :func:`ppo_config`): what a run saves in its config, so
    that a later change of a preset or a default cannot change a resumed run."""
    return _as_dict(cfg)


def saved_ppo_document(config: Mapping[str, Any]) -> dict[str, Any]:
    """A saved run config (config.json) with its "ppo" section whole, as the run trained with it.

    A section that names every PPO field is returned as saved. One saved before runs stored every value
    holds only the overrides of its preset: they are completed with that preset as it stood then
    (:data:`OVERRIDES_ERA_PRESETS`), not with today's, so a resume compares what the run really used.
    """
    section = config.get("ppo")
    preset = config.get("preset", "default")
    if not isinstance(section, Mapping) or set(section) >= {f.name for f in fields(PPOConfig)}:
        return dict(config)
    if preset not in OVERRIDES_ERA_PRESETS:
        return dict(config)  # an unknown preset: the comparison names it
    return {**config, "ppo": {**_as_dict(OVERRIDES_ERA_PRESETS[preset]), **section}}


def net_config(cfg: PPOConfig, centralised_critic: bool = False) -> NetConfig:
    """The network architecture a PPO config asks for."""
    return NetConfig(
        entity_dim=cfg.entity_dim,
        hidden=cfg.hidden,
        init_log_std=cfg.init_log_std,
        centralised_critic=centralised_critic,
        proximity=cfg.proximity,
        history=cfg.history,
    )


def architecture(cfg: PPOConfig, centralised_critic: bool = False) -> dict[str, Any]:
    """The architecture header (see :mod:`atdrone.models.architectures`) of the network a PPO config asks for."""
    return ActorCritic.header(net_config(cfg, centralised_critic))


def _as_dict(cfg: PPOConfig) -> dict[str, Any]:
    return dict(cfg.__dict__)


def gae(
    rewards: np.ndarray, values: np.ndarray, dones: np.ndarray, last_values: np.ndarray, gamma: float, lam: float
) -> tuple[np.ndarray, np.ndarray]:
    """Generalised advantage estimates and returns, vectorised over all but time.

    rewards, values (T, ...); dones (T, ...) true where the episode ended at that step
    (the next value is then not bootstrapped; timeouts fold their bootstrap into the
    reward beforehand); last_values (...) the value after the last step.
    """
    T = rewards.shape[0]
    adv = np.zeros_like(rewards, dtype=np.float32)
    running = np.zeros_like(last_values, dtype=np.float32)
    next_value = last_values
    for t in range(T - 1, -1, -1):
        live = 1.0 - dones[t]
        delta = rewards[t] + gamma * next_value * live - values[t]
        running = delta + gamma * lam * live * running
        adv[t] = running
        next_value = values[t]
    return adv, adv + values


def learning_rate(cfg: PPOConfig, progress: float) -> float:
    """The learning rate at ``progress`` in [0, 1] of the run."""
    if cfg.lr_schedule == "linear":
        return cfg.lr * max(1.0 - progress, 0.05)
    return cfg.lr


Batch = dict[str, np.ndarray]


def minibatches(counts: Sequence[int], size: int, generator: torch.Generator) -> list[tuple[int, torch.Tensor]]:
    """One epoch's minibatches of groups of ``counts`` samples: (group, sample indices) in the order to take
    them. Each group is shuffled and cut in minibatches of ``min(size, its count)`` (a remainder left out);
    with several groups the minibatches are taken in a shuffled order."""
    out = []
    for g, n in enumerate(counts):
        mb = min(size, n)
        order = torch.randperm(n, generator=generator)
        out += [(g, order[start : start + mb]) for start in range(0, n - mb + 1, mb)] if mb else []
    if len(counts) > 1:
        out = [out[int(i)] for i in torch.randperm(len(out), generator=generator)]
    return out


def ppo_update(
    model: PolicyModel,
    optimizer: torch.optim.Optimizer,
    batch: Batch | Sequence[tuple[int, Batch]],
    cfg: PPOConfig,
    num_e: int,
    num_p: int,
    generator: torch.Generator,
    lr: float | None = None,
) -> dict[str, float]:
    """Epochs of clipped-surrogate PPO over a flat batch; returns loss statistics.

    batch: obs (N, D), u (N,) pre-squash actions, logp (N,), adv (N,), ret (N,),
    state (N, S) for a centralised critic, and mates (N, P - 1, 3) for a teammate model
    with a decoder, whose loss (``decoder_loss``) joins the update times teammate_coef.
    Teams of several sizes (:mod:`atdrone.learn.sizes`) come as (pursuers, batch) pairs:
    every minibatch is of one size, the sizes' minibatches shuffled together.
    """
    device = next(model.parameters()).device
    groups = [(num_p, batch)] if isinstance(batch, dict) else list(batch)
    data = [(p, {k: torch.as_tensor(v, device=device) for k, v in b.items()}) for p, b in groups]
    if lr is not None:
        for group in optimizer.param_groups:
            group["lr"] = lr
    stats: dict[str, list[float]] = {k: [] for k in ("policy_loss", "value_loss", "entropy", "approx_kl", "clipfrac")}
    decoder = any("mates" in t for _, t in data) and getattr(model, "decoder", None) is not None
    if decoder:
        stats["decoder_loss"] = []
    params = model.parameter_groups()  # actor and critic: the critic's large gradients must not shrink the actor's
    counts = [t["obs"].shape[0] for _, t in data]
    for _ in range(cfg.epochs):
        for g, order in minibatches(counts, cfg.minibatch_size, generator):
            p, t = data[g]
            idx = order.to(device)
            dist = model.dist(t["obs"][idx], num_e)
            logp = squash_log_prob(dist, t["u"][idx])
            ratio = (logp - t["logp"][idx]).exp()
            adv = t["adv"][idx]
            if cfg.normalize_advantages:
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
            pg = -torch.min(ratio * adv, ratio.clamp(1 - cfg.clip, 1 + cfg.clip) * adv).mean()
            state = t["state"][idx] if "state" in t else None
            v = model.value(t["obs"][idx], num_e, state, p)
            vloss = 0.5 * ((v - t["ret"][idx]) ** 2).mean()
            ent = dist.entropy().mean()
            loss = pg + cfg.vf_coef * vloss - cfg.ent_coef * ent
            if decoder:
                dec = model.decoder_loss(t["obs"][idx], t["mates"][idx])  # type: ignore[attr-defined]
                loss = loss + cfg.teammate_coef * dec
                stats["decoder_loss"].append(float(dec.detach()))
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            for group_params in params:
                nn.utils.clip_grad_norm_(group_params, cfg.max_grad_norm)
            optimizer.step()
            with torch.no_grad():
                log_ratio = logp - t["logp"][idx]
                stats["approx_kl"].append(float(((ratio - 1) - log_ratio).mean()))
                stats["clipfrac"].append(float(((ratio - 1).abs() > cfg.clip).float().mean()))
            stats["policy_loss"].append(float(pg.detach()))
            stats["value_loss"].append(float(vloss.detach()))
            stats["entropy"].append(float(ent.detach()))
    return {k: float(np.mean(v)) if v else 0.0 for k, v in stats.items()}
