"""The statistics of a benchmark report: mean +- std over seeds, paired differences with t intervals, and
the aggregates of ``rliable`` (Agarwal et al., 2021): interquartile mean (IQM) and mean with stratified
bootstrap intervals, performance profiles and the probability of improvement.

Scores arrive as one array per method of shape runs x tasks x zoos: a *run* is one (method, task, seed)
training run, evaluated on every test zoo. The aggregates and the profile are ``rliable``'s own functions
(``metrics.aggregate_iqm``, ``metrics.aggregate_mean``, ``metrics.probability_of_improvement``,
``library.score_distributions``; inside the probability of improvement's bootstrap the same count done
with numpy, :func:`pair_share`, checked equal to rliable's) and the intervals come from ``rliable``'s
bootstrap classes, with two changes made by subclassing them:

- **a run stays whole.** ``rliable``'s ``StratifiedBootstrap`` draws a run index for every entry of the
  array, so on a runs x tasks x zoos array it splits one run across its zoos, as if each (task, zoo) had
  its own runs; the zoos of one run share the learner and are correlated, so that interval is too narrow.
  Here each task's runs are drawn with replacement (the stratification) and a drawn run brings all its zoos.
- **the draws come from a passed-in seed.** ``rliable`` 1.2.0 draws from numpy's global random state
  (``np.random.choice``) whatever ``random_state`` it is given (two calls with the same ``RandomState``
  give different intervals); here they come from the bootstrap's ``numpy.random.Generator`` (arch's
  ``seed``), so a report is reproducible.

Why the import goes through :func:`rliable_modules`: ``rliable`` 1.2.0 (the latest release) requires
``arch >=5.3.1,<8.0``. arch 7.2.0, the latest below 8, fails at import under pandas 3: its
``arch/univariate/base.py`` decorates a method with pandas' private ``deprecate_kwarg("type",
"plot_type")``, whose pandas 3 signature gained a leading warning class (``TypeError: deprecate_kwarg()
missing 1 required positional argument: 'new_arg_name'``); ``import arch.bootstrap`` runs that module
through ``arch/__init__``. arch 8.0.0 has no such call but removed the ``random_state`` keyword, and
``rliable`` passes ``random_state=`` to every arch bootstrap (even an explicit ``RandomState``), which arch 8
then refuses as data ("Input `random_state` has type ..."); and pip cannot install arch 8 beside
``rliable`` at all (its pin says ``<8.0``; a constraints file only narrows, it cannot override). So the
project installs ``rliable`` 1.2.0 with arch 7.2.0 (constraints.txt) and, only while importing it, gives
pandas' ``deprecate_kwarg`` the pre-3 call form (the old call ``(old, new)`` becomes ``(FutureWarning, old,
new)``); pandas is left as it was after the import, and under pandas 2 nothing is changed. The bootstrap
path (``arch.bootstrap``) never calls the decorated method. tests/test_benchmark_stats.py checks the
import, the subclasses against plain loops, and the hand computations of the t intervals.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np
import pandas as pd
import scipy.stats

CONFIDENCE = 0.95
PROFILE_TAUS = np.linspace(0.0, 1.0, 21)  # thresholds of a performance profile of scores in [0, 1]


# ------------------------------------------------------------------ over seeds
def mean_std(values: pd.Series | np.ndarray) -> tuple[float, float]:
    """Mean and standard deviation (ddof 1; NaN for one value) of the finite ``values``."""
    x = np.asarray(values, dtype=np.float64)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan"), float("nan")
    return float(x.mean()), float(x.std(ddof=1)) if len(x) > 1 else float("nan")


def over_seeds(values: Sequence[float] | np.ndarray) -> str:
    """``mean ± std`` (ddof 1) of the finite ``values`` to one decimal; ``x (1 seed)`` for one; ``-`` for none."""
    mean, std = mean_std(np.asarray(values, dtype=np.float64))
    n = int(np.isfinite(np.asarray(values, dtype=np.float64)).sum())
    if n == 0:
        return "-"
    return f"{mean:.1f} (1 seed)" if n == 1 else f"{mean:.1f} ± {std:.1f}"


def t_interval(diffs: Sequence[float] | np.ndarray) -> dict[str, Any]:
    """Mean of the finite ``diffs``, its standard error and the t-based 95 % interval with n - 1 degrees of
    freedom, n the values used (NaN where fewer than two)."""
    d = np.asarray(diffs, dtype=np.float64)
    d = d[np.isfinite(d)]
    n = len(d)
    mean = float(d.mean()) if n else float("nan")
    if n < 2:
        return {"diff": mean, "se": float("nan"), "ci95": [float("nan"), float("nan")], "n": n}
    se = float(d.std(ddof=1) / np.sqrt(n))
    t = float(scipy.stats.t.ppf(0.5 + CONFIDENCE / 2, n - 1))
    return {"diff": mean, "se": se, "ci95": [mean - t * se, mean + t * se], "n": n}


def paired_difference(a: pd.DataFrame, b: pd.DataFrame, metrics: Sequence[str]) -> dict[str, Any] | None:
    """``a - b`` over the seeds both have (frames indexed by seed): per metric the mean difference, its
    standard error, the t-based 95 % interval and ``n``, the seeds where both values exist (AST is missing for
    a seed without a success): the degrees of freedom are that ``n`` - 1. ``n`` at the top: the seeds paired.
    None with fewer than two pairs."""
    paired = a[list(metrics)].sub(b[list(metrics)]).dropna(how="all")
    if len(paired) < 2:
        return None
    out: dict[str, Any] = {"n": len(paired)}
    for m in metrics:
        out[m] = t_interval(paired[m].to_numpy(np.float64))
    return out


# ------------------------------------------------------------------ rliable
def _pre3_deprecate_kwarg(original: Callable[..., Any]) -> Callable[..., Any]:
    """pandas 3's ``deprecate_kwarg(klass, old, new)`` also callable as before pandas 3: ``(old, new)``."""

    def deprecate_kwarg(*args: Any, **kwargs: Any) -> Any:
        if args and isinstance(args[0], str):
            return original(FutureWarning, *args, **kwargs)
        return original(*args, **kwargs)

    return deprecate_kwarg


@functools.cache
def rliable_modules() -> tuple[Any, Any]:
    """``rliable.library`` and ``rliable.metrics``, imported under pandas 3 (see the module docstring)."""
    import pandas.util._decorators as decorators

    original = decorators.deprecate_kwarg
    pandas3 = next(iter(inspect.signature(original).parameters)) == "klass"
    if pandas3:
        decorators.deprecate_kwarg = _pre3_deprecate_kwarg(original)
    try:
        from rliable import library, metrics
    finally:
        decorators.deprecate_kwarg = original
    return library, metrics


def _whole_runs(shape: tuple[int, ...], generator: np.random.Generator) -> np.ndarray:
    """Run indices for a runs x tasks x ... array: per task, runs drawn with replacement, one draw per run for
    all its later axes (zoos): shape (runs, tasks, 1, ...), broadcast against rliable's strata indices."""
    return generator.integers(0, shape[0], size=(shape[0], shape[1], *([1] * (len(shape) - 2))))


@functools.cache
def _bootstraps() -> tuple[type, type]:
    """rliable's two bootstrap classes with whole runs and seeded draws (the module docstring)."""
    library, _ = rliable_modules()

    class RunBootstrap(library.StratifiedBootstrap):  # type: ignore[misc,name-defined]
        """rliable's stratified bootstrap of one runs x tasks x zoos array; a run stays whole."""

        def __init__(self, scores: np.ndarray, seed: int) -> None:
            super().__init__(scores, seed=np.random.default_rng(seed))

        def update_indices(self) -> tuple[np.ndarray, ...]:
            return (_whole_runs(self._args_shape, self.generator), *self._strata_indices)

    class IndependentRunBootstrap(library.StratifiedIndependentBootstrap):  # type: ignore[misc,name-defined]
        """rliable's stratified bootstrap of several methods' arrays, each resampled on its own; runs whole."""

        def __init__(self, *scores: np.ndarray, seed: int) -> None:
            super().__init__(*scores, seed=np.random.default_rng(seed))

        def _get_indices(
            self, num_runs: int, array_shape: tuple[int, ...], strata_indices: list[np.ndarray]
        ) -> tuple[np.ndarray, ...]:
            return (_whole_runs(array_shape, self.generator), *strata_indices)

    return RunBootstrap, IndependentRunBootstrap


def _runs_by_cells(scores: np.ndarray) -> np.ndarray:
    """A runs x tasks x zoos array as rliable's runs x "tasks" matrix, every (task, zoo) a column."""
    return np.asarray(scores, dtype=np.float64).reshape(scores.shape[0], -1)


def iqm(scores: np.ndarray) -> float:
    """rliable's interquartile mean of every entry (the mean of the middle 50 %)."""
    return float(rliable_modules()[1].aggregate_iqm(np.asarray(scores, dtype=np.float64)))


def mean_score(scores: np.ndarray) -> float:
    """rliable's mean of the per-(task, zoo) means over runs."""
    return float(rliable_modules()[1].aggregate_mean(_runs_by_cells(scores)))


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> float:
    """rliable's P(X > Y): per (task, zoo) the Mann-Whitney share of run pairs where x beats y (ties half),
    averaged over the (task, zoo) columns."""
    return float(rliable_modules()[1].probability_of_improvement(_runs_by_cells(x), _runs_by_cells(y)))


def pair_share(x: np.ndarray, y: np.ndarray) -> float:
    """The same P(X > Y) counted over all run pairs at once (numpy): what each bootstrap resample computes.
    rliable's function calls scipy's Mann-Whitney test once per column, 72.6 s for 2,000 resamples of one
    pair of 3 x 4 x 3 arrays (on the project's 2-core machine); a paper-budget report has 28 such pairs.
    tests/test_benchmark_stats.py checks it equals rliable's on random inputs with ties."""
    a, b = _runs_by_cells(x), _runs_by_cells(y)
    wins = (a[:, None, :] > b[None, :, :]).mean(axis=(0, 1))
    ties = (a[:, None, :] == b[None, :, :]).mean(axis=(0, 1))
    return float(np.mean(wins + 0.5 * ties))


def performance_profile(scores: np.ndarray, taus: np.ndarray = PROFILE_TAUS) -> np.ndarray:
    """rliable's score distribution: per threshold tau, the share of all (run, task, zoo) scores above tau."""
    return np.asarray(rliable_modules()[0].score_distributions(np.asarray(scores, dtype=np.float64), taus))


def _interval(bootstrap: Any, func: Callable[..., Any], reps: int) -> np.ndarray:
    return np.asarray(bootstrap.conf_int(func, reps=reps, size=CONFIDENCE, method="percentile"))


def bootstrap_interval(
    scores: np.ndarray, statistic: Callable[[np.ndarray], float], reps: int, seed: int
) -> tuple[float, float, float]:
    """``statistic`` of ``scores`` (runs x tasks x zoos) and its percentile 95 % interval by the stratified
    bootstrap over whole runs (``reps`` resamples drawn from ``seed``)."""
    run_bootstrap, _ = _bootstraps()
    scores = np.asarray(scores, dtype=np.float64)
    ci = _interval(run_bootstrap(scores, seed), lambda s: np.array([statistic(s)]), reps)
    return float(statistic(scores)), float(ci[0, 0]), float(ci[1, 0])


def poi_interval(x: np.ndarray, y: np.ndarray, reps: int, seed: int) -> tuple[float, float, float]:
    """rliable's P(X > Y) and its percentile 95 % interval, each method's runs resampled on their own (whole
    runs) by rliable's independent bootstrap, each resample's P(X > Y) by :func:`pair_share`."""
    _, independent = _bootstraps()
    x, y = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    ci = _interval(independent(x, y, seed=seed), lambda a, b: np.array([pair_share(a, b)]), reps)
    return probability_of_improvement(x, y), float(ci[0, 0]), float(ci[1, 0])


def profile_interval(
    scores: np.ndarray, reps: int, seed: int, taus: np.ndarray = PROFILE_TAUS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The performance profile at ``taus`` and its pointwise percentile 95 % band (whole runs resampled)."""
    run_bootstrap, _ = _bootstraps()
    scores = np.asarray(scores, dtype=np.float64)
    ci = _interval(run_bootstrap(scores, seed), lambda s: performance_profile(s, taus), reps)
    return performance_profile(scores, taus), ci[0], ci[1]


def aggregate_intervals(
    score_dict: Mapping[str, np.ndarray], reps: int, seed: int
) -> dict[str, dict[str, tuple[float, float, float]]]:
    """Per method: IQM and mean, each with its interval (value, low, high); method i's bootstraps draw from
    ``seed + 2 i`` (IQM) and ``seed + 2 i + 1`` (mean)."""
    out: dict[str, dict[str, tuple[float, float, float]]] = {}
    for i, (method, x) in enumerate(score_dict.items()):
        out[method] = {
            "IQM": bootstrap_interval(x, iqm, reps, seed + 2 * i),
            "mean": bootstrap_interval(x, mean_score, reps, seed + 2 * i + 1),
        }
    return out


# ------------------------------------------------------------------ scales and tables
def normalise(score: np.ndarray | float, floor: float, ceiling: float) -> np.ndarray | float:
    """``(score - floor) / (ceiling - floor)``: 0 at the floor, 1 at the best response; NaN when the best
    response does not beat the floor (no scale to measure against)."""
    if not np.isfinite(floor) or not np.isfinite(ceiling) or ceiling <= floor:
        return np.full_like(np.asarray(score, dtype=np.float64), np.nan) if np.ndim(score) else float("nan")
    return (score - floor) / (ceiling - floor)


def md_table(frame: pd.DataFrame) -> str:
    """A Markdown table of a frame, its index as the first columns."""
    flat = frame.reset_index()
    rows = ["| " + " | ".join(map(str, flat.columns)) + " |", "|---" * len(flat.columns) + "|"]
    rows += ["| " + " | ".join(str(v) for v in row) + " |" for row in flat.itertuples(index=False)]
    return "\n".join(rows)
