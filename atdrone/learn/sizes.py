"""Team sizes drawn in training: one rollout worker per size, each rollout drawing the size it is played at.

A training protocol's ``"sizes": [lo, hi]`` asks for teams of lo .. hi pursuers: the task's
shipped variants ``<P>p<E>e<O>o`` (configs/tasks/; the same evaders, obstacles and rules,
each size with its own spawn layout). A :class:`MixedSizeWorker` holds one
:class:`~atdrone.learn.rollout.RolloutWorker` per size, whose environments keep their
episodes between the rollouts played at that size, and draws the size of every rollout
uniformly from its own seeded generator, so a replayed job draws the same sizes. The
entity networks pool teammates, so one network acts in every size; the PPO update takes
each size's samples in minibatches of their own (:func:`~atdrone.learn.ppo.ppo_update`).

With partners, the learner keeps its slots and partners fill the others: a team of P
pursuers has P - num_ctrl partner slots, each drawn from the training's distribution
(uniform, weighted, a variable count: per slot, so at any count), and every size gets
partner policies of its own (they keep per-drone memory), which act in a team of any size
(they read the evader count off the arena). A distribution of whole partner profiles
(HOLA-Drone V2's worst-case profiles) fills another slot count with the drawn profile's
own members (:meth:`~atdrone.teams.partners.Profiles.resized`: a random subset of them in
fewer slots, extra slots drawn from them in more). A teammate model's decoder predicts
the teammates its encoder reads (:meth:`~atdrone.models.teammate.TeammateActorCritic.decoder_loss`).
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import torch

from atdrone.config import CONFIG_DIR, ConfigError, TaskConfig, load_task
from atdrone.envs.events import EventPlan
from atdrone.learn.ppo import PPOConfig
from atdrone.learn.rollout import Fragment, RolloutWorker
from atdrone.policies.base import Policy
from atdrone.teams.partners import PartnerDistribution, Profiles, as_sampler

PartnerSource = Callable[[TaskConfig], Sequence[Policy | None]]  # fresh partner policies for a team size

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


def check_sizes(sizes: tuple[int, int] | None, task: TaskConfig, path: str) -> None:
    """ConfigError at ``path``.sizes when a protocol's sizes cannot be trained: a task variant is missing."""
    if sizes is not None:
        size_tasks(task, sizes, f"{path}.sizes")


def size_seed(seed: int, pursuers: int) -> int:
    """The seed of a :class:`MixedSizeWorker`'s worker for teams of ``pursuers``."""
    return int(np.random.SeedSequence([seed, pursuers]).generate_state(1)[0] >> 1)


class MixedSizeWorker:
    """One rollout worker per team size, the size of every rollout drawn (see the module docstring).

    The arguments are :class:`~atdrone.learn.rollout.RolloutWorker`'s, but ``partners`` makes
    each size's partner policies and ``distribution`` draws them (None: uniform per slot);
    ``num_ctrl`` (the learner's slots) applies with partners, self-play fills every slot;
    ``split`` is capped at each size's learner slots. The workers share one action-noise
    generator (:attr:`generator`, which a service worker reseeds per fragment).
    """

    def __init__(
        self,
        tasks: Sequence[TaskConfig],
        seed: int,
        architecture: dict[str, Any],
        ppo: PPOConfig,
        partners: PartnerSource | None = None,
        num_ctrl: int | None = None,
        distribution: PartnerDistribution | None = None,
        num_envs: int | None = None,
        events: EventPlan | None = None,
        split: tuple[int, int] | None = None,
    ) -> None:
        self.workers: dict[int, RolloutWorker] = {}
        for task in tasks:
            p = task.players.num_p
            team = list(partners(task)) if partners is not None else []
            ctrl = (task.players.num_ctrl if num_ctrl is None else num_ctrl) if team else p
            if team and ctrl >= p:
                raise ConfigError("protocol.sizes", f"a team of {p} leaves no partner slot beside {ctrl} learners")
            capped = None if split is None else (min(split[0], ctrl), min(split[1], ctrl))
            sampler = None
            if team and isinstance(distribution, Profiles):
                sampler = distribution.resized(p - ctrl)
            elif team and distribution is not None:
                sampler = as_sampler(distribution, p - ctrl)
            self.workers[p] = RolloutWorker(
                task,
                size_seed(seed, p),
                architecture,
                ppo,
                partners=team,
                num_ctrl=ctrl if team else None,
                sampler=sampler,
                num_envs=num_envs,
                events=events,
                split=capped,
            )
        self.generator = torch.Generator().manual_seed(seed + 2)
        for worker in self.workers.values():
            worker.generator = self.generator
        self.rng = np.random.default_rng([seed, 17])

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
        return self.workers[p].collect(steps)


def make_worker(
    task: TaskConfig,
    seed: int,
    architecture: dict[str, Any],
    ppo: PPOConfig,
    sizes: tuple[int, int] | None = None,
    partners: PartnerSource | None = None,
    num_ctrl: int | None = None,
    distribution: PartnerDistribution | None = None,
    **kwargs: Any,
) -> RolloutWorker | MixedSizeWorker:
    """A rollout worker of ``task`` (``partners(task)`` its partner policies, drawn from ``distribution``), or with
    ``sizes`` a :class:`MixedSizeWorker` over the task's variants; ``kwargs`` among num_envs, events and split."""
    if sizes is not None:
        tasks = size_tasks(task, sizes)
        return MixedSizeWorker(tasks, seed, architecture, ppo, partners, num_ctrl, distribution, **kwargs)
    team = list(partners(task)) if partners is not None else []
    sampler = as_sampler(distribution, task.players.num_p - num_ctrl) if distribution and num_ctrl else None
    return RolloutWorker(task, seed, architecture, ppo, partners=team, num_ctrl=num_ctrl, sampler=sampler, **kwargs)
