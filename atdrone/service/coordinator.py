"""The coordinator actor: one generation of any service algorithm reads in one method.

HOLA-Drone V2 (``hola``; ``hola_no_g`` draws partners uniformly)::

    evaluate the missing hyperedges (teams touching last generation's learners, spread
    over the rollout workers) -> preference hypergraph -> eta -> rho over the partners
    -> best-response PPO learners trained against partner profiles drawn from rho
    -> register the learners (population update: drop the lowest-eta member when full)

Generation 0 of HOLA bootstraps the population with a self-play learner. ``sp`` trains
one self-play learner and registers a snapshot per generation; ``br`` does the same
against a fixed zoo; ``pbt`` trains a population of IPPO learners against each other
and then exploits (the worst copies the best) and explores (perturbs learning rate and
entropy coefficient). The coordinator returns a plain report per generation; the driver
logs it to MLflow.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np
import ray

from atdrone.config import load_task
from atdrone.learn.ppo import net_config, ppo_config
from atdrone.policies.zoo import MemberSpec, load_zoo
from atdrone.population import hypergraph as hola
from atdrone.registry import find_registry_actor, new_member_id
from atdrone.service.actors import LearnerActor, RolloutWorkerActor
from atdrone.service.experiment import ExperimentConfig, registry_name


@ray.remote(num_cpus=0, max_restarts=0)
class Coordinator:
    """Owns the rollout workers and learners of one experiment run."""

    def __init__(
        self, cfg: ExperimentConfig, run_dir: str, state: dict[str, Any] | None = None, registry: Any = None
    ) -> None:
        self.cfg = cfg
        self.run = cfg.name
        self.run_dir = Path(run_dir)
        self.task = load_task(cfg.task)
        self.ppo = ppo_config(cfg.ppo, cfg.preset)
        self.net = net_config(self.ppo)
        # the run's registry actor: passed in (the handle keeps it alive) or found by name
        self.registry = registry if registry is not None else find_registry_actor(registry_name(cfg.name))
        self.num_p = self.task.players.num_p
        self.num_ctrl = self.task.players.num_ctrl
        self.num_partners = self.num_p - self.num_ctrl
        self.workers = [
            RolloutWorkerActor.remote(self.task, cfg.envs_per_worker, cfg.seed * 1000 + i, self.net, self.ppo.gamma)
            for i in range(cfg.num_workers)
        ]
        self.zoo = load_zoo(cfg.zoo).spec.members if cfg.zoo else ()
        state = state or {}
        self.generation: int = state.get("generation", 0)
        self.population: list[str] = state.get("population", [])
        self.new_learners: list[str] = state.get("new_learners", [])
        self.eta: dict[str, float] = state.get("eta", {})
        self.hparams: dict[str, dict[str, float]] = state.get("hparams", {})
        self.exploit_from: dict[str, str] = state.get("exploit_from", {})  # PBT: loser -> winner
        self.rng = np.random.default_rng(cfg.seed)
        if "rng" in state:
            self.rng.bit_generator.state = state["rng"]
        self.learner_seed = cfg.seed * 7919

    # ---------------------------------------------------------------- state
    def state(self) -> dict[str, Any]:
        """Everything needed to continue after the last completed generation."""
        return {
            "generation": self.generation,
            "population": list(self.population),
            "new_learners": list(self.new_learners),
            "eta": dict(self.eta),
            "hparams": dict(self.hparams),
            "exploit_from": dict(self.exploit_from),
            "rng": self.rng.bit_generator.state,
        }

    def worker_pids(self) -> list[int]:
        return ray.get([w.pid.remote() for w in self.workers])

    def workers_handles(self) -> list[Any]:
        return list(self.workers)

    # -------------------------------------------------------------- helpers
    def spec(self, member_id: str) -> MemberSpec:
        return MemberSpec(name=member_id, kind="checkpoint", checkpoint=str(self.checkpoint_path(member_id)))

    def checkpoint_path(self, member_id: str) -> Path:
        return (self.run_dir / "members" / f"{member_id}.pt").resolve()

    def _learner(self, init_from: str | None = None, hparams: dict[str, float] | None = None) -> Any:
        """A fresh learner actor, with the weights (and hyperparameters) of ``init_from`` when given."""
        self.learner_seed += 1
        learner = LearnerActor.options(num_gpus=self.cfg.learner_gpus).remote(
            self.net, self.ppo, self.task.players.num_e, self.num_p, self.learner_seed
        )
        if init_from is not None:
            from atdrone.models.checkpoint import load_checkpoint

            model, _ = load_checkpoint(self.checkpoint_path(init_from))
            ray.get(learner.set_weights.remote(model.state_dict()))
        hp = hparams if hparams is not None else self.hparams.get(init_from or "")
        if hp:
            ray.get(learner.set_hparams.remote(**hp))
        return learner

    def _train(
        self, learner: Any, partners: list[MemberSpec], probs: list[float] | None, num_ctrl: int
    ) -> list[dict[str, float]]:
        """updates_per_generation PPO updates of ``learner`` with these partners."""
        history = []
        for _ in range(self.cfg.updates_per_generation):
            t0 = time.perf_counter()
            weights = learner.get_weights.remote()  # one object ref, shared by every worker
            fragments = [
                w.collect.remote(weights, partners, probs, num_ctrl, self.cfg.rollout_steps) for w in self.workers
            ]
            stats = ray.get(learner.update.remote(*fragments))
            stats["perf/pursuer_steps_per_s"] = stats["train/samples"] / (time.perf_counter() - t0)
            history.append(stats)
        return history

    def _register(self, learner: Any, algorithm: str, parents: list[str], history: list[dict[str, float]]) -> str:
        member_id = new_member_id(algorithm, self.generation)
        last = history[-1] if history else {}
        header = {
            "name": member_id,
            "task": self.task.name,
            "num_p": self.num_p,
            "num_e": self.task.players.num_e,
            "algorithm": algorithm,
            "config": self.cfg.to_dict(),
            "seed": self.cfg.seed,
            "step": self.cfg.updates_per_generation
            * self.cfg.num_workers
            * self.cfg.envs_per_worker
            * self.cfg.rollout_steps,
            "generation": self.generation,
            "parents": parents,
            "metrics": {k: v for k, v in last.items() if k.startswith("train/")},
        }
        full = ray.get(learner.save.remote(str(self.checkpoint_path(member_id)), header))
        ray.get(
            self.registry.add_member.remote(
                run=self.run,
                algorithm=algorithm,
                generation=self.generation,
                task=self.task.name,
                parents=parents,
                checkpoint=str(self.checkpoint_path(member_id)),
                sha256=full["sha256"],
                metrics=header["metrics"],
                member_id=member_id,
            )
        )
        self.hparams[member_id] = ray.get(learner.hparams.remote())
        return member_id

    def _evaluate_teams(self, teams: list[tuple[str, ...]]) -> list[dict[str, Any]]:
        """Play each team (learner id repeated num_ctrl times + partner ids) on the workers; record the matches."""
        seeds = [self.cfg.seed * 100003 + self.generation * 1009 + i for i in range(len(teams))]
        calls = [
            self.workers[i % len(self.workers)].evaluate.remote(
                self.spec(team[0]), [self.spec(p) for p in team[self.num_ctrl :]], self.cfg.eval_episodes, seed
            )
            for i, (team, seed) in enumerate(zip(teams, seeds, strict=True))
        ]
        rows = []
        for team, seed, result in zip(teams, seeds, ray.get(calls), strict=True):
            self.registry.add_match.remote(
                list(team), self.task.name, self.run, self.generation, [seed], self.cfg.eval_episodes, result
            )
            rows.append({"team": list(team), **result})
        return rows

    def _slot_order(self, key: tuple[str, ...], learners: list[str]) -> tuple[str, ...]:
        """A team_key as slots: the learner (filling num_ctrl slots) first, then its partners."""
        for m in learners:
            if key.count(m) >= self.num_ctrl:
                rest = list(key)
                for _ in range(self.num_ctrl):
                    rest.remove(m)
                return (m,) * self.num_ctrl + tuple(rest)
        raise ValueError(f"team {key} has no learner filling {self.num_ctrl} slots")

    # ----------------------------------------------------------- generation
    def run_generation(self) -> dict[str, Any]:
        """One generation of the configured algorithm; returns its report."""
        t0 = time.perf_counter()
        ray.get(self.registry.start_generation.remote(self.run, self.generation, {"algorithm": self.cfg.algorithm}))
        algo = self.cfg.algorithm
        report: dict[str, Any] = {"generation": self.generation, "algorithm": algo}
        if algo in ("hola", "hola_no_g"):
            report.update(self._hola_generation(uniform=algo == "hola_no_g"))
        elif algo == "pbt":
            report.update(self._pbt_generation())
        else:
            report.update(self._single_generation(algo))
        report["population"] = list(self.population)
        report["wall_s"] = time.perf_counter() - t0
        ray.get(
            self.registry.finish_generation.remote(
                self.run, self.generation, {"population": self.population, "learners": report["learners"]}
            )
        )
        self.generation += 1
        return report

    def _single_generation(self, algo: str) -> dict[str, Any]:
        """sp: self-play snapshot; br: best response to the zoo (uniform partners)."""
        parent = self.population[-1] if self.population else None
        learner = self._learner(init_from=parent)
        if algo == "sp":
            history = self._train(learner, [], None, self.num_p)
        else:
            history = self._train(learner, list(self.zoo), [1.0] * len(self.zoo), self.num_ctrl)
        member = self._register(learner, algo, [parent] if parent else [], history)
        ray.kill(learner)
        self.population.append(member)
        return {"learners": [member], "history": {member: history}}

    def _hola_generation(self, uniform: bool) -> dict[str, Any]:
        if not self.population:  # bootstrap: a self-play learner
            learner = self._learner()
            boot = self._train(learner, [], None, self.num_p)
            member = self._register(learner, self.cfg.algorithm, [], boot)
            ray.kill(learner)
            self.population, self.new_learners = [member], [member]
            return {"learners": [member], "history": {member: boot}, "matches": [], "eta": {}, "rho": {}}
        played = ray.get(self.registry.matches.remote(run=self.run))
        known = [tuple(t) for t in played["team"]] if len(played) else []
        missing = hola.missing_hyperedges(self.population, self.new_learners, self.num_ctrl, self.num_partners, known)
        matches = self._evaluate_teams([self._slot_order(k, self.new_learners) for k in missing])
        table = ray.get(self.registry.matches.remote(run=self.run))
        weights = {}
        if len(table):
            table = table[table["team"].map(lambda t: set(t) <= set(self.population))].copy()
            table["score"] = table["SUC"] / 100.0  # a hyperedge's weight: the team's success rate
            weights = hola.hyperedge_weights(table)
        self.eta = hola.preference_centrality(weights, nodes=self.population)
        candidates = list(self.population)
        rho = hola.uniform_distribution(candidates) if uniform else hola.partner_distribution(self.eta, candidates)
        profiles = hola.sample_profiles(rho, 8, self.num_partners, self.rng)  # logged: what the learners face
        learners: list[str] = []
        history: dict[str, list[dict[str, float]]] = {}
        for _ in range(self.cfg.learners_per_generation):
            learner = self._learner(init_from=self.new_learners[-1])
            specs = [self.spec(m) for m in candidates]
            h = self._train(learner, specs, [rho[m] for m in candidates], self.num_ctrl)
            member = self._register(learner, self.cfg.algorithm, [self.new_learners[-1]], h)
            ray.kill(learner)
            learners.append(member)
            history[member] = h
        eta_all = {m: self.eta.get(m, 0.0) for m in self.population}
        self.population, removed = hola.update_population(self.population, eta_all, learners, self.cfg.population_size)
        for m in removed:
            self.registry.update_member.remote(m, status="retired")
        self.new_learners = learners
        return {
            "learners": learners,
            "history": history,
            "matches": matches,
            "eta": dict(self.eta),
            "rho": rho,
            "rho_entropy": hola.distribution_entropy(rho),
            "profiles": [list(p) for p in profiles],
            "weights": {"|".join(k): v for k, v in weights.items()},
            "preference": {n: list(e) for n, e in hola.preference_hypergraph(weights).items()},
            "removed": removed,
        }

    def _pbt_generation(self) -> dict[str, Any]:
        """Train every member against the others, then exploit/explore by team SUC."""
        size = self.cfg.population_size
        previous: list[str | None] = list(self.population) or [None] * size
        new_members: list[str] = []
        history: dict[str, list[dict[str, float]]] = {}
        for i, parent in enumerate(previous):
            # an exploited member continues from its winner's weights with its own perturbed hyperparameters
            source = self.exploit_from.get(parent, parent) if parent else None
            learner = self._learner(init_from=source, hparams=self.hparams.get(parent) if parent else None)
            if parent is None:  # first generation: spread the hyperparameters
                f = self.cfg.pbt_perturb ** (i - (size - 1) / 2)
                ray.get(learner.set_hparams.remote(lr=self.ppo.lr * f, ent_coef=self.ppo.ent_coef / f))
            others = [m for m in previous if m is not None and m != parent]
            if others:
                h = self._train(learner, [self.spec(m) for m in others], [1.0] * len(others), self.num_ctrl)
            else:
                h = self._train(learner, [], None, self.num_p)
            member = self._register(learner, "pbt", [source] if source else [], h)
            ray.kill(learner)
            new_members.append(member)
            history[member] = h
        # fitness: each member with partners drawn from the others
        teams = []
        for m in new_members:
            others = [o for o in new_members if o != m]
            picks = self.rng.choice(len(others), size=self.num_partners)
            teams.append((m,) * self.num_ctrl + tuple(others[j] for j in picks))
        matches = self._evaluate_teams(teams)
        fitness = {t["team"][0]: t["SUC"] for t in matches}
        order = sorted(new_members, key=lambda m: fitness[m])
        k = max(1, size // 4)
        exploited = {}
        for loser, winner in zip(order[:k], order[::-1][:k], strict=True):
            if loser == winner:
                continue
            hp = dict(self.hparams[winner])
            hp["lr"] *= float(self.rng.choice([1 / self.cfg.pbt_perturb, self.cfg.pbt_perturb]))
            hp["ent_coef"] *= float(self.rng.choice([1 / self.cfg.pbt_perturb, self.cfg.pbt_perturb]))
            self.hparams[loser] = hp
            exploited[loser] = winner
        self.exploit_from = exploited
        self.population = new_members
        return {
            "learners": new_members,
            "history": history,
            "matches": matches,
            "fitness": fitness,
            "exploited": exploited,
            "hparams": {m: self.hparams[m] for m in new_members},
        }

    # ------------------------------------------------------------ final eval
    def evaluate_population(self, zoo_name: str, episodes: int) -> dict[str, dict[str, float]]:
        """Every population member with partners from a zoo: SUC/COL/AST/REW per member."""
        zoo = load_zoo(zoo_name)
        if zoo.missing:
            return {}
        specs = list(zoo.spec.members)
        calls = [
            self.workers[i % len(self.workers)].evaluate_zoo.remote(self.spec(m), specs, episodes, 4242 + i)
            for i, m in enumerate(self.population)
        ]
        results = dict(zip(self.population, ray.get(calls), strict=True))
        for m, res in results.items():
            self.registry.update_member.remote(m, metrics={f"{zoo_name}/{k}": v for k, v in res.items()})
        return results
