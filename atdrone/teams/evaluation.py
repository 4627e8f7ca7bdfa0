"""The AT-Drone evaluation protocol (paper section 3.3, SPEC section 9).

A learner fills the num_ctrl learner slots, a zoo fills the rest, and N episodes,
numbered 0..N-1, run in parallel on BatchedPursuit (so short episodes are not
over-counted): up to ``max_envs`` at a time, a row that finishes starts the next
episode not yet started, and once every episode has started, finished rows leave the
batch, so N episodes cost about the sum of their lengths in environment steps. An
episode's draws (spawn, evader wandering, team, sampled actions) come from its own
key, so its record depends on the seed and its number only, not on the batch it ran
in. From the raw episode records:
  SUC  % of episodes in which every evader was captured;
  COL  % of episodes with a collision (drone-drone or drone-obstacle);
  AST  mean length in steps of the successful episodes (NaN when none succeeded);
  REW  mean team return per episode.
Each metric comes with a 95 % confidence interval over the episodes (all seeds pooled):
Wilson's score interval for the percentages SUC and COL, the normal interval of a mean
for AST and REW. With several seeds, the Student-t interval of the per-seed values says
how much a seed moves the result; one seed has no spread to report, so none is printed.
With a protocol of team events (:mod:`atdrone.teams.protocols`) every record also holds
its schedule, the step of its first event and the steps from it to the next capture, and
the metrics add EVENT_METRICS (SUC/COL before and after the event, recovery time).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from atdrone.config import ConfigError, TaskConfig, load_task
from atdrone.envs.core import CAPTURED, DONE_REASONS, BatchedPursuit
from atdrone.envs.events import EventPlan, describe
from atdrone.envs.geometry import NUM_WALLS
from atdrone.policies.base import Policy
from atdrone.policies.zoo import Zoo, load_zoo
from atdrone.teams.match import Match, PartnerSampler
from atdrone.teams.protocols import (
    EVENT_FIELDS,
    EVENT_METRICS,
    Protocol,
    evaluation_protocol,
    event_counts,
    event_metrics,
)

if TYPE_CHECKING:  # imported where a frame is made: a learner or rollout actor that never evaluates skips it
    import pandas as pd

METRICS = ("SUC", "COL", "AST", "REW")
MAX_ENVS = 1024
Z95 = 1.959963984540054  # the standard normal's 97.5 % quantile
Interval = tuple[float, float]


def wilson_interval(successes: int, n: int, z: float = Z95) -> Interval:
    """Wilson's score interval of a proportion, in %: sound at 0 % and 100 %, where the normal one collapses."""
    if n < 1:
        return (float("nan"), float("nan"))
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (100.0 * max(0.0, centre - half), 100.0 * min(1.0, centre + half))


def mean_interval(values: np.ndarray, z: float = Z95) -> Interval:
    """The normal 95 % interval of a mean of independent values; NaN with fewer than two."""
    values = np.asarray(values, dtype=float)
    if len(values) < 2:
        return (float("nan"), float("nan"))
    mean, half = float(values.mean()), z * float(values.std(ddof=1)) / math.sqrt(len(values))
    return (mean - half, mean + half)


def seed_interval(values: np.ndarray) -> Interval:
    """The Student-t 95 % interval of the mean of per-seed values; NaN with fewer than two finite ones."""
    from scipy.stats import t as student

    finite = np.asarray(values, dtype=float)
    finite = finite[np.isfinite(finite)]
    if len(finite) < 2:
        return (float("nan"), float("nan"))
    half = float(student.ppf(0.975, len(finite) - 1)) * float(finite.std(ddof=1)) / math.sqrt(len(finite))
    return (float(finite.mean()) - half, float(finite.mean()) + half)


def episode_intervals(records: pd.DataFrame) -> dict[str, Interval]:
    """The 95 % interval of each of METRICS (and EVENT_METRICS, for records with events) over episode records."""
    success = records["success"].to_numpy(bool)
    out = {
        "SUC": wilson_interval(int(success.sum()), len(success)),
        "COL": wilson_interval(int(records["collided"].to_numpy(bool).sum()), len(success)),
        "AST": mean_interval(records["length"].to_numpy()[success]),
        "REW": mean_interval(records["return"].to_numpy()),
    }
    if "event_step" in records:
        counts, rec = event_counts(records)
        out.update({k: wilson_interval(hits, total) for k, (hits, total) in counts.items()})
        out["REC"] = mean_interval(rec)
    return out


@dataclass(frozen=True)
class Evaluation:
    """Metrics of one learner x task x zoo, per seed and aggregated, with the raw records."""

    task: str
    zoo: str
    learner: str
    per_seed: pd.DataFrame  # index seed, columns METRICS
    records: pd.DataFrame  # one row per episode
    zoo_version: str = ""  # the zoo manifest's version of the task's zoos ("" for a zoo it does not list)
    cross_task: tuple[str, ...] = ()  # partners trained on another task (``name@task``), played on purpose
    protocol: str = ""  # the protocol of team events played ("" for none; then ``zoo`` names it)

    @property
    def metric_names(self) -> tuple[str, ...]:
        """METRICS, and EVENT_METRICS when a protocol of team events was played."""
        return METRICS + EVENT_METRICS if self.protocol else METRICS

    @property
    def mean(self) -> dict[str, float]:
        return {m: float(self.per_seed[m].mean()) for m in self.metric_names}

    @property
    def std(self) -> dict[str, float]:
        return {m: float(self.per_seed[m].std(ddof=0)) for m in self.metric_names}

    @property
    def pooled(self) -> dict[str, float]:
        """The metrics of all episodes together (the centre of :attr:`interval`)."""
        return metrics(self.records)

    @property
    def interval(self) -> dict[str, Interval]:
        """95 % confidence interval of each metric over the episodes, every seed's pooled."""
        return episode_intervals(self.records)

    @property
    def seed_interval(self) -> dict[str, Interval] | None:
        """95 % Student-t interval of each metric over the seeds' values; None with one seed."""
        if len(self.per_seed) < 2:
            return None
        return {m: seed_interval(self.per_seed[m].to_numpy()) for m in self.metric_names}

    def summary(self) -> dict[str, object]:
        row: dict[str, object] = {"task": self.task, "zoo": self.zoo, "learner": self.learner}
        if self.protocol:
            row["protocol"] = self.protocol
        if "num_ctrl" in self.records:
            row["num_ctrl"] = int(self.records["num_ctrl"].iloc[0])
        row["zoo_version"] = self.zoo_version
        if self.cross_task:
            row["cross_task_partners"] = list(self.cross_task)
        row["episodes"] = len(self.records)
        row["seeds"] = len(self.per_seed)
        interval, over_seeds = self.interval, self.seed_interval
        for m in self.metric_names:
            row[m] = self.mean[m]
            row[f"{m}_std"] = self.std[m]
            row[f"{m}_ci95"] = list(interval[m])
            if over_seeds is not None:
                row[f"{m}_seeds_ci95"] = list(over_seeds[m])
        return row


def metrics(records: pd.DataFrame) -> dict[str, float]:
    """SUC, COL, AST, REW of a set of episode records (and EVENT_METRICS for records with events)."""
    success = records["success"].to_numpy(bool)
    out = {
        "SUC": 100.0 * success.mean(),
        "COL": 100.0 * records["collided"].to_numpy(bool).mean(),
        "AST": float(records["length"][success].mean()) if success.any() else float("nan"),
        "REW": float(records["return"].mean()),
    }
    if "event_step" in records:
        out.update(event_metrics(records))
    return out


def crash_shares(records: pd.DataFrame) -> dict[str, float]:
    """% of episodes ended by a collision with a learner in it, and by partners alone."""
    ended = (records["outcome"] == "collision").to_numpy(bool)
    learner = records["learner_crashed"].to_numpy(bool) & ended
    partner_only = records["partner_crashed"].to_numpy(bool) & ended & ~learner
    return {"learner_crash": 100.0 * learner.mean(), "partner_only_crash": 100.0 * partner_only.mean()}


CRASH_KINDS = (
    "learner-learner",
    "learner-partner",
    "partner-partner",
    "learner-wall",
    "learner-obstacle",
    "partner-wall",
    "partner-obstacle",
)


def crash_kinds(info: dict, envs: np.ndarray, learner_slots: np.ndarray, pairs: np.ndarray) -> list[str]:
    """What collided in each of ``envs`` this step, as "+"-joined CRASH_KINDS ("" when nothing did).

    learner_slots (len(envs), num_ctrl); pairs (pairs, 2) as ``BatchedPursuit.pairs``.
    """
    learner = np.zeros((len(envs), info["collided"].shape[1]), dtype=bool)
    np.put_along_axis(learner, learner_slots, True, axis=1)
    hit_pairs, hit_obstacle = info["hit_pairs"][envs], info["hit_obstacle"][envs]
    in_pair = learner[:, pairs[:, 0]].astype(int) + learner[:, pairs[:, 1]]  # learners in each pair: 2, 1, 0
    wall = (hit_obstacle >= 0) & (hit_obstacle < NUM_WALLS)
    obstacle = hit_obstacle >= NUM_WALLS
    kinds = np.stack(
        [
            (hit_pairs & (in_pair == 2)).any(1),
            (hit_pairs & (in_pair == 1)).any(1),
            (hit_pairs & (in_pair == 0)).any(1),
            (wall & learner).any(1),
            (obstacle & learner).any(1),
            (wall & ~learner).any(1),
            (obstacle & ~learner).any(1),
        ],
        1,
    )  # (n, CRASH_KINDS)
    return ["+".join(k for k, hit in zip(CRASH_KINDS, row, strict=True) if hit) for row in kinds]


def crash_breakdown(records: pd.DataFrame) -> dict[str, float]:
    """% of episodes whose ending collision involved each of CRASH_KINDS (an episode may count twice)."""
    counts = records["crash"].fillna("").str.split("+").explode().value_counts()
    return {kind: 100.0 * float(counts.get(kind, 0)) / len(records) for kind in CRASH_KINDS}


def task_fit(policy: Policy, tasks: Sequence[TaskConfig], cross_task: bool = False) -> list[str]:
    """Check a trained policy against the tasks it is asked to play.

    A network pools its teammates and evaders, so it acts in a team of any size. Another task (another
    size included) is refused (ConfigError naming both tasks) unless ``cross_task`` asks for it; then it
    plays, with a note (returned) saying so.
    """
    trained_on = getattr(policy, "task", "")
    num_p, num_e = getattr(policy, "num_p", None), getattr(policy, "num_e", None)
    if not trained_on or num_p is None:  # a rule policy plays any task
        return []
    notes = []
    for task in tasks:
        players = task.players
        if task.name != trained_on and not cross_task:
            raise ConfigError(
                "--task",
                f"{policy.name} was trained on {trained_on}, not on {task.name}: a cross-task evaluation must be "
                "asked for (--cross-task)",
            )
        if players.num_e != num_e or task.name != trained_on:
            notes.append(
                f"{policy.name} was trained on {trained_on} ({num_p}p{num_e}e) and plays {task.name} "
                f"({players.num_p}p{players.num_e}e): an unseen task, not its own"
            )
    return notes


def run_episodes(
    learner: Policy,
    task: TaskConfig | str,
    partners: Zoo | Sequence[Policy],
    episodes: int,
    seed: int = 0,
    max_envs: int = MAX_ENVS,
    on_progress: Callable[[int], None] | None = None,
    sampler: PartnerSampler | None = None,
    events: EventPlan | None = None,
    num_ctrl: int | None = None,
    seats: Sequence[int] | None = None,
    lineups: np.ndarray | None = None,
) -> pd.DataFrame:
    """Play episodes 0..``episodes``-1 of ``learner`` with ``partners``; one record per episode, in episode order.

    ``sampler`` picks the partner members of each episode (default: uniformly per slot), or ``lineups``
    fixes them: row e, the partners' indices of episode e; ``events``: the team events of every episode;
    ``num_ctrl``: the learner's slots (default the task's); ``seats``: which slots, fixed (default: drawn per
    episode).
    """
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    cfg = load_task(task)
    n = min(episodes, max_envs)
    core_seed, match_seed = episode_seeds(seed)
    core = BatchedPursuit(cfg, num_envs=n, seed=core_seed, events=events)
    match = Match(core, partners, seed=match_seed, sampler=sampler, num_ctrl=num_ctrl, seats=seats, lineups=lineups)
    match.reset()  # episodes 0..n-1; a row that ends starts the next one
    learner.reset(np.ones(n, dtype=bool))
    fields = {**_FIELDS, **EVENT_FIELDS} if core.events is not None else _FIELDS
    rec = {k: np.zeros(episodes, dtype=t) for k, t in fields.items()}
    if core.events is not None:
        rec["event_step"][:], rec["recovery"][:] = -1, -1
    teams = np.empty(episodes, dtype=object)
    while core.num_envs:
        playing = core.state.episode.copy()  # the episode each row plays this step
        batch = match.learner_batch()
        actions = learner.act(batch).reshape(core.num_envs, match.num_ctrl)
        _, _, dones, info = match.step(actions)
        if core.events is not None:
            _track_events(learner, match, info, playing, rec)
        if not dones.any():
            continue
        learner.reset(match.by_seat(dones))
        idx = np.flatnonzero(dones)
        ep = playing[idx]
        rec["reason"][ep] = info["done_reason"][idx]
        rec["length"][ep] = info["episode_length"][idx]
        rec["return"][ep] = info["episode_return"][idx]
        rec["collided"][ep] = info["episode_collided"][idx]
        rec["captured"][ep] = info["episode_captured"][idx]
        team = info["team"]
        teams[ep] = [",".join(match.partner_names[m] for m in members) for members in team["partner_members"][idx]]
        slots = team["learner_slots"][idx]
        rec["learner_slots"][ep] = [",".join(map(str, s)) for s in slots]
        hit = info["collided"][idx]  # (n, P) pursuers in this step's collision
        rec["learner_crashed"][ep] = np.take_along_axis(hit, slots, axis=1).any(1)
        rec["partner_crashed"][ep] = np.take_along_axis(hit, team["partner_slots"][idx], axis=1).any(1)
        rec["crash"][ep] = crash_kinds(info, idx, slots, core.pairs)
        if core.events is not None:
            assert core.final_state is not None  # the batch as the episodes ended
            fs = core.final_state
            rec["events"][ep] = describe(fs.ev_kind[idx], fs.ev_step[idx], fs.ev_slot[idx])
        if on_progress is not None:
            on_progress(len(idx))
        if core.next_episode > episodes:  # the rows that ended started episodes past the last: they leave
            match.keep(np.flatnonzero(core.state.episode < episodes))
    import pandas as pd

    out = pd.DataFrame(rec)
    out.insert(0, "episode", np.arange(episodes))
    out["partners"] = teams
    out["success"] = out["reason"] == CAPTURED
    out["outcome"] = np.array(DONE_REASONS)[out["reason"].to_numpy()]
    out.insert(1, "seed", seed)
    out["num_ctrl"] = match.num_ctrl
    return out


def _track_events(learner: Policy, match: Match, info: dict, playing: np.ndarray, rec: dict[str, np.ndarray]) -> None:
    """Record each episode's first team event and the steps from it to the next capture; a learner drone
    the event replaced is forgotten by the learner."""
    changed = info["team_changed"]
    t = info["episode_length"]
    hit = changed.any(1)
    if hit.any():
        ep = playing[hit]
        first = rec["event_step"][ep] < 0
        rec["event_step"][ep[first]] = t[hit][first]
        env, k = match.changed_learners(changed)
        forget = getattr(learner, "forget", None)
        if len(env) and forget is not None:
            forget(match.seats[env], match.learner_slots[env, k])
    caught = info["captured_now"].any(1)
    if caught.any():
        ep = playing[caught]
        start = rec["event_step"][ep]
        new = (start >= 0) & (rec["recovery"][ep] < 0) & (t[caught] > start)
        rec["recovery"][ep[new]] = t[caught][new] - start[new]


_FIELDS = {
    "reason": np.int8,
    "length": np.int64,
    "return": np.float64,
    "collided": bool,
    "captured": np.int64,
    "learner_slots": object,
    "learner_crashed": bool,  # a learner drone was in the collision that ended the episode
    "partner_crashed": bool,  # a partner drone was in it
    "crash": object,  # what collided at the end: "+"-joined CRASH_KINDS, "" when none
}


def episode_seeds(seed: int) -> tuple[int, int]:
    """The core's and the Match's seeds of evaluation seed ``seed`` (its episodes' keys and teams)."""
    core, match = np.random.SeedSequence(seed).generate_state(2)
    return int(core), int(match)


def evaluate(
    learner: Policy,
    task: TaskConfig | str,
    zoo: Zoo | str | Path,
    episodes: int = 500,
    seeds: Sequence[int] = (0,),
    on_progress: Callable[[int], None] | None = None,
    cross_task: bool = False,
    protocol: Protocol | str | None = None,
    num_ctrl: int | None = None,
    seats: Sequence[int] | None = None,
) -> Evaluation:
    """SUC/COL/AST/REW of ``learner`` with ``zoo`` on ``task``, per seed and aggregated.

    A learner trained on another task is refused (ConfigError) unless ``cross_task``. With a ``protocol``
    its team events are played and its name labels the result; ``num_ctrl`` and ``seats``: see
    :func:`run_episodes`.
    """
    import pandas as pd

    cfg = load_task(task)
    task_fit(learner, [cfg], cross_task)
    proto = evaluation_protocol(protocol) if protocol is not None else None
    zoo = (zoo if isinstance(zoo, Zoo) else load_zoo(zoo)).resolve(cfg)
    partners = zoo.policies()
    plan = proto.plan if proto is not None else None
    records = pd.concat(
        [
            run_episodes(
                learner,
                cfg,
                partners,
                episodes,
                s,
                on_progress=on_progress,
                events=plan,
                num_ctrl=num_ctrl,
                seats=seats,
            )
            for s in seeds
        ],
        ignore_index=True,
    )
    per_seed = pd.DataFrame([{"seed": s, **metrics(g)} for s, g in records.groupby("seed")]).set_index("seed")
    return Evaluation(
        task=cfg.name,
        zoo=proto.name if proto is not None else zoo.name,
        protocol=proto.name if proto is not None else "",
        learner=getattr(learner, "name", "learner"),
        per_seed=per_seed,
        records=records,
        zoo_version=zoo.version if _is_shipped(zoo) else "",
        cross_task=tuple(zoo.cross_task()),
    )


def _is_shipped(zoo: Zoo) -> bool:
    """Whether ``zoo`` is one of the manifest's documents (a user's own zoo has no manifest version)."""
    from atdrone.policies.manifest import POOLS, ZOOS

    return zoo.name in ZOOS or zoo.name in POOLS


@dataclass(frozen=True)
class GridCell:
    """One task x zoo cell of an evaluation grid: its evaluation, or the zoo members that are missing."""

    task: str
    zoo: str
    evaluation: Evaluation | None
    missing: tuple[str, ...] = ()


def evaluate_grid(
    learner: Policy,
    tasks: Sequence[TaskConfig | str],
    zoos: Sequence[Zoo | str],
    episodes: int = 500,
    seeds: Sequence[int] = (0,),
    on_progress: Callable[[int], None] | None = None,
    cross_task: bool = False,
    protocol: Protocol | None = None,
) -> list[GridCell]:
    """Evaluate ``learner`` on every task x zoo (row-major: tasks outer, zoos inner), with ``protocol``'s team
    events when given (its name labels the cells).

    A zoo with missing members is not played: its cells list the missing members.
    """
    cfgs = [load_task(t) for t in tasks]
    loaded = [z if isinstance(z, Zoo) else load_zoo(z) for z in zoos]
    cells = []
    for cfg in cfgs:
        for zoo in (z.resolve(cfg) for z in loaded):
            if zoo.missing:
                cells.append(GridCell(cfg.name, protocol.name if protocol else zoo.name, None, tuple(zoo.missing)))
            else:
                result = evaluate(
                    learner,
                    cfg,
                    zoo,
                    episodes,
                    seeds,
                    on_progress=on_progress,
                    cross_task=cross_task,
                    protocol=protocol,
                )
                cells.append(GridCell(cfg.name, result.zoo, result))
    return cells
