"""The bounds of the normalised scores, per (task, test zoo), kept with the zoo version they were measured with.

A bound is the best response trained with the zoo's partners (its runs' SUC with that zoo, one value per
seed: the upper bound) and the floor (a random learner with the zoo's partners: its successes over its
episodes). A bound is *usable* only when the best response is significantly above the floor: a one-sided
Welch t-test of the runs' mean SUC against the floor's, at the 5 % level, with the floor's binomial variance
and the runs' sample variance (degrees of freedom by Welch-Satterthwaite; one run gives no test, so no
usable bound). An unusable bound is kept and marked, and no score is normalised against it.

The bounds come from a benchmark's ``br`` and ``floor`` cells (:func:`bounds_from_records`) and are stored
in one JSON file (benchmarks/results/bounds.json by default) keyed by task and zoo, each with the zoo
version of its task; :func:`usable_bound` answers only for the current zoo version, so every report
normalises a score against bounds measured with the same partners.
"""

from __future__ import annotations

import json
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.stats

from atdrone.config import repo_path
from atdrone.fileio import atomic_write_bytes

BOUNDS_FILE = "benchmarks/results/bounds.json"
ALPHA = 0.05


@dataclass(frozen=True)
class Bound:
    """The bounds of one (task, zoo): the best response's SUC per run and the floor's successes."""

    task: str
    zoo: str
    zoo_version: str
    br_suc: tuple[float, ...]  # % per best-response run (seed)
    floor_successes: int
    floor_episodes: int
    p_value: float  # one-sided: the best response's mean SUC is above the floor's
    usable: bool  # significant at ALPHA: scores are normalised against it

    @property
    def floor_suc(self) -> float:
        return 100.0 * self.floor_successes / self.floor_episodes

    @property
    def br_mean(self) -> float:
        return float(np.mean(self.br_suc))

    def normalise(self, suc: float) -> float:
        """(SUC - floor) / (best response - floor); NaN when the bound is not usable."""
        if not self.usable:
            return float("nan")
        return (suc - self.floor_suc) / (self.br_mean - self.floor_suc)


def above_floor(br_suc: Sequence[float], floor_successes: int, floor_episodes: int) -> float:
    """One-sided Welch p-value that the runs' mean SUC (%) is above the floor's (NaN with under two runs)."""
    x = np.asarray(br_suc, dtype=np.float64) / 100.0
    n = len(x)
    if n < 2 or floor_episodes < 1:
        return float("nan")
    p = floor_successes / floor_episodes
    var_br = float(x.var(ddof=1)) / n
    var_floor = p * (1 - p) / floor_episodes
    se = math.sqrt(var_br + var_floor)
    diff = float(x.mean()) - p
    if se == 0.0:
        return 0.0 if diff > 0 else 1.0
    parts = [v**2 / d for v, d in ((var_br, n - 1), (var_floor, floor_episodes - 1)) if v > 0 and d > 0]
    df = (var_br + var_floor) ** 2 / sum(parts) if parts else float(n - 1)
    return float(scipy.stats.t.sf(diff / se, df))


def make_bound(
    task: str, zoo: str, zoo_version: str, br_suc: Sequence[float], floor_successes: int, floor_episodes: int
) -> Bound:
    p_value = above_floor(br_suc, floor_successes, floor_episodes)
    usable = bool(np.isfinite(p_value) and p_value < ALPHA)
    return Bound(
        task, zoo, zoo_version, tuple(float(v) for v in br_suc), floor_successes, floor_episodes, p_value, usable
    )


def bounds_from_records(records: Iterable[Mapping[str, Any]], episodes: int) -> list[Bound]:
    """The bounds of a benchmark's finished ``br`` and ``floor`` cell records (``episodes`` per evaluation)."""
    br: dict[tuple[str, str], list[float]] = {}
    floor: dict[tuple[str, str], float] = {}
    versions: dict[tuple[str, str], str] = {}
    for r in records:
        cell = r["cell"]
        if cell["kind"] not in ("br", "floor"):
            continue
        key = (cell["task"], cell["zoo"])
        versions[key] = str(r.get("zoo_version", ""))
        suc = float(r["metrics"][cell["zoo"]]["SUC"])
        if cell["kind"] == "br":
            br.setdefault(key, []).append(suc)
        else:
            floor[key] = suc
    out = []
    for key in sorted(set(br) & set(floor)):
        successes = round(floor[key] * episodes / 100.0)
        out.append(make_bound(*key, versions[key], br[key], successes, episodes))
    return out


def write_bounds(bounds: Sequence[Bound], path: Path | None = None) -> Path:
    """Merge ``bounds`` into the bounds file (a (task, zoo) measured again replaces the old entry)."""
    path = path or repo_path(BOUNDS_FILE)
    doc: dict[str, Any] = json.loads(path.read_text()) if path.is_file() else {"alpha": ALPHA, "bounds": {}}
    for b in bounds:
        entry = asdict(b)
        entry.update(br_mean=b.br_mean, floor_suc=b.floor_suc)
        doc["bounds"].setdefault(b.task, {})[b.zoo] = entry
    atomic_write_bytes(path, (json.dumps(doc, indent=1, sort_keys=True) + "\n").encode())
    return path


def load_bounds(path: Path | None = None) -> dict[tuple[str, str], Bound]:
    """Every stored bound, keyed by (task, zoo)."""
    path = path or repo_path(BOUNDS_FILE)
    if not path.is_file():
        return {}
    doc = json.loads(path.read_text())
    fields = Bound.__dataclass_fields__
    out = {}
    for task, zoos in doc["bounds"].items():
        for zoo, entry in zoos.items():
            kept = {k: v for k, v in entry.items() if k in fields}
            kept["br_suc"] = tuple(kept["br_suc"])
            out[(task, zoo)] = Bound(**kept)
    return out


def usable_bound(task: str, zoo: str, path: Path | None = None) -> Bound | None:
    """The stored bound of (task, zoo) when it was measured with today's zoo version and is usable."""
    from atdrone.policies.manifest import task_version

    bound = load_bounds(path).get((task, zoo))
    if bound is None or not bound.usable or bound.zoo_version != task_version(task):
        return None
    return bound
