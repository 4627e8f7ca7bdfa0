"""HOLA-Drone V2 (the paper's appendix "HOLA-Drone (V2) Algorithm"; SPEC section 10) and its "w/o g" ablation.

Generation 0 builds Pi_0; every later generation t reads like PSRO's iteration, over
the pure functions of :mod:`atdrone.population.hypergraph`:

    N_t (last generation's learners) are in Pi_t
    -> G'_t: N_t with every M-subset of Pi_t minus N_t       (learner_hyperedges)
    -> play them until the preferences are resolved or capped (pooled, contested_preferences)
    -> PG'_t and eta = in-degree in PG'_t / degree in G'_t    (preference_centrality)
    -> rho over Pi_t minus N_t: normalised 1 / eta, eta with a prior count (smoothed_centrality)
    -> profiles M ~ rho: teams of M distinct members         (profile_distribution)
    -> max step: PPO best responses N_{t+1} trained on exactly those draws, per
       environment and per episode; the rollout counts the profiles it drew
    -> N_{t+1} joins the population (retirement only with a cap)

Settings (the ``"hola"`` section of an experiment document):

- ``pi0_seeds`` x ``pi0_levels``: Pi_0 is ``pi0_seeds`` self-play runs, each frozen at
  ``pi0_levels`` evenly spaced skill levels of its ``updates_per_generation`` updates
  (as fictitious co-play and the public HOLA-Drone code do), so the first partners
  span seeds and skill. N_0 is the final snapshot of the first
  ``learners_per_generation`` seeds.
- ``learner_start``: ``"last"`` (each learner continues from a learner of N_t, fresh
  optimiser) or ``"scratch"``.
- ``weight``: a hyperedge's weight, ``"return"`` (mean team return per episode) or
  ``"SUC"`` (success rate); both are recorded with standard errors every generation,
  with the share of preferences each resolves (``hypergraph.json``: ``resolution``).
- ``min_episodes`` / ``max_episodes`` / ``z``: each hyperedge is played
  ``min_episodes`` episodes; while a node's preference is contested (its best team
  does not beat a rival by ``z`` standard errors of the difference) both teams play as
  many episodes again, up to ``max_episodes``. Each round's matches are one batch per
  rollout worker (the coordinator's ``evaluate``), not one match at a time.
- ``eta_prior`` and ``eta_centre``: rho's eta with a prior count a centred on c,
  ``(in + 2 a c) / (degree + 2 a)``; c is the candidates' mean raw eta (``"mean"``,
  the default: typical eta is about 1 / (n - 1), so a member with few hyperedges
  shrinks towards a typical member) or 1/2 (``"half"``, Laplace's rule for a = 1).
- ``rho``: ``"softmin"`` (the default: the appendix's mixed strategy, the learner's own
  hyperedges as profiles, P proportional to exp(-(w - min w) / ``temperature``), in the
  weight's units, 2 by default) or ``"reciprocal"`` (normalised 1 / eta). Chosen by
  measurement: with one partner planted 20 points worse than four others, softmin gives
  it 0.50 of the partner mass (2.5x uniform) in each of 20 seeded generations, the
  reciprocal of eta 0.43 on average and 0.31 at worst, since a good member nobody
  happened to prefer has eta 0 as well (tests/test_hola_signal.py).
- ``replay``: what earns a hyperedge more episodes: the contested preferences of
  ``"partners"`` (the non-learner nodes', whose preferences order the reciprocal rho) or
  of ``"all"`` nodes; or ``"softmin"``: only the learners' hyperedges whose softmin mass
  is still uncertain (they may hold mass and their standard error is over half a
  temperature; :func:`~atdrone.population.hypergraph.uncertain_softmin`), since the
  softmin rho reads nothing else. ``"auto"`` (the default): ``"softmin"`` with the
  softmin rho, else ``"partners"``. Measured on planted preferences (one partner 5 or 20
  points worse, returns with a 15-point sd, 20 seeds; benchmarks/hola_replay.py): with
  the strong effect the softmin replays spend a half to a third of the episodes, with the
  weak one 1-2 % more, and they put as much mass on the planted worst partner or more
  (worst seed 0.42 against 0.36 with 5 candidates, 0.36 against 0.17 with 8).
- ``null_trials``: every generation also reports rho of i.i.d. random weights on the
  same hyperedges (entropy mean and sd, largest rho; ``hypergraph.json``'s ``null``), so
  a reader sees whether the min step found anything. Ties between equal weights are
  broken by a permutation drawn from the generation's generator; a NaN weight or
  standard error is an error.
- ``max_hyperedges``: play a seeded uniform sample of this many hyperedges of G'_t
  when it has more (0: all of them).
- ``population_size`` / ``retire``: off by default (0: the population grows, as in the
  paper); with a cap, the rule ``"oldest"`` or ``"lowest_eta"`` (the public code's).
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

import atdrone.population.hypergraph as hg
from atdrone.config import ConfigError
from atdrone.population.base import (
    Algorithm,
    GenerationReport,
    MatchResult,
    Oracle,
    Team,
    TrainingRecord,
    frozen_snapshots,
    record,
)
from atdrone.teams.partners import profiles, slot_counts

WEIGHTS = {"return": "REW", "SUC": "SUC"}  # weight name -> match metric
STARTS = ("last", "scratch")
CENTRES = ("mean", "half")  # eta's prior centred on the candidates' mean raw eta, or on 1/2 (Laplace)
RHO_RULES = ("reciprocal", "softmin")
REPLAYS = ("auto", "partners", "all", "softmin")  # what earns a hyperedge more episodes (see the module docstring)


@dataclass(frozen=True)
class HolaConfig:
    """See the module docstring."""

    pi0_seeds: int = 2
    pi0_levels: int = 2
    learners_per_generation: int = 1
    learner_start: str = "last"
    weight: str = "return"
    eta_prior: float = 1.0
    min_episodes: int = 32
    max_episodes: int = 256
    z: float = 2.0
    max_hyperedges: int = 0
    population_size: int = 0
    retire: str = "oldest"
    eta_centre: str = "mean"
    rho: str = "softmin"
    temperature: float = 2.0
    replay: str = "auto"
    null_trials: int = 200


class Hola(Algorithm):
    name = "hola"
    Config = HolaConfig
    uniform = False  # the "w/o g" ablation draws partners uniformly

    def __init__(self, config: HolaConfig, seed: int) -> None:
        super().__init__(config, seed)
        self.learners: list[str] = []  # N_t: the last generation's learners
        self.eta: dict[str, float] = {}  # raw eta of the last G'_t
        self.rho: dict[str, float] = {}
        self.drawn: dict[str, int] = {}  # episodes each member was a partner in, last generation
        self.null: dict[str, float] = {}  # rho of random weights on the same hyperedges (null_rho)
        self.min_step_s = 0.0  # wall seconds of the last min step's matches
        self._ties = 0  # the seed of this generation's tie-breaking permutation

    @classmethod
    def check_config(cls, cfg: Any, path: str) -> None:
        checks = [
            ("pi0_seeds", cfg.pi0_seeds >= 1, "must be >= 1"),
            ("pi0_levels", cfg.pi0_levels >= 1, "must be >= 1"),
            ("learners_per_generation", 1 <= cfg.learners_per_generation <= cfg.pi0_seeds, "must be in 1..pi0_seeds"),
            ("learner_start", cfg.learner_start in STARTS, f"must be one of {STARTS}"),
            ("weight", cfg.weight in WEIGHTS, f"must be one of {sorted(WEIGHTS)}"),
            ("eta_prior", cfg.eta_prior > 0, "must be > 0 (it keeps 1 / eta finite)"),
            ("min_episodes", cfg.min_episodes >= 2, "must be >= 2 (a standard error needs two episodes)"),
            ("max_episodes", cfg.max_episodes >= cfg.min_episodes, "must be >= min_episodes"),
            ("z", cfg.z >= 0, "must be >= 0"),
            ("max_hyperedges", cfg.max_hyperedges >= 0, "must be >= 0 (0: every hyperedge of G'_t)"),
            ("retire", cfg.retire in hg.RETIRE_RULES, f"must be one of {hg.RETIRE_RULES}"),
            ("eta_centre", cfg.eta_centre in CENTRES, f"must be one of {CENTRES}"),
            ("rho", cfg.rho in RHO_RULES, f"must be one of {RHO_RULES}"),
            ("temperature", cfg.temperature > 0, "must be > 0"),
            ("replay", cfg.replay in REPLAYS, f"must be one of {REPLAYS}"),
            ("replay", cfg.replay != "softmin" or cfg.rho == "softmin", "'softmin' replays serve the softmin rho only"),
            ("null_trials", cfg.null_trials >= 0, "must be >= 0 (0: no null baseline)"),
        ]
        for key, ok, message in checks:
            if not ok:
                raise ConfigError(f"{path}.{key}", f"{message}, got {getattr(cfg, key)!r}")
        smallest = cfg.pi0_seeds * cfg.pi0_levels + cfg.learners_per_generation
        if cfg.population_size and cfg.population_size < smallest:
            raise ConfigError(
                f"{path}.population_size",
                f"must be 0 (no cap) or hold Pi_0 and a generation's learners ({smallest}), got {cfg.population_size}",
            )

    @classmethod
    def check_experiment(cls, cfg: Any, experiment: Any, path: str) -> None:
        if experiment.updates_per_generation < cfg.pi0_levels:
            raise ConfigError(
                f"{path}.pi0_levels",
                f"{cfg.pi0_levels} skill levels need updates_per_generation >= {cfg.pi0_levels}, "
                f"got {experiment.updates_per_generation}",
            )

    # ------------------------------------------------------------ generation
    def generation(self, oracle: Oracle) -> GenerationReport:
        if not self.population:
            return self._pi0(oracle)
        cfg = self.config
        others = [m for m in self.population if m not in self.learners]  # Pi_t minus N_t
        played, rounds, stats, smoothed, draws = self.min_step(oracle, others)
        # max step: best responses trained on profiles drawn from rho, per environment and episode
        learners, training = [], []
        for k in range(cfg.learners_per_generation):
            start = self.learners[k % len(self.learners)] if cfg.learner_start == "last" else None
            trained = oracle.train(start, profiles(draws))
            member = oracle.register(trained, [start] if start else [])
            learners.append(member)
            training.append(record(member, trained))
        # N_{t+1} joins the population
        self.population, removed = hg.update_population(
            self.population, learners, cfg.population_size, cfg.retire, smoothed
        )
        oracle.retire(removed)
        self.learners = learners
        return self._report(oracle, learners, training, played, removed, stats, smoothed, draws, rounds)

    def min_step(
        self, oracle: Oracle, others: list[str]
    ) -> tuple[dict[Team, list[MatchResult]], int, dict[str, dict[Team, tuple[float, float]]], dict[str, float], dict]:
        """G'_t played until its preferences are resolved (or capped), eta, rho and the profiles to draw.

        Sets ``eta``, ``rho`` and ``null``; returns (played matches, rounds, statistics per
        weight, smoothed eta, profile distribution).
        """
        cfg = self.config
        # min step: G'_t, played until its preferences are resolved (or capped)
        edges = hg.learner_hyperedges(self.learners, others, oracle.num_ctrl, oracle.num_partners)
        if cfg.max_hyperedges and len(edges) > cfg.max_hyperedges:
            keep = sorted(oracle.rng.choice(len(edges), size=cfg.max_hyperedges, replace=False).tolist())
            edges = [edges[i] for i in keep]
        started = time.perf_counter()
        played, rounds = self._play(oracle, edges)
        self.min_step_s = time.perf_counter() - started  # the matches' wall time (perf/min_step_s)
        stats = {w: self._stats(played, metric) for w, metric in WEIGHTS.items()}
        weights = {team: w for team, (w, _) in stats[cfg.weight].items()}
        tie_seed = int(oracle.rng.integers(2**32))  # ties broken by one permutation from the generation's rng
        self._ties = tie_seed
        ties = lambda: np.random.default_rng(tie_seed)  # the same permutation for every call
        self.eta = hg.preference_centrality(weights, nodes=self.population, rng=ties())
        smoothed = self._smoothed(weights, others, ties)
        self.rho, draws = self._profiles(weights, others, oracle.num_partners, ties)
        if cfg.null_trials:

            def rho_of(w: dict[Team, float]) -> dict[str, float]:
                return self._profiles(w, others, oracle.num_partners, ties)[0]

            self.null = hg.null_rho(weights, rho_of, np.random.default_rng(tie_seed), cfg.null_trials)
        return played, rounds, stats, smoothed, draws

    def _smoothed(self, weights: dict[Team, float], others: list[str], ties: Any) -> dict[str, float]:
        """eta with the prior count, centred as the config says (see the module docstring)."""
        cfg = self.config
        centre = hg.mean_centrality(weights, others, ties()) if cfg.eta_centre == "mean" else 0.5
        return hg.smoothed_centrality(weights, self.population, cfg.eta_prior, centre, ties())

    def _profiles(
        self, weights: dict[Team, float], others: list[str], num_partners: int, ties: Any
    ) -> tuple[dict[str, float], dict[Team, float]]:
        """rho over Pi minus N_t and the partner profiles to draw: uniform ("w/o g"), the reciprocal of the
        smoothed eta, or softmin over the learners' hyperedges (rho: each member's share of the slots)."""
        cfg = self.config
        if self.uniform or cfg.rho == "reciprocal":
            rho = (
                hg.uniform_distribution(others)
                if self.uniform
                else hg.partner_distribution(self._smoothed(weights, others, ties), others)
            )
            return rho, hg.profile_distribution(rho, num_partners)
        return hg.softmin_rho(weights, self.learners, others, num_partners, cfg.temperature)

    def _pi0(self, oracle: Oracle) -> GenerationReport:
        """Pi_0: pi0_seeds self-play runs, each frozen at pi0_levels skill levels; N_0: the first seeds' finals."""
        cfg = self.config  # updates_per_generation >= pi0_levels (check_experiment)
        members, training, splits = frozen_snapshots(oracle, cfg.pi0_seeds, cfg.pi0_levels)
        self.population.extend(members)
        finals = members[cfg.pi0_levels - 1 :: cfg.pi0_levels]
        self.learners = finals[: cfg.learners_per_generation]
        return GenerationReport(
            oracle.generation,
            self.name,
            list(self.learners),
            list(self.population),
            training=training,
            documents={"pi0.json": {"seeds": cfg.pi0_seeds, "levels": splits, "members": self.population}},
        )

    def _play(self, oracle: Oracle, edges: Sequence[Team]) -> tuple[dict[Team, list[MatchResult]], int]:
        """Every hyperedge min_episodes episodes, then the contested ones as many again, up to max_episodes."""
        cfg = self.config
        played: dict[Team, list[MatchResult]] = {e: [] for e in edges}
        episodes = dict.fromkeys(edges, 0)
        todo, rounds = list(edges), 0
        replay = cfg.replay if cfg.replay != "auto" else ("softmin" if cfg.rho == "softmin" else "partners")
        while todo:
            counts = [min(max(cfg.min_episodes, episodes[e]), cfg.max_episodes - episodes[e]) for e in todo]
            for result in oracle.evaluate(todo, counts):
                played[result.team].append(result)
                episodes[result.team] += result.episodes
            rounds += 1
            stats = self._stats(played, WEIGHTS[cfg.weight])
            if replay == "softmin":
                uncertain = hg.uncertain_softmin(stats, self.learners, cfg.temperature, cfg.z)
                todo = [e for e in edges if hg.team_key(e) in uncertain and episodes[e] < cfg.max_episodes]
                continue
            judges = hg.contested_preferences(stats, cfg.z)
            if replay == "partners":  # the learner's own preference decides nothing about rho's order
                judges = {node: teams for node, teams in judges.items() if node not in self.learners}
            contested = set().union(*judges.values())
            todo = [e for e in edges if hg.team_key(e) in contested and episodes[e] < cfg.max_episodes]
        return played, rounds

    @staticmethod
    def _stats(played: Mapping[Team, list[MatchResult]], metric: str) -> dict[Team, tuple[float, float]]:
        """team_key -> (weight, standard error) from the pooled episodes of every match of the team."""
        out = {}
        for team, results in played.items():
            batches = []
            for r in results:
                if metric == "SUC":
                    p = r.metrics["SUC"] / 100.0
                    batches.append((r.episodes, p, r.episodes * p * (1 - p) / max(r.episodes - 1, 1)))
                else:
                    batches.append((r.episodes, r.metrics["REW"], r.metrics["REW_var"]))
            mean, se, _ = hg.pooled(batches)
            out[hg.team_key(team)] = (mean, se)
        return out

    def _report(
        self,
        oracle: Oracle,
        learners: list[str],
        training: list[TrainingRecord],
        played: dict[Team, list[MatchResult]],
        removed: list[str],
        stats: dict[str, dict[Team, tuple[float, float]]],
        smoothed: dict[str, float],
        draws: dict[Team, float],
        rounds: int,
    ) -> GenerationReport:
        cfg = self.config
        drawn_profiles: dict[str, int] = {}
        for t in training:
            for profile, n in t.drawn.items():
                drawn_profiles[profile] = drawn_profiles.get(profile, 0) + n
        self.drawn = slot_counts(drawn_profiles)
        nodes = len({m for e in played for m in e})
        resolution = {
            w: {"contested_nodes": len(hg.contested_preferences(s, cfg.z)), "nodes": nodes} for w, s in stats.items()
        }
        matches = [r for results in played.values() for r in results]
        episodes = sum(r.episodes for r in matches)
        weights = {team: w for team, (w, _) in stats[cfg.weight].items()}
        metrics = {
            "pop/rho_entropy": hg.distribution_entropy(self.rho),
            **{f"pop/null_rho_{k}": v for k, v in self.null.items() if k != "trials"},
            "eval/hyperedges": float(len(played)),
            "eval/episodes": float(episodes),
            "eval/rounds": float(rounds),
            "perf/min_step_s": self.min_step_s,
        }
        metrics.update(
            {f"eval/contested_share/{w}": r["contested_nodes"] / max(r["nodes"], 1) for w, r in resolution.items()}
        )
        metrics.update({f"pop/eta/{m}": v for m, v in self.eta.items()})
        metrics.update({f"pop/rho/{m}": v for m, v in self.rho.items()})
        metrics.update({f"pop/drawn/{m}": float(n) for m, n in self.drawn.items()})
        graph = {
            "learners": sorted({e[0] for e in played}),
            "weight": cfg.weight,
            "hyperedges": [
                {
                    "team": list(team),
                    "episodes": sum(r.episodes for r in results),
                    **{f"{w}": stats[w][hg.team_key(team)][0] for w in WEIGHTS},
                    **{f"{w}_se": stats[w][hg.team_key(team)][1] for w in WEIGHTS},
                }
                for team, results in played.items()
            ],
            "weights": {"|".join(k): v for k, v in weights.items()},
            "preference": {
                n: list(e) for n, e in hg.preference_hypergraph(weights, np.random.default_rng(self._ties)).items()
            },
            "eta": dict(self.eta),
            "eta_smoothed": smoothed,
            "rho": dict(self.rho),
            "null": dict(self.null),
            "profiles": {"|".join(sorted(p)): v for p, v in draws.items()},
            "member_shares": hg.member_shares(draws),
            "drawn_profiles": dict(sorted(drawn_profiles.items())),
            "drawn_members": dict(sorted(self.drawn.items())),
            "resolution": resolution,
            "rounds": rounds,
            "removed": removed,
        }
        return GenerationReport(
            oracle.generation,
            self.name,
            learners,
            list(self.population),
            training=training,
            matches=matches,
            removed=removed,
            metrics=metrics,
            documents={"hypergraph.json": graph},
        )

    # ----------------------------------------------------------------- state
    def state(self) -> dict[str, Any]:
        return {
            **super().state(),
            "learners": self.learners,
            "eta": self.eta,
            "rho": self.rho,
            "drawn": self.drawn,
            "null": self.null,
        }

    def load_state(self, state: Mapping[str, Any]) -> None:
        super().load_state(state)
        self.learners = list(state.get("learners", []))
        self.eta = dict(state.get("eta", {}))
        self.rho = dict(state.get("rho", {}))
        self.drawn = dict(state.get("drawn", {}))
        self.null = dict(state.get("null", {}))

    @classmethod
    def figures(cls, report: GenerationReport, out_dir: Path) -> list[Path]:
        graph = report.documents.get("hypergraph.json")
        if not graph or not graph["weights"]:
            return []
        from atdrone.population.plots import draw_hypergraph

        path = out_dir / "hypergraph.png"
        draw_hypergraph(
            graph["weights"], graph["preference"], graph["eta"], path, rho=graph["rho"], generation=report.generation
        )
        return [path]


class HolaNoG(Hola):
    """The ablation: profiles drawn uniformly from Pi minus N_t instead of from rho."""

    name = "hola_no_g"
    uniform = True
