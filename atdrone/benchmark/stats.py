"""The statistics of a benchmark report: mean +- std over seeds, paired differences with t intervals,
and rliable-style aggregates (interquartile mean with stratified bootstrap intervals, probability of
improvement).

The aggregates follow Agarwal et al. (2021, the ``rliable`` package): a method's scores form a matrix of
runs (seeds) x tasks; the interquartile mean (IQM) is the mean of the middle 50 % of all its entries; a
stratified bootstrap resamples the runs of each task (column) independently with replacement; the
probability of improvement P(X > Y) is, per task, the Mann-Whitney probability that a run of X beats a run
of Y (ties count half), averaged over tasks. ``rliable`` itself is not used: its ``arch`` dependency
(pinned below 8.0, latest 7.2.0) fails at import under pandas 3, so these few functions are written here
with numpy and scipy and checked against plain loops in tests/test_benchmark_stats.py. Every bootstrap
draws from a passed-in seed, so a report is reproducible.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
import pandas as pd
import scipy.stats

CONFIDENCE = 0.95


def mean_std(values: pd.Series | np.ndarray) -> tuple[float, float]:
    """Mean and standard deviation (ddof 1; NaN for one value) of the finite ``values``."""
    x = np.asarray(values, dtype=np.float64)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan"), float("nan")
    return float(x.mean()), float(x.std(ddof=1)) if len(x) > 1 else float("nan")


def paired_difference(a: pd.DataFrame, b: pd.DataFrame, metrics: Sequence[str]) -> dict[str, Any] | None:
    """``a - b`` over the seeds both have (frames indexed by seed): per metric the mean difference, its
    standard error and the t-based 95 % confidence interval; None with fewer than two pairs."""
    paired = a[list(metrics)].sub(b[list(metrics)]).dropna(how="all")
    if len(paired) < 2:
        return None
    t = float(scipy.stats.t.ppf(0.5 + CONFIDENCE / 2, len(paired) - 1))
    out: dict[str, Any] = {"n": len(paired)}
    for m in metrics:
        d = paired[m].dropna()
        mean = float(d.mean())
        se = float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan")
        out[m] = {"diff": mean, "se": se, "ci95": [mean - t * se, mean + t * se]}
    return out


def iqm(scores: np.ndarray) -> float:
    """The interquartile mean of every entry of ``scores`` (the mean of the middle 50 %)."""
    return float(scipy.stats.trim_mean(np.asarray(scores, dtype=np.float64).ravel(), 0.25))


def mean_score(scores: np.ndarray) -> float:
    """The plain mean of every entry (beside the IQM, as rliable reports it)."""
    return float(np.mean(scores))


def stratified_resample(scores: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One stratified bootstrap sample of a runs x tasks matrix: each column's runs drawn with replacement."""
    runs, tasks = scores.shape
    rows = rng.integers(0, runs, size=(runs, tasks))
    return np.take_along_axis(scores, rows, axis=0)


def bootstrap_interval(
    scores: np.ndarray, statistic: Callable[[np.ndarray], float], reps: int, seed: int
) -> tuple[float, float, float]:
    """``statistic`` of ``scores`` (runs x tasks) and its percentile 95 % stratified bootstrap interval."""
    rng = np.random.default_rng(seed)
    draws = np.array([statistic(stratified_resample(scores, rng)) for _ in range(reps)])
    low, high = np.percentile(draws, [50 * (1 - CONFIDENCE), 50 * (1 + CONFIDENCE)])
    return statistic(scores), float(low), float(high)


def probability_of_improvement(x: np.ndarray, y: np.ndarray) -> float:
    """P(X > Y): per task (column) the share of run pairs where x beats y (ties half), averaged over tasks."""
    wins = (x[:, None, :] > y[None, :, :]).mean(axis=(0, 1))
    ties = (x[:, None, :] == y[None, :, :]).mean(axis=(0, 1))
    return float(np.mean(wins + 0.5 * ties))


def poi_interval(x: np.ndarray, y: np.ndarray, reps: int, seed: int) -> tuple[float, float, float]:
    """P(X > Y) and its 95 % interval, both matrices resampled by stratified bootstrap (independently)."""
    rng = np.random.default_rng(seed)
    draws = np.array(
        [probability_of_improvement(stratified_resample(x, rng), stratified_resample(y, rng)) for _ in range(reps)]
    )
    low, high = np.percentile(draws, [50 * (1 - CONFIDENCE), 50 * (1 + CONFIDENCE)])
    return probability_of_improvement(x, y), float(low), float(high)


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
