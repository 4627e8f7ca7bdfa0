"""Matches: learners and zoo partners sharing the pursuer slots of a BatchedPursuit.

For every episode of every environment a :class:`Match` draws which pursuer slots the
learners fill (shuffled) and which partner member fills each remaining slot (drawn
from the zoo, uniformly unless a sampler or a lineup per episode is given), steps the partners itself, and
exposes the learners' slots only: observations (B, num_ctrl, obs_dim) and actions
(B, num_ctrl). ``info["team"]`` records the team of the episodes played in the step:
``learner_slots`` (B, num_ctrl), ``partner_slots`` and ``partner_members``
(B, num_unctrl) and ``partners``, the members' names (B, num_unctrl). ``info["dists"]``
(B, num_p, 2) holds the pre-squash Gaussian (mean, std) of every partner that has one
(a trained drone's ``last_dist``), NaN for rule-based partners and learner slots.

Each episode's team is drawn from a generator seeded by the episode's key (the core's
``state.key``) and the Match's seed, and each drone a policy acts for carries a random
key of its episode, step and slot (``DroneBatch.keys``), so an episode plays the same
whichever row it runs in. :meth:`Match.keep` lets finished rows leave the batch; the
policies keep seeing every remaining drone under its first row number (its seat), so
their per-episode memory needs no moving.

With team events in the core (:mod:`atdrone.envs.events`) the Match tells the core which
slots are the learners' (events hit partner slots by default; in self-play, where the
learners fill every slot, each is the others' partner), and when a swap or join
puts a new drone in a partner slot it draws the member that flies it (another member of
the partner set, from the episode's key) and has every partner policy forget that slot's
drone (:meth:`forget`); :meth:`changed_learners` names the learner drones to forget.

With a ``split`` (lo, hi) each episode draws how many of the learners' ``num_ctrl`` slots
the learner flies, k uniform in lo..hi; the other num_ctrl - k learner columns are lent
to partners for the episode (``lent`` (B, num_ctrl), each flown by a member drawn
uniformly from the partner set): they act as partner slots (partner actions, team
events, swaps), the learner's actions there are not executed, and ``info["team"]["lent"]``
says which, so training leaves them out of the loss.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from atdrone.envs.core import BatchedPursuit
from atdrone.envs.observation import Poses
from atdrone.envs.streams import DRONE_DRAWS, EVENT_DRAWS, fold, unit
from atdrone.policies.base import DroneBatch, Policy
from atdrone.policies.zoo import Zoo

# (rng, n) -> (n, num_unctrl) member indices for n fresh episodes
PartnerSampler = Callable[[np.random.Generator, int], np.ndarray]


class Match:
    """Learners + partners on one batched core (see the module docstring)."""

    def __init__(
        self,
        core: BatchedPursuit,
        partners: Zoo | Sequence[Policy],
        seed: int | None = None,
        num_ctrl: int | None = None,
        shuffle_slots: bool = True,
        sampler: PartnerSampler | None = None,
        seats: Sequence[int] | None = None,
        lineups: np.ndarray | None = None,
        split: tuple[int, int] | None = None,
    ) -> None:
        self.core = core
        self.partners: list[Policy] = (
            partners.resolve(core.cfg.name).policies() if isinstance(partners, Zoo) else list(partners)
        )
        self.partner_names = [p.name for p in self.partners]
        self._names = np.array(self.partner_names, dtype=object)
        self.num_ctrl = core.cfg.players.num_ctrl if num_ctrl is None else num_ctrl
        self.num_unctrl = core.num_p - self.num_ctrl
        if not 0 < self.num_ctrl <= core.num_p:
            raise ValueError(f"num_ctrl must be in 1..{core.num_p}, got {self.num_ctrl}")
        if self.num_unctrl and not self.partners:
            raise ValueError(f"{self.num_unctrl} partner slots but no partner policies")
        if split is not None and not (1 <= split[0] <= split[1] <= self.num_ctrl and self.partners):
            raise ValueError(
                f"split must be (lo, hi) with 1 <= lo <= hi <= {self.num_ctrl} learner slots, and partner policies "
                f"to lend the others to; got {split} with {len(self.partners)} partners"
            )
        self.split = split
        self.shuffle_slots = shuffle_slots and seats is None
        self.sampler = sampler or self._uniform
        self.lineups = None if lineups is None else np.asarray(lineups, dtype=np.intp)
        if self.lineups is not None and (
            self.lineups.ndim != 2
            or self.lineups.shape[1] != self.num_unctrl
            or not len(self.lineups)
            or not ((self.lineups >= 0) & (self.lineups < len(self.partners))).all()
        ):
            raise ValueError(
                f"lineups must be (episodes, {self.num_unctrl}) indices of the {len(self.partners)} partners, "
                f"got shape {None if self.lineups is None else self.lineups.shape}"
            )
        self.seed = int(np.random.SeedSequence(seed).entropy)  # type: ignore[arg-type]  # with an episode key: its team
        B = core.num_envs
        order = np.arange(core.num_p)  # learners first, then partners; ``seats``: the learners' slots, fixed
        if seats is not None:
            if len(seats) != self.num_ctrl or len(set(seats)) != len(seats) or not set(seats) <= set(range(core.num_p)):
                raise ValueError(f"seats must be {self.num_ctrl} distinct slots of 0..{core.num_p - 1}, got {seats}")
            order = np.r_[np.asarray(seats, dtype=np.intp), np.setdiff1d(order, seats)]
        self.slots = np.tile(order, (B, 1))
        self.members = np.zeros((B, self.num_unctrl), dtype=np.intp)
        self.lent = np.zeros((B, self.num_ctrl), dtype=bool)  # learner columns a partner flies this episode
        self.lent_members = np.zeros((B, self.num_ctrl), dtype=np.intp)
        self.seats = np.arange(B)  # the row number the policies know each row by (its first row)
        self.num_seats = B
        self._rows = np.arange(B)[:, None]
        self._obs: np.ndarray | None = None
        self._step_keys: np.ndarray | None = None  # the core's step keys, once per step
        self._seat_poses: Poses | None = None  # seat-sized poses, once rows have left
        self.drawn: Counter[str] = Counter()  # partner profile ("a|b", ids sorted) -> episodes started with it

    def _uniform(self, rng: np.random.Generator, n: int) -> np.ndarray:
        return rng.integers(len(self.partners), size=(n, self.num_unctrl))

    @property
    def learner_slots(self) -> np.ndarray:
        """(B, num_ctrl) pursuer slots of the learners this episode."""
        return self.slots[:, : self.num_ctrl]

    @property
    def partner_slots(self) -> np.ndarray:
        """(B, num_unctrl) pursuer slots of the partners this episode."""
        return self.slots[:, self.num_ctrl :]

    def _assign(self, envs: np.ndarray) -> None:
        """Draw the teams of the episodes starting in rows ``envs``: one generator per episode, from its key."""
        if not len(envs):
            return
        P = self.core.num_p
        rngs = [np.random.Generator(np.random.PCG64([int(k), self.seed])) for k in self.core.state.key[envs]]
        if self.shuffle_slots:
            self.slots[envs] = np.argsort(np.stack([rng.random(P) for rng in rngs]), axis=1)
        if self.num_unctrl and self.lineups is not None:  # episode e plays lineups[e] (past the last: its last)
            drawn = self.lineups[np.minimum(self.core.state.episode[envs], len(self.lineups) - 1)]
            self.members[envs] = drawn
            self._count(drawn)
        elif self.num_unctrl:
            drawn = np.concatenate([self.sampler(rng, 1) for rng in rngs])
            self.members[envs] = drawn
            self._count(drawn)
        if self.split is not None:  # drawn after the team, so an episode's team is the same with or without
            lo, hi = self.split
            flown = np.array([rng.integers(lo, hi + 1) for rng in rngs])
            self.lent[envs] = np.arange(self.num_ctrl)[None] >= flown[:, None]
            self.lent_members[envs] = np.stack([rng.integers(len(self.partners), size=self.num_ctrl) for rng in rngs])
        learner = np.zeros((len(envs), P), dtype=bool)
        np.put_along_axis(learner, self.slots[envs, : self.num_ctrl], ~self.lent[envs], axis=1)
        self.core.bind_events(envs, learner)

    def _count(self, drawn: np.ndarray) -> None:
        """Add the drawn profiles (n, num_unctrl) to ``drawn``: one Python step per distinct profile, not per env."""
        profiles, counts = np.unique(np.sort(drawn, axis=1), axis=0, return_counts=True)
        for profile, n in zip(profiles, counts, strict=True):
            self.drawn["|".join(sorted(self._names[profile]))] += int(n)

    def reset(self, seed: int | None = None, episodes: np.ndarray | None = None) -> np.ndarray:
        """Reset every environment (to ``episodes``, see the core's reset) and draw new teams.

        Returns the learner observations (B, num_ctrl, D).
        """
        if seed is not None:
            self.seed = seed
        self._obs = self.core.reset(seed=seed, episodes=episodes)
        self._step_keys = None
        self._assign(np.arange(self.core.num_envs))
        for policy in self.partners:
            policy.reset(np.ones(self.num_seats, dtype=bool))
        return self.learner_view(self._obs)

    def keep(self, rows: np.ndarray) -> None:
        """Drop every row but ``rows`` from the core and the teams; the policies still know them by seat."""
        rows = np.asarray(rows, dtype=np.intp)
        if self._seat_poses is None:
            s = self.core.state
            self._seat_poses = Poses(s.pos.copy(), s.heading.copy(), s.captured.copy(), self.core.arena)
        self.core.keep(rows)
        self.slots, self.members, self.seats = self.slots[rows], self.members[rows], self.seats[rows]
        self.lent, self.lent_members = self.lent[rows], self.lent_members[rows]
        self._rows = np.arange(len(rows))[:, None]
        if self._obs is not None:
            self._obs = self._obs[rows]
        self._step_keys = None

    def by_seat(self, mask: np.ndarray) -> np.ndarray:
        """A row mask (B,) as a seat mask (num_seats,): what the policies' ``reset`` takes."""
        if self._seat_poses is None:
            return mask
        out = np.zeros(self.num_seats, dtype=bool)
        out[self.seats] = mask
        return out

    def poses(self) -> Poses:
        """The core's poses, with rows at their seats once rows have left (the rows policies index)."""
        poses = self.core.poses()
        full = self._seat_poses
        if full is None:
            return poses
        full.pos[self.seats], full.heading[self.seats], full.captured[self.seats] = (
            poses.pos,
            poses.heading,
            poses.captured,
        )
        return full

    def drones(self, env: np.ndarray, slot: np.ndarray, poses: Poses | None = None) -> DroneBatch:
        """The drones in rows ``env`` and pursuer ``slot`` (M,) as the policies see them: by seat, with their keys."""
        assert self._obs is not None
        if self._step_keys is None:
            self._step_keys = self.core.step_keys()
        keys = fold(self._step_keys[env], DRONE_DRAWS + slot)
        poses = self.poses() if poses is None else poses
        return DroneBatch(obs=self._obs[env, slot], env=self.seats[env], slot=slot, poses=poses, keys=keys)

    def _replace(self, changed: np.ndarray) -> None:
        """New drones in the ``changed`` (B, P) slots: a swapped or joined partner slot (or lent learner slot) gets
        another member of the partner set (drawn from the episode's key, step and slot); every partner policy
        forgets the slot."""
        self._redraw(changed, self.partner_slots, self.members, np.ones_like(self.members, dtype=bool))
        if self.split is not None:
            self._redraw(changed, self.learner_slots, self.lent_members, self.lent)

    def _redraw(self, changed: np.ndarray, slots: np.ndarray, members: np.ndarray, partnered: np.ndarray) -> None:
        """:meth:`_replace` for the columns ``slots`` (B, n) whose ``members`` (B, n) fly where ``partnered``."""
        env, j = np.nonzero(np.take_along_axis(changed, slots, axis=1) & partnered)
        if not len(env):
            return
        slot = slots[env, j]
        n = len(self.partners)
        s = self.core.state
        arriving = s.present[env, slot]  # a swap or a join; a drop leaves the member in its (empty) slot
        u = unit(fold(fold(s.key[env], EVENT_DRAWS + 2), s.t[env] * self.core.num_p + slot))
        other = (members[env, j] + 1 + (u * (n - 1)).astype(np.intp)) % n if n > 1 else members[env, j]
        members[env, j] = np.where(arriving, other, members[env, j])
        self.forget(env, slot)

    def forget(self, env: np.ndarray, slot: np.ndarray) -> None:
        """Every partner policy with per-drone memory forgets the drones in rows ``env`` and slots ``slot`` (M,)."""
        for policy in self.partners:
            forget = getattr(policy, "forget", None)
            if forget is not None:
                forget(self.seats[env], slot)

    def changed_learners(self, changed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The learner drones a team event replaced (``info["team_changed"]`` (B, P)): rows and learner indices
        (M,) each, for the learners' memory to forget."""
        env, k = np.nonzero(np.take_along_axis(changed, self.learner_slots, axis=1))
        return env, k

    def learner_view(self, obs: np.ndarray) -> np.ndarray:
        return obs[self._rows, self.learner_slots]

    def observe(self) -> np.ndarray:
        """The learners' current observations (B, num_ctrl, obs_dim)."""
        if self._obs is None:
            raise RuntimeError("call reset() first")
        return self.learner_view(self._obs)

    def team(self) -> dict[str, np.ndarray]:
        """The teams of the episodes now running (the layout of ``info["team"]``)."""
        team = {
            "learner_slots": self.learner_slots.copy(),
            "partner_slots": self.partner_slots.copy(),
            "partner_members": self.members.copy(),
            "partners": self._names[self.members],
        }
        if self.split is not None:
            team["lent"] = self.lent.copy()
        return team

    def learner_batch(self) -> DroneBatch:
        """The learners' drones as a DroneBatch, env-major (for policies that drive learners)."""
        if self._obs is None:
            raise RuntimeError("call reset() first")
        env = np.repeat(np.arange(self.core.num_envs), self.num_ctrl)
        return self.drones(env, self.learner_slots.reshape(-1))

    def partner_actions(self, actions: np.ndarray, dists: np.ndarray | None = None) -> None:
        """Fill the partner slots of ``actions`` (B, num_p) from the partner policies, and of ``dists``
        (B, num_p, 2) the (mean, std) of those whose policy exposes its last distribution."""
        assert self._obs is not None
        poses = self.poses()
        for m, policy in enumerate(self.partners):
            env, j = np.nonzero(self.members == m)
            slot = self.partner_slots[env, j]
            if self.split is not None:  # and the learner columns lent to this member
                lent_env, c = np.nonzero(self.lent & (self.lent_members == m))
                env, slot = np.r_[env, lent_env], np.r_[slot, self.learner_slots[lent_env, c]]
            if len(env):
                actions[env, slot] = policy.act(self.drones(env, slot, poses))
                last = getattr(policy, "last_dist", None)
                if dists is not None and last is not None:
                    dists[env, slot, 0], dists[env, slot, 1] = last

    def step(self, learner_actions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Step with the learners' actions (B, num_ctrl); partners act themselves.

        Returns learner observations, learner rewards (B, num_ctrl), dones (B,) and the
        core's info, with ``final_obs`` in the learners' view, ``actions`` (B, num_p) as
        executed and ``team``: the teams of the episodes played this step (see :meth:`team`).
        """
        if self._obs is None:
            raise RuntimeError("call reset() before step()")
        learner_actions = np.asarray(learner_actions, dtype=np.float64)
        B = self.core.num_envs
        if learner_actions.shape != (B, self.num_ctrl):
            raise ValueError(f"learner actions must have shape {(B, self.num_ctrl)}, got {learner_actions.shape}")
        actions = np.empty((B, self.core.num_p))
        actions[self._rows, self.learner_slots] = learner_actions
        dists = np.full((B, self.core.num_p, 2), np.nan)
        self.partner_actions(actions, dists)
        obs, rewards, dones, info = self.core.step(actions)
        self._step_keys = None
        info["actions"] = actions  # every slot's turn as executed: learners' and partners'
        info["dists"] = dists
        info["final_obs"] = self.learner_view(info["final_obs"])
        changed = info.get("team_changed")
        if changed is not None and changed.any():
            self._replace(changed)
        info["team"] = self.team()
        if dones.any():
            for policy in self.partners:
                policy.reset(self.by_seat(dones))
            self._assign(np.flatnonzero(dones))
        self._obs = obs
        return self.learner_view(obs), rewards[:, : self.num_ctrl], dones, info
