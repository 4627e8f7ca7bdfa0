"""Team sizes drawn in training: one rollout worker per size, each rollout drawing the size it is played at.

A training protocol's ``"sizes": [lo, hi]`` asks for teams of lo .. hi pursuers: the task's
shipped variants ``<P>p<E>e<O>o`` (configs/tasks/; the same evaders, obstacles and rules,
each size with its own spawn layout). A :class:`MixedSizeWorker` holds one
:class:`~atdrone.learn.rollout.RolloutWorker` per size, whose environments keep their
episodes between the rollouts played at that size, and draws the size of every rollout
uniformly from its own seeded generator, so a replayed job draws the same sizes. The
entity networks pool teammates, so one network acts in every size; the PPO update takes
each size's samples in minibatches of their own (:func:`~atdrone.learn.ppo.ppo_update`).

Self-play only: partner policies are built for one team size, so a protocol with sizes is
refused where training has partners (:func:`check_sizes`).
"""

from __future__ import annotations

import re
from collections import Counter
from typing import Any

import numpy as np
import torch

from atdrone.config import CONFIG_DIR, ConfigError, TaskConfig, load_task
from atdrone.envs.events import EventPlan
from atdrone.learn.ppo import PPOConfig
from atdrone.learn.rollout import Fragment, RolloutWorker

_NAME = re.compile(r"^(\d+)p(\d+e\d+o)$")


def size_tasks(task: TaskConfig, sizes: tuple[int, int], path: str = "protocol.sizes") -> list[TaskConfig]:
    """The variants of ``task`` with lo .. hi pursuers (configs/tasks/<P>p<E>e<O>o.json), smallest first;
    ConfigError at ``path`` when ``task`` is not a shipped size family or a variant is missing."""
    match = _NAME.match(task.name)
    if match is None:
        raise ConfigError(path, f"task {task.name!r} is not named <P>p<E>e<O>o, so it has no size variants")
    out = []
    for p in range(sizes[0], sizes[1] + 1):
        name = f"{p}p{match.group(2)}"
        file = CONFIG_DIR / "tasks" / f"{name}.json"
        if p == task.players.num_p:
            out.append(task)
        elif file.is_file():
            out.append(load_task(file))
        else:
            known = sorted(f.stem for f in (CONFIG_DIR / "tasks").glob(f"*p{match.group(2)}.json"))
            raise ConfigError(path, f"no task variant {name} (configs/tasks/ has {', '.join(known)})")
    return out


def check_sizes(sizes: tuple[int, int] | None, task: TaskConfig, with_partners: bool, path: str) -> None:
    """ConfigError at ``path`` when a protocol's sizes cannot be trained: partners in the team, or a missing
    task variant."""
    if sizes is None:
        return
    if with_partners:
        raise ConfigError(
            f"{path}.sizes", "team sizes are drawn in self-play training only (partners are built for one size)"
        )
    size_tasks(task, sizes, f"{path}.sizes")


def size_seed(seed: int, pursuers: int) -> int:
    """The seed of a :class:`MixedSizeWorker`'s worker for teams of ``pursuers``."""
    return int(np.random.SeedSequence([seed, pursuers]).generate_state(1)[0] >> 1)


class MixedSizeWorker:
    """One rollout worker per team size, the size of every rollout drawn (see the module docstring).

    The arguments are :class:`~atdrone.learn.rollout.RolloutWorker`'s for self-play; ``split``
    is capped at each size's pursuers. The workers share one action-noise generator
    (:attr:`generator`, which a service worker reseeds per fragment).
    """

    def __init__(
        self,
        tasks: list[TaskConfig],
        seed: int,
        architecture: dict[str, Any],
        ppo: PPOConfig,
        num_envs: int | None = None,
        events: EventPlan | None = None,
        split: tuple[int, int] | None = None,
    ) -> None:
        self.workers: dict[int, RolloutWorker] = {}
        for task in tasks:
            p = task.players.num_p
            capped = None if split is None else (min(split[0], p), min(split[1], p))
            self.workers[p] = RolloutWorker(
                task, size_seed(seed, p), architecture, ppo, num_envs=num_envs, events=events, split=capped
            )
        self.generator = torch.Generator().manual_seed(seed + 2)
        for worker in self.workers.values():
            worker.generator = self.generator
        self.rng = np.random.default_rng([seed, 17])
        self.played: Counter[int] = Counter()  # rollouts played at each size

    @property
    def drawn(self) -> Counter[str]:
        """Partner profiles drawn for the episodes started so far, over every size."""
        out: Counter[str] = Counter()
        for worker in self.workers.values():
            out.update(worker.drawn)
        return out

    def set_weights(self, state_dict: dict[str, torch.Tensor]) -> None:
        for worker in self.workers.values():
            worker.set_weights(state_dict)

    def collect(self, steps: int) -> Fragment:
        """A fragment of ``steps`` steps at a size drawn uniformly (its :attr:`Fragment.num_p`)."""
        sizes = sorted(self.workers)
        p = sizes[int(self.rng.integers(len(sizes)))]
        self.played[p] += 1
        return self.workers[p].collect(steps)


def make_worker(
    task: TaskConfig,
    seed: int,
    architecture: dict[str, Any],
    ppo: PPOConfig,
    sizes: tuple[int, int] | None = None,
    **kwargs: Any,
) -> RolloutWorker | MixedSizeWorker:
    """A rollout worker, or with ``sizes`` a :class:`MixedSizeWorker` over the task's variants (self-play: no
    partners, ``kwargs`` among num_envs, events and split)."""
    if sizes is None:
        return RolloutWorker(task, seed, architecture, ppo, **kwargs)
    if kwargs.get("partners") or kwargs.get("sampler") is not None:
        raise ConfigError("protocol.sizes", "team sizes are drawn in self-play training only")
    kwargs = {k: v for k, v in kwargs.items() if k in ("num_envs", "events", "split")}
    return MixedSizeWorker(size_tasks(task, sizes), seed, architecture, ppo, **kwargs)
