"""The architectures table: every network a checkpoint can name, behind one small protocol.

A checkpoint header's ``architecture`` entry is ``{"class": name, **config}``;
:func:`build_model` looks ``name`` up in :data:`ARCHITECTURES` and builds the network
from the config. The checkpoint loader, the policy adapter
(:class:`atdrone.policies.neural.NeuralPolicy`) and the rollout worker use a network
only through :class:`PolicyModel`, so a new network plugs in by adding a row to the
table: an ``nn.Module`` class with the protocol's methods.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import Any, Protocol, Self, runtime_checkable

import torch
from torch import nn

from atdrone.errors import UserError
from atdrone.models.history import DroneMemory
from atdrone.models.networks import ActorCritic
from atdrone.models.teammate import TeammateActorCritic


class CheckpointError(UserError, ValueError):
    """A checkpoint file is corrupted, truncated or does not fit what it is loaded for."""


@runtime_checkable
class PolicyModel(Protocol):
    """What the rest of atdrone asks of a network: an ``nn.Module`` with these methods.

    Inputs are what the model's :meth:`memory` makes of the raw observations;
    ``num_e`` (evaders) and ``num_p`` (pursuers) give the task shape, which the
    observation layout needs to split entities. The last block is ``nn.Module``'s own.
    """

    @classmethod
    def from_architecture(cls, config: Mapping[str, Any]) -> PolicyModel:
        """The network described by a header's architecture entry, without its "class"."""
        ...

    @property
    def centralised(self) -> bool:
        """Whether :meth:`value` needs the global state (a MAPPO critic)."""
        ...

    def architecture(self) -> dict[str, Any]:
        """The checkpoint header's entry: ``{"class": name, **config}``, JSON only."""
        ...

    def memory(self, num_envs: int, num_keys: int, obs_dim: int) -> DroneMemory:
        """Per-drone memory keyed by (env, key) that makes this network's inputs; grows on demand."""
        ...

    def dist(self, inputs: torch.Tensor, num_e: int) -> torch.distributions.Normal:
        """Gaussian over the pre-squash action u (action = tanh(u)), shape inputs.shape[:-1]."""
        ...

    def value(
        self, inputs: torch.Tensor, num_e: int, state: torch.Tensor | None = None, num_p: int = 0
    ) -> torch.Tensor:
        """State values, shape inputs.shape[:-1]; ``state`` is the global state of a centralised critic."""
        ...

    def parameter_groups(self) -> tuple[list[nn.Parameter], list[nn.Parameter]]:
        """(actor parameters, critic parameters)."""
        ...

    def widen_from(self, other: PolicyModel) -> None:
        """Start from a narrower network's weights so that actions start unchanged; ValueError if impossible."""
        ...

    def state_dict(self, *args: Any, **kwargs: Any) -> dict[str, Any]: ...

    def load_state_dict(self, state_dict: Mapping[str, Any], strict: bool = True, assign: bool = False) -> Any: ...

    def parameters(self, recurse: bool = True) -> Iterator[nn.Parameter]: ...

    def to(self, *args: Any, **kwargs: Any) -> Self: ...

    def train(self, mode: bool = True) -> Self: ...

    def eval(self) -> Self: ...


ARCHITECTURES: dict[str, type[PolicyModel]] = {"ActorCritic": ActorCritic, "TeammateActorCritic": TeammateActorCritic}

# the most parameters a network may have (about 400 MB of float32 weights): the paper's
# ActorCritic has 85,123, the widest that NetConfig's limits allow 69,679,107
MAX_PARAMETERS = 100_000_000


def _construct(architecture: Mapping[str, Any]) -> PolicyModel:
    """The network of ``architecture`` built on the current device; CheckpointError when it cannot be."""
    config = dict(architecture)
    name = config.pop("class", None)
    cls = ARCHITECTURES.get(name) if isinstance(name, str) else None
    if cls is None:
        raise CheckpointError(f"unknown architecture class {name!r}; known: {', '.join(sorted(ARCHITECTURES))}")
    if not issubclass(cls, nn.Module):
        raise CheckpointError(f"architecture {name!r} is not a torch nn.Module")
    try:
        return cls.from_architecture(config)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise CheckpointError(f"architecture {dict(architecture)!r} cannot be built: {exc}") from None


def skeleton(architecture: Mapping[str, Any]) -> PolicyModel:
    """The network of ``architecture`` on torch's meta device: shapes without memory.

    CheckpointError when it names no known network, its config is refused, or it has
    more than :data:`MAX_PARAMETERS` parameters, so a header cannot make a loader
    allocate a huge network.
    """
    with torch.device("meta"):
        model = _construct(architecture)
    count = sum(p.numel() for p in model.parameters())
    if count > MAX_PARAMETERS:
        raise CheckpointError(f"architecture {dict(architecture)!r} has {count:,} parameters, over {MAX_PARAMETERS:,}")
    return model


def build_model(architecture: Mapping[str, Any]) -> PolicyModel:
    """A fresh network of the header entry ``architecture``; CheckpointError when it names no known one
    or is too big (checked on the meta device first, :func:`skeleton`)."""
    skeleton(architecture)
    return _construct(architecture)
