"""Every split of the team: a learner in k of the N pursuer slots, for every k and seat assignment.

The N-agent ad hoc teamwork protocol: for k = 1 .. N - 1 and every choice of the k slots
the learner flies (the seats; the zoo fills the others), the same numbered episodes are
played, so a per-k row pools its seat assignments over the same spawns. Teams of other
sizes are tasks of their own (configs/tasks/<P>p<E>e1o.json): the entity networks pool
teammates and evaders, so a drone trained in one team size acts in the others unchanged.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path
from typing import TYPE_CHECKING

from atdrone.config import TaskConfig, load_task
from atdrone.policies.base import Policy
from atdrone.policies.zoo import Zoo, load_zoo
from atdrone.teams.evaluation import METRICS, Evaluation, evaluate, metrics
from atdrone.teams.protocols import Protocol

if TYPE_CHECKING:
    import pandas as pd


def seat_assignments(num_p: int) -> list[tuple[int, ...]]:
    """Every set of learner slots: k = 1 .. num_p - 1, each k's slot sets in lexicographic order."""
    return [seats for k in range(1, num_p) for seats in combinations(range(num_p), k)]


@dataclass(frozen=True)
class SplitResult:
    """One evaluation per seat assignment, and the per-k table."""

    task: str
    zoo: str
    cells: dict[tuple[int, ...], Evaluation]

    def records(self) -> pd.DataFrame:
        """Every episode of every seat assignment, with its ``k`` and ``seats``."""
        import pandas as pd

        frames = []
        for seats, ev in self.cells.items():
            frame = ev.records.copy()
            frame["k"], frame["seats"] = len(seats), ",".join(map(str, seats))
            frames.append(frame)
        return pd.concat(frames, ignore_index=True)

    def per_k(self) -> pd.DataFrame:
        """One row per k: METRICS over all its seat assignments' episodes, and how many assignments it has."""
        import pandas as pd

        rows = []
        for k, group in self.records().groupby("k"):
            rows.append({"k": int(k), "seat_sets": group["seats"].nunique(), "episodes": len(group), **metrics(group)})
        return pd.DataFrame(rows).set_index("k")[["seat_sets", "episodes", *METRICS]]


def evaluate_splits(
    learner: Policy,
    task: TaskConfig | str,
    zoo: Zoo | str | Path,
    episodes: int = 500,
    seeds: Sequence[int] = (0,),
    protocol: Protocol | str | None = None,
    cross_task: bool = False,
    on_progress: Callable[[int], None] | None = None,
) -> SplitResult:
    """``learner`` in every seat assignment of ``task`` (:func:`seat_assignments`), ``episodes`` per seed each."""
    cfg = load_task(task)
    resolved = (zoo if isinstance(zoo, Zoo) else load_zoo(zoo)).resolve(cfg)
    cells = {
        seats: evaluate(
            learner,
            cfg,
            resolved,
            episodes,
            seeds,
            on_progress=on_progress,
            cross_task=cross_task,
            protocol=protocol,
            num_ctrl=len(seats),
            seats=seats,
        )
        for seats in seat_assignments(cfg.players.num_p)
    }
    first = next(iter(cells.values()))
    return SplitResult(task=cfg.name, zoo=first.zoo, cells=cells)
