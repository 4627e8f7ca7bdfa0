"""The coordinator actor: the oracle the population algorithms call, and the run's rollout workers.

The algorithm (a class of :data:`atdrone.population.ALGORITHMS`) decides what a
generation does; the coordinator does it (:class:`atdrone.population.base.Oracle`):

- ``evaluate(teams)``: play each team on the rollout workers and record the matches;
- ``train(start_from, partners, hparams)``: a learner (an idle learner actor of this
  coordinator's, reset to the new spec, else a new one) from a member's weights, updated
  ``updates_per_generation`` times on fragments the workers collect with partners drawn
  from ``partners`` per environment and per episode;
- ``register(trained, parents)``: the learner's checkpoint and registry row (the learner
  actor goes back to the pool);
- ``retire(members)``.

Every random draw of generation g comes from seeds derived from (experiment seed, g,
index): learner initialisation and update order, each worker's environments and
partner draws, evaluation seeds, and ``rng``, the generation's generator handed to the
algorithm. The saved state (:meth:`Coordinator.state`: the generation index and the
algorithm's JSON state) therefore fixes everything a resumed generation draws, and a
run killed mid-generation and resumed ends exactly as an uninterrupted one.
"""

from __future__ import annotations

import os
import time
from collections import Counter
from collections.abc import Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import ray
from ray.util.placement_group import PlacementGroup, placement_group, placement_group_table, remove_placement_group
from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

from atdrone.config import TaskConfig, load_task
from atdrone.learn.learner import LearnerSpec
from atdrone.learn.ppo import ppo_config
from atdrone.models.checkpoint import load_checkpoint
from atdrone.policies.manifest import task_version
from atdrone.policies.zoo import MemberSpec, load_zoo
from atdrone.population.base import Algorithm, GenerationReport, MatchResult, Team, Trained
from atdrone.registry import member_id
from atdrone.registry_ray import find_registry_actor
from atdrone.service.actors import (
    ANSWER_TIMEOUT_S,
    LearnerActor,
    RolloutJob,
    RolloutWorkerActor,
    answers,
    run_updates,
)
from atdrone.service.experiment import ExperimentConfig, registry_name
from atdrone.teams.partners import LEARNER_COPY, PartnerDistribution, describe
from atdrone.teams.protocols import load_protocol, zoo_of

# streams of derive_seed(experiment seed, generation, STREAM, index)
LEARNER_STREAM, EVAL_STREAM, RNG_STREAM = 0, 1, 2


def derive_seed(*parts: int) -> int:
    """A reproducible 31-bit seed from integers (numpy's SeedSequence)."""
    return int(np.random.SeedSequence([int(p) for p in parts]).generate_state(1)[0] % 2**31)


def match_batches(teams: Sequence[Team], workers: int) -> list[list[int]]:
    """The teams' indices in batches to play at once: the teams of one learner (``team[0]``), dealt round the
    ``workers``; a team named again in the same call goes to a later batch (each batch's matches are
    distinct, as the registry keys a match by its team and seeds)."""
    if workers < 1:
        raise ValueError(f"need at least one worker, got {workers}")
    groups: dict[tuple[str, int], list[int]] = {}
    seen: dict[tuple[str, ...], int] = {}
    for i, team in enumerate(teams):
        k = seen.get(tuple(team), 0)
        seen[tuple(team)] = k + 1
        groups.setdefault((team[0], k), []).append(i)
    return [idx[j::workers] for idx in groups.values() for j in range(min(workers, len(idx)))]


def reserve_cpus(num_workers: int) -> PlacementGroup:
    """One CPU for each of a run's rollout workers, as a placement group (packed onto as few nodes as hold it):
    held for the run by whoever made it, freed with ``remove_placement_group``."""
    return placement_group([{"CPU": 1.0}] * num_workers, strategy="PACK")


@ray.remote(num_cpus=0, max_restarts=0)
class Coordinator:
    """Owns the rollout workers and learners of one experiment run; runs its algorithm's generations.

    Made with a run's arguments it starts that run; made with none it waits for :meth:`start`. One
    coordinator serves one run after another (:mod:`atdrone.service.pool`): :meth:`release` ends a
    run (its CPUs freed when it reserved them), :meth:`start` sets up the next as a new coordinator
    would; the learners and rollout workers it made are kept, emptied, for the next run.
    """

    def __init__(self, *run: Any) -> None:
        self.workers: list[Any] = []
        self.cpus: PlacementGroup | None = None  # the run's CPUs, one bundle per rollout worker
        self._own_cpus = False  # made by this coordinator (freed at release), else by the caller
        self._idle_workers: list[tuple[Any, TaskConfig, str]] = []  # (worker, its task, its node) between runs
        self._pids: dict[Any, int] = {}  # the run's workers' pids when it began, by worker
        self._own_learners: list[Any] = []  # the learner actors this coordinator made (kept between runs)
        self._own_gpus = 0.0
        self._idle_learners: list[Any] = []
        if run:
            self.start(*run)

    def start(
        self,
        cfg: ExperimentConfig,
        algorithm: type[Algorithm],
        run_dir: str,
        state: Mapping[str, Any] | None = None,
        registry: Any = None,
        cpus: PlacementGroup | None = None,
    ) -> None:
        """Set up a run: what a new coordinator made with these arguments would hold (the learners and rollout
        workers it made for earlier runs are reused: emptied, they hold what new ones would).

        ``cpus``: the run's CPUs (:func:`reserve_cpus`), reserved and later freed by the caller (the driver:
        freed even when this coordinator dies); without, the coordinator reserves them and frees them at
        :meth:`release`."""
        if self.workers:
            raise RuntimeError("the coordinator is running a run: release it first")
        self.cfg = cfg
        self.run = cfg.name
        self.run_dir = Path(run_dir)
        self.task = load_task(cfg.task)
        self.ppo = ppo_config(cfg.ppo, cfg.preset)
        # the run's registry actor: passed in (the handle keeps it alive) or found by name
        self.registry = registry if registry is not None else find_registry_actor(registry_name(cfg.name))
        self.num_p = self.task.players.num_p
        self.num_ctrl = self.task.players.num_ctrl
        self.num_partners = self.num_p - self.num_ctrl
        self.updates_per_generation = cfg.updates_per_generation
        self.protocol = load_protocol(cfg.protocol) if cfg.protocol else None  # drawn in every rollout episode
        self.algorithm = algorithm(algorithm.parse_config(cfg.section, cfg.algorithm), cfg.seed)
        self.architecture = self.algorithm.architecture(self.ppo, self.task)  # the learners' network
        state = dict(state or {})
        self.generation: int = state.get("generation", 0)
        # the run's totals so far: training env steps and learner samples, evaluation env steps
        self.budget: dict[str, int] = {"env_steps": 0, "learner_samples": 0, "eval_env_steps": 0}
        self.budget.update(state.get("budget", {}))
        if "algorithm" in state:
            self.algorithm.load_state(state["algorithm"])
        self.zoo_specs: dict[str, MemberSpec] = {}
        if self._own_gpus != cfg.learner_gpus:  # learners asking other GPUs than this run's
            for learner in self._own_learners:
                ray.kill(learner)
            self._own_learners, self._own_gpus = [], cfg.learner_gpus
        self._own_learners = [learner for learner in self._own_learners if answers(learner.ping)]
        # learner actors between trainings (one process, many learners), made when first needed
        self._idle_learners = list(self._own_learners)
        self._reserve(cfg.num_workers, cpus)  # last: a run refused above starts no worker
        self._begin(self.generation)

    def _reserve(self, num_workers: int, cpus: PlacementGroup | None) -> None:
        """The run's rollout workers: one CPU each reserved (``cpus`` or a placement group of its own, waited for
        as Ray waits to place an actor), each worker on its bundle's node: one kept from an earlier run on that
        node and task, else a new one."""
        self._own_cpus = cpus is None
        self.cpus = reserve_cpus(num_workers) if cpus is None else cpus
        try:
            while not self.cpus.wait(timeout_seconds=60):
                pass
            nodes = placement_group_table(self.cpus)["bundles_to_node_id"]
            idle, self._idle_workers = self._idle_workers, []
            for i in range(num_workers):
                kept = next((k for k in idle if k[1] == self.task and k[2] == nodes[i]), None)
                if kept is not None:
                    idle.remove(kept)
                    self.workers.append(kept[0])
                else:
                    where = NodeAffinitySchedulingStrategy(nodes[i], soft=True)
                    self.workers.append(RolloutWorkerActor.options(scheduling_strategy=where).remote(self.task))
            for worker, _, _ in idle:  # not needed by this run: not kept either
                ray.kill(worker, no_restart=True)
            self._pids = dict(zip(self.workers, ray.get([w.pid.remote() for w in self.workers]), strict=True))
        except BaseException:
            self._end_workers()
            raise

    def _end_workers(self) -> None:
        """The run's rollout workers: each one that was never restarted kept (emptied) for the next run, the
        others ended; the run's CPUs freed."""
        for worker in self.workers:
            try:
                pid, node = ray.get(worker.release.remote(), timeout=ANSWER_TIMEOUT_S)
            except ray.exceptions.RayError:
                pid, node = -1, ""
            if pid == self._pids.get(worker):
                self._idle_workers.append((worker, self.task, node))
            else:  # restarted in the run (its restart budget spent in part), gone, or never up
                ray.kill(worker, no_restart=True)
        self.workers, self._pids = [], {}
        if self.cpus is not None and self._own_cpus:
            remove_placement_group(self.cpus)
        self.cpus = None

    def release(self) -> None:
        """End the run: its rollout workers emptied and kept (their CPUs freed), its learners emptied and kept for
        the next :meth:`start`, its registry handle dropped."""
        self._end_workers()
        # their models and optimisers freed; one that died is dropped
        self._own_learners = [learner for learner in self._own_learners if answers(learner.release)]
        self._idle_learners = []
        self.registry = None

    def ping(self) -> bool:
        """True: the actor answers."""
        return True

    def kept(self) -> dict[str, list[Any]]:
        """The actors this coordinator keeps between runs: its learners, and its idle rollout workers."""
        return {"learners": list(self._own_learners), "workers": [w for w, _, _ in self._idle_workers]}

    def _new_learner(self) -> Any:
        learner = LearnerActor.options(num_gpus=self.cfg.learner_gpus).remote()
        self._own_learners.append(learner)
        return learner

    def _begin(self, generation: int) -> None:
        """Counters and the generator of a generation, all derived from (seed, generation)."""
        self._progress = ""
        self.new_members: list[str] = []  # registered in this generation, in order
        self.rng = np.random.default_rng(derive_seed(self.cfg.seed, generation, RNG_STREAM))
        self.trained = 0
        self.registered = 0
        self.evaluated = 0

    # ---------------------------------------------------------------- state
    def state(self) -> dict[str, Any]:
        """Everything needed to continue after the last completed generation (JSON)."""
        return {
            "generation": self.generation,
            "seed": self.cfg.seed,
            "budget": dict(self.budget),
            "algorithm": self.algorithm.state(),
        }

    def progress(self) -> str:
        """What the running generation is doing ("train: learner 1, update 5/12"); answered from a second thread."""
        return self._progress

    def population(self) -> list[str]:
        return list(self.algorithm.population)

    def worker_pids(self) -> list[int]:
        return ray.get([w.pid.remote() for w in self.workers])

    def pid(self) -> int:
        return os.getpid()

    def learner_pids(self) -> list[int]:
        """The process ids of this coordinator's learner actors (for tests that kill them)."""
        return ray.get([learner.pid.remote() for learner in self._own_learners])

    def workers_handles(self) -> list[Any]:
        return list(self.workers)

    # ----------------------------------------------------------- generation
    def run_generation(self) -> GenerationReport:
        """One generation of the algorithm; returns its report."""
        t0 = time.perf_counter()
        self._begin(self.generation)
        ray.get(self.registry.start_generation.remote(self.run, self.generation, {"algorithm": self.cfg.algorithm}))
        report = self.algorithm.generation(self)
        fresh = [m for m in self.new_members if m in report.population]
        if self.cfg.final_zoo and fresh:  # the parent run's curves: the generation's new members on the zoo
            self.evaluate_population(self.cfg.final_zoo, self.cfg.eval_episodes, members=fresh)
        report.budget = dict(self.budget)
        report.wall_s = time.perf_counter() - t0
        ray.get(
            self.registry.finish_generation.remote(
                self.run, self.generation, {"population": report.population, "learners": report.learners}
            )
        )
        self.generation += 1
        return report

    # --------------------------------------------------------------- oracle
    def member_spec(self, member: str) -> MemberSpec:
        """How a worker builds a member's policy: a zoo member (``zoo1:greedy``) or a population checkpoint."""
        if member in self.zoo_specs:
            return self.zoo_specs[member]
        if member == LEARNER_COPY:
            return MemberSpec(name=member, kind="learner")
        return MemberSpec(name=member, kind="checkpoint", checkpoint=str(self.checkpoint_path(member)))

    def checkpoint_path(self, member: str) -> Path:
        return (self.run_dir / "members" / f"{member}.pt").resolve()

    def zoo_members(self, zoo: str) -> list[str]:
        loaded = load_zoo(zoo, self.task)
        ids = []
        for spec in loaded.spec.members:
            ident = f"{loaded.name}:{spec.name}"
            self.zoo_specs[ident] = replace(spec, name=ident)
            ids.append(ident)
        return ids

    def train(
        self,
        start_from: str | None,
        partners: PartnerDistribution | None,
        hparams: Mapping[str, float] | None = None,
        updates: int | None = None,
    ) -> Trained:
        updates = self.cfg.updates_per_generation if updates is None else updates
        if updates < 1:
            raise ValueError(f"updates must be >= 1, got {updates}")
        index, self.trained = self.trained, self.trained + 1
        seed = derive_seed(self.cfg.seed, self.generation, LEARNER_STREAM, index)
        spec = LearnerSpec(
            ppo=self.ppo,
            num_e=self.task.players.num_e,
            num_p=self.num_p,
            seed=seed,
            total_updates=updates,
            architecture=self.architecture,
        )
        learner = self._idle_learners.pop() if self._idle_learners else self._new_learner()
        ray.get(learner.reset.remote(spec, self.cfg.learner_threads))
        if start_from is not None:
            model, _ = load_checkpoint(self.checkpoint_path(start_from))
            ray.get(learner.set_weights.remote(model.state_dict()))
        if hparams:
            ray.get(learner.set_hparams.remote(**hparams))
        num_ctrl = self.num_p if partners is None else self.num_ctrl
        specs = tuple(self.member_spec(m) for m in partners.members) if partners is not None else ()
        envs = self.ppo.num_envs // len(self.workers)
        events, split, sizes = None, None, None
        if self.protocol is not None:  # a split asks for at most the slots this training gives its learner
            events, split, sizes = self.protocol.plan, self.protocol.split, self.protocol.sizes
            split = None if split is None else (min(split[0], num_ctrl), min(split[1], num_ctrl))
        jobs = [
            ray.put(
                RolloutJob(
                    derive_seed(seed, i),
                    self.ppo,
                    envs,
                    num_ctrl,
                    self.architecture,
                    specs,
                    partners,
                    events,
                    split,
                    sizes,
                )
            )
            for i in range(len(self.workers))
        ]

        def report(done: int) -> None:
            self._progress = f"train: learner {index + 1}, update {done}/{updates}"

        history, draws = run_updates(learner, self.workers, jobs, updates, self.ppo.rollout_steps, on_update=report)
        env_steps = updates * envs * len(self.workers) * self.ppo.rollout_steps
        samples = int(sum(h["train/samples"] for h in history))
        self.budget["env_steps"] += env_steps
        self.budget["learner_samples"] += samples
        drawn: Counter[str] = Counter()
        for counts in draws:
            drawn.update(counts)
        return Trained(
            start_from=start_from,
            seed=seed,
            history=history,
            drawn=dict(sorted(drawn.items())),
            hparams=ray.get(learner.hparams.remote()),
            partners=describe(partners),
            env_steps=env_steps,
            samples=samples,
            handle=learner,
        )

    def register(self, trained: Trained, parents: Sequence[str], tags: Mapping[str, Any] | None = None) -> str:
        member = member_id(self.cfg.algorithm, self.generation, self.registered)
        tags = {**self.algorithm.member_tags(), "zoo_version": task_version(self.task.name), **dict(tags or {})}
        if self.protocol is not None:  # what its training drew: the protocol's document as it stood
            tags["protocol"] = self.protocol.to_dict()
        self.registered += 1
        self.new_members.append(member)
        last = trained.history[-1] if trained.history else {}
        path = self.checkpoint_path(member)
        header = {
            "name": member,
            "task": self.task.name,
            "num_p": self.num_p,
            "num_e": self.task.players.num_e,
            "algorithm": self.cfg.algorithm,
            "config": self.cfg.to_dict(),
            "seed": trained.seed,
            "step": trained.env_steps,
            "generation": self.generation,
            "parents": list(parents),
            "partners": trained.partners,
            "metrics": {k: v for k, v in last.items() if k.startswith("train/")},
            "tags": tags,
        }
        full = ray.get(trained.handle.save.remote(str(path), header))
        self._idle_learners.append(trained.handle)  # the next training resets it
        ray.get(
            self.registry.add_member.remote(
                run=self.run,
                algorithm=self.cfg.algorithm,
                generation=self.generation,
                task=self.task.name,
                parents=list(parents),
                checkpoint=str(path),
                sha256=full["sha256"],
                metrics=header["metrics"],
                tags=tags,
                member_id=member,
            )
        )
        return member

    def retire(self, members: Sequence[str]) -> None:
        ray.get([self.registry.update_member.remote(m, status="retired") for m in members])

    def evaluate(self, teams: Sequence[Team], episodes: int | Sequence[int] | None = None) -> list[MatchResult]:
        """Play each team (learner id repeated num_ctrl times + partner ids) on the workers; record the matches.

        ``episodes`` per team (one count for all; default eval_episodes). The teams of one learner are
        played in batches, one per worker (:meth:`RolloutWorkerActor.evaluate_lineups`), each with a seed
        of its own from the generation's evaluation stream; every call draws fresh seeds.
        """
        if episodes is None or isinstance(episodes, int):
            counts = [self.cfg.eval_episodes if episodes is None else int(episodes)] * len(teams)
        else:
            counts = [int(n) for n in episodes]
        if len(counts) != len(teams) or any(n < 1 for n in counts):
            raise ValueError(f"need a positive episode count per team, got {counts} for {len(teams)} teams")
        first, self.evaluated = self.evaluated, self.evaluated + len(teams)
        self._progress = f"evaluate: {len(teams)} matches, {sum(counts)} episodes ({first} matches before)"
        batches = match_batches(teams, len(self.workers))
        seeds = [derive_seed(self.cfg.seed, self.generation, EVAL_STREAM, first + b) for b in range(len(batches))]
        calls = []
        for b, (batch, seed) in enumerate(zip(batches, seeds, strict=True)):
            partners = list(dict.fromkeys(p for i in batch for p in teams[i][self.num_ctrl :]))
            lineups = [[partners.index(p) for p in teams[i][self.num_ctrl :]] for i in batch]
            calls.append(
                self.workers[b % len(self.workers)].evaluate_lineups.remote(
                    self.member_spec(teams[batch[0]][0]),
                    [self.member_spec(p) for p in partners],
                    lineups,
                    [counts[i] for i in batch],
                    seed,
                )
            )
        played: dict[int, tuple[int, dict[str, Any]]] = {}
        for batch, seed, out in zip(batches, seeds, ray.get(calls), strict=True):
            played.update({i: (seed, result) for i, result in zip(batch, out, strict=True)})
        results = []
        for i, team in enumerate(teams):
            seed, result = played[i]
            ray.get(
                self.registry.add_match.remote(
                    list(team), self.task.name, self.run, self.generation, [seed], counts[i], result
                )
            )
            self.budget["eval_env_steps"] += int(result["steps"])
            results.append(MatchResult(tuple(team), dict(result), counts[i], seed))
        return results

    # ------------------------------------------------------------ final eval
    def evaluate_population(
        self, zoo_name: str, episodes: int, members: Sequence[str] | None = None
    ) -> dict[str, dict[str, float]]:
        """Every population member (or ``members``) with partners from a zoo, or a protocol's zoo with its team
        events: SUC/COL/AST/REW (and the events' metrics) per member."""
        zoo_base, events = zoo_of(zoo_name)
        zoo = load_zoo(zoo_base, self.task)
        if zoo.missing:
            return {}
        specs = list(zoo.spec.members)
        population = self.population() if members is None else list(members)
        self._progress = f"zoo: {len(population)} member(s) on {zoo_name}, {episodes} episodes each"
        calls = [
            self.workers[i % len(self.workers)].evaluate_zoo.remote(
                self.member_spec(m), specs, episodes, 4242 + i, events
            )
            for i, m in enumerate(population)
        ]
        results = dict(zip(population, ray.get(calls), strict=True))
        ray.get(
            [
                self.registry.update_member.remote(m, metrics={f"{zoo_name}/{k}": v for k, v in res.items()})
                for m, res in results.items()
            ]
        )
        return results
