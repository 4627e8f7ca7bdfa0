"""The Learner: a model, its optimiser, the PPO update and their state, in one object.

The local trainer (``atdrone train CONFIG``) calls a Learner directly; the service's
learner actor is a thin Ray wrapper around the same object, so both paths update
identically given the same fragments. This module is also the one place that builds a
learner's model (under a seed, without touching the global torch RNG), picks the
device and turns fragments into update statistics.

State (:meth:`Learner.get_state`) is tensors plus JSON: parameters, the optimiser's
moments, the update generator's RNG state, the schedule position and the
hyperparameter overrides. :meth:`Learner.save` writes it as a safetensors file with a
digest (:mod:`atdrone.models.tensorfile`); nothing is unpickled to read it back.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from atdrone.config import ConfigError
from atdrone.learn.ppo import PPOConfig, architecture, learning_rate, ppo_update
from atdrone.learn.rollout import Fragment, concat_fragments
from atdrone.models import PolicyModel, build_model
from atdrone.models.tensorfile import load_tensors, save_tensors

STATE_FORMAT = 1


def check_device(name: str, path: str = "device") -> None:
    """ConfigError unless ``name`` is auto, cpu, or a CUDA device this machine has (cuda, cuda:N)."""
    if name in ("auto", "cpu"):
        return
    try:
        device = torch.device(name)
    except (RuntimeError, ValueError):
        raise ConfigError(path, f"must be auto, cpu, cuda or cuda:N, got {name!r}") from None
    if device.type != "cuda":
        raise ConfigError(path, f"must be auto, cpu, cuda or cuda:N, got {name!r}")
    if not torch.cuda.is_available():
        raise ConfigError(path, f"{name!r} asks for CUDA, but torch sees no GPU here (use auto or cpu)")
    if device.index is not None and device.index >= torch.cuda.device_count():
        raise ConfigError(path, f"{name!r}: this machine has {torch.cuda.device_count()} GPU(s)")


def pick_device(name: str = "auto") -> torch.device:
    """``auto``: CUDA when torch sees a GPU, else the CPU; or the named device (see :func:`check_device`)."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    check_device(name)
    return torch.device(name)


def seeded_model(architecture: Mapping[str, Any], seed: int) -> PolicyModel:
    """A freshly initialised model of ``architecture``, its initial weights drawn from ``seed``."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        return build_model(dict(architecture))


def fragment_stats(frags: Fragment | Sequence[Fragment]) -> dict[str, float]:
    """Episode outcomes and timings of fragments (one, or one per team size), namespaced train/ and perf/."""
    frags = [frags] if isinstance(frags, Fragment) else list(frags)
    samples = sum(f.samples for f in frags)
    out: dict[str, float] = {"train/samples": float(samples)}
    eps = [e for f in frags for e in f.episodes]
    if eps:
        out["train/episodes"] = float(len(eps))
        out["train/success"] = float(np.mean([e["outcome"] == "captured" for e in eps]))
        out["train/collision"] = float(np.mean([e["collided"] for e in eps]))
        out["train/episode_return"] = float(np.mean([e["return"] for e in eps]))
        out["train/episode_length"] = float(np.mean([e["length"] for e in eps]))
    out["perf/simulation_s"] = sum(f.timings.get("simulation", 0.0) for f in frags)
    out["perf/inference_s"] = sum(f.timings.get("inference", 0.0) for f in frags)
    return out


@dataclass(frozen=True)
class LearnerSpec:
    """Everything that builds a Learner: plain data, so it travels to a Ray actor.

    total_updates: the length of the learning-rate schedule in updates (a float: the
    local trainer's env-step budget over the env steps of one update).
    """

    ppo: PPOConfig
    num_e: int
    num_p: int
    seed: int
    total_updates: float
    centralised_critic: bool = False
    device: str = "auto"
    architecture: dict[str, Any] = field(default_factory=dict)

    def model_architecture(self) -> dict[str, Any]:
        """The model's architecture header: given, or the PPO config's network."""
        if self.architecture:
            return dict(self.architecture)
        return architecture(self.ppo, self.centralised_critic)


class Learner:
    """Model + optimiser + PPO update + state (see the module docstring)."""

    def __init__(self, spec: LearnerSpec) -> None:
        if spec.total_updates <= 0:
            raise ValueError(f"total_updates must be > 0, got {spec.total_updates}")
        self.spec = spec
        self.ppo = spec.ppo
        self.device = pick_device(spec.device)
        self.model: PolicyModel = seeded_model(spec.model_architecture(), spec.seed).to(self.device)
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=self.ppo.lr, eps=1e-5)
        self.generator = torch.Generator().manual_seed(spec.seed)
        self.updates = 0
        self.hparams: dict[str, float] = {"lr": self.ppo.lr, "ent_coef": self.ppo.ent_coef}

    # ------------------------------------------------------------- weights
    def get_weights(self) -> dict[str, torch.Tensor]:
        """The model's parameters as CPU tensors (what rollout workers load)."""
        return {k: v.detach().cpu().clone() for k, v in self.model.state_dict().items()}

    def set_weights(self, weights: Mapping[str, torch.Tensor]) -> None:
        self.model.load_state_dict(dict(weights))

    def set_hparams(self, lr: float | None = None, ent_coef: float | None = None) -> None:
        """Override the learning rate (the schedule scales it) and entropy coefficient (PBT)."""
        if lr is not None:
            self.hparams["lr"] = float(lr)
        if ent_coef is not None:
            self.hparams["ent_coef"] = float(ent_coef)

    @property
    def progress(self) -> float:
        """Position in the learning-rate schedule, 0 at the start, 1 at total_updates."""
        return self.updates / self.spec.total_updates

    def current_lr(self) -> float:
        return learning_rate(replace(self.ppo, lr=self.hparams["lr"]), self.progress)

    # -------------------------------------------------------------- update
    def update(self, fragments: Fragment | Sequence[Fragment]) -> dict[str, float]:
        """One PPO update over the fragments (joined along environments); returns statistics."""
        t0 = time.perf_counter()
        given = [fragments] if isinstance(fragments, Fragment) else list(fragments)
        cfg = replace(self.ppo, ent_coef=self.hparams["ent_coef"])
        lr = self.current_lr()
        sizes = sorted({f.num_p for f in given})
        frags = [concat_fragments([f for f in given if f.num_p == p]) for p in sizes]  # one per team size
        # each with its pursuer count (a centralised critic reads the global state by it), the task's if unknown
        batch = [(f.num_p or self.spec.num_p, f.batch(cfg.gamma, cfg.gae_lambda)) for f in frags]
        stats = ppo_update(
            self.model, self.optimizer, batch, cfg, self.spec.num_e, self.spec.num_p, self.generator, lr=lr
        )
        self.updates += 1
        out = {f"train/{k}": v for k, v in stats.items()}
        out.update(fragment_stats(frags))
        if len(sizes) > 1 or sizes[0] not in (0, self.spec.num_p):  # sizes drawn: the mean pursuers per sample
            out["train/team_size"] = sum(f.num_p * f.samples for f in frags) / max(out["train/samples"], 1.0)
        out["train/lr"] = lr
        log_std = getattr(self.model, "log_std", None)  # the exploration noise, for models that have one
        if log_std is not None:
            out["train/log_std"] = float(log_std.detach().cpu().mean())
        out["perf/update_s"] = time.perf_counter() - t0
        return out

    # --------------------------------------------------------------- state
    def get_state(self) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """(tensors, JSON document): parameters, optimiser, RNG, schedule position, hparams."""
        tensors = {f"model/{k}": v for k, v in self.get_weights().items()}
        tensors["rng/update"] = self.generator.get_state()
        optim = self.optimizer.state_dict()
        scalars: dict[str, dict[str, Any]] = {}
        for idx, slots in optim["state"].items():
            for name, value in slots.items():
                if torch.is_tensor(value):
                    tensors[f"optim/{idx}/{name}"] = value.detach().cpu()
                else:
                    scalars.setdefault(str(idx), {})[name] = value
        doc = {
            "format": STATE_FORMAT,
            "updates": self.updates,
            "hparams": dict(self.hparams),
            "optimizer": {"param_groups": optim["param_groups"], "scalars": scalars},
            "architecture": self.spec.model_architecture(),
            "seed": self.spec.seed,
        }
        return tensors, doc

    def set_state(self, tensors: Mapping[str, torch.Tensor], doc: Mapping[str, Any]) -> None:
        """Restore what :meth:`get_state` returned (the model's architecture must match)."""
        if doc.get("format") != STATE_FORMAT:
            raise ValueError(f"learner state format {doc.get('format')!r}, expected {STATE_FORMAT}")
        if doc["architecture"] != self.spec.model_architecture():
            raise ValueError(f"learner state of architecture {doc['architecture']} != {self.spec.model_architecture()}")
        self.set_weights({k[len("model/") :]: v for k, v in tensors.items() if k.startswith("model/")})
        self.generator.set_state(tensors["rng/update"])
        state: dict[int, dict[str, Any]] = {}
        for key, value in tensors.items():
            if key.startswith("optim/"):
                _, idx, name = key.split("/", 2)
                state.setdefault(int(idx), {})[name] = value.to(self.device)
        for idx, slots in doc["optimizer"]["scalars"].items():
            state.setdefault(int(idx), {}).update(slots)
        ordered = dict(sorted(state.items()))  # parameter order, as the optimiser saved it
        self.optimizer.load_state_dict({"state": ordered, "param_groups": doc["optimizer"]["param_groups"]})
        self.updates = int(doc["updates"])
        self.hparams = {k: float(v) for k, v in doc["hparams"].items()}

    def save(self, path: str | Path, extra: Mapping[str, Any] | None = None) -> Path:
        """Write the state (plus ``extra`` JSON, e.g. a trainer's counters) atomically to ``path``."""
        tensors, doc = self.get_state()
        return save_tensors(path, tensors, {**doc, "extra": dict(extra or {})})

    def load(self, path: str | Path) -> dict[str, Any]:
        """Restore the state saved at ``path``; returns the ``extra`` JSON saved with it."""
        tensors, doc = load_tensors(path)
        self.set_state(tensors, doc)
        return dict(doc.get("extra", {}))
