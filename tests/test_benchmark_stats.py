"""The benchmark's statistics: t intervals worked by hand, rliable's aggregates with whole runs against plain
loops, and the performance profile on a worked example."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from atdrone.benchmark import stats

T_975_DF2 = 4.302652729749464  # Student t, 97.5th percentile, 2 degrees of freedom (printed tables: 4.303)


def test_rliable_imports_under_pandas_3_and_leaves_pandas_as_it_was() -> None:
    import pandas.util._decorators as decorators

    before = decorators.deprecate_kwarg
    library, metrics = stats.rliable_modules()
    assert decorators.deprecate_kwarg is before
    assert library.__name__ == "rliable.library" and metrics.__name__ == "rliable.metrics"


def test_the_ast_interval_takes_its_degrees_of_freedom_from_the_seeds_with_a_success() -> None:
    """Seed 1 of ``a`` had no success (AST missing): three of the four seeds pair, so t has 2 degrees of
    freedom, not 3 (the number of seeds)."""
    a = pd.DataFrame({"SUC": [40.0, 0.0, 30.0, 50.0], "AST": [300.0, np.nan, 280.0, 320.0]})
    b = pd.DataFrame({"SUC": [35.0, 10.0, 30.0, 40.0], "AST": [310.0, 305.0, 300.0, 330.0]})
    d = stats.paired_difference(a, b, ["SUC", "AST"])
    assert d is not None and d["n"] == 4
    # by hand: differences -10, -20, -10; mean -13.333; sd 5.7735; se 5.7735 / sqrt 3 = 3.3333
    ast = d["AST"]
    assert ast["n"] == 3
    assert ast["diff"] == pytest.approx(-40.0 / 3)
    assert ast["se"] == pytest.approx(10.0 / 3)
    half = T_975_DF2 * 10.0 / 3  # 14.342
    assert ast["ci95"] == pytest.approx([-40.0 / 3 - half, -40.0 / 3 + half])
    assert d["SUC"]["n"] == 4  # SUC pairs on every seed: 3 degrees of freedom there


def test_a_paired_metric_with_one_value_has_no_interval() -> None:
    a = pd.DataFrame({"SUC": [10.0, 0.0, 0.0], "AST": [300.0, np.nan, np.nan]})
    b = pd.DataFrame({"SUC": [20.0, 5.0, 0.0], "AST": [310.0, 305.0, 300.0]})
    d = stats.paired_difference(a, b, ["SUC", "AST"])
    assert d is not None and d["AST"]["n"] == 1 and np.isnan(d["AST"]["ci95"]).all()


def test_iqm_is_the_mean_of_the_middle_half() -> None:
    x = np.arange(1.0, 9.0).reshape(4, 2, 1)  # 1..8: the middle half is 3..6
    assert stats.iqm(x) == pytest.approx(4.5)


def test_probability_of_improvement_counts_run_pairs_per_task_and_zoo_ties_half() -> None:
    rng = np.random.default_rng(3)
    x, y = rng.integers(0, 3, (4, 2, 3)).astype(float), rng.integers(0, 3, (5, 2, 3)).astype(float)
    per_cell = []
    for t in range(2):
        for z in range(3):
            wins = sum((a > b) + 0.5 * (a == b) for a in x[:, t, z] for b in y[:, t, z])
            per_cell.append(wins / (len(x) * len(y)))
    assert stats.probability_of_improvement(x, y) == pytest.approx(np.mean(per_cell))


def test_the_bootstraps_pair_share_equals_rliables_probability_of_improvement() -> None:
    rng = np.random.default_rng(8)
    for _ in range(20):
        runs_x, runs_y, tasks, zoos = rng.integers(2, 6, 4)
        x = rng.integers(0, 4, (runs_x, tasks, zoos)).astype(float)  # few values: many ties
        y = rng.integers(0, 4, (runs_y, tasks, zoos)).astype(float)
        assert stats.pair_share(x, y) == pytest.approx(stats.probability_of_improvement(x, y))
    same = rng.random((3, 2, 2))
    assert stats.pair_share(same, same) == stats.probability_of_improvement(same, same) == 0.5


def test_a_bootstrap_resample_draws_runs_per_task_and_keeps_each_run_whole() -> None:
    runs, tasks, zoos = 5, 3, 4
    x = np.arange(runs * tasks * zoos, dtype=np.float64).reshape(runs, tasks, zoos)
    run_bootstrap, _ = stats._bootstraps()
    bs = run_bootstrap(x, seed=0)
    drawn_runs = set()
    for (sample,), _ in bs.bootstrap(20):
        for t in range(tasks):
            for row in sample[:, t, :]:  # every resampled row is one original run's zoos, in order
                matches = [r for r in range(runs) if np.array_equal(row, x[r, t, :])]
                assert len(matches) == 1
                drawn_runs.add((t, matches[0]))
    assert len(drawn_runs) == runs * tasks  # runs of every task are drawn
    assert stats.bootstrap_interval(x, stats.iqm, 200, seed=1) == stats.bootstrap_interval(x, stats.iqm, 200, seed=1)


def _plain_interval(x: np.ndarray, whole: bool, reps: int, seed: int) -> tuple[float, float]:
    """The percentile 95 % interval of the mean by a plain loop: whole runs per task, or each (task, zoo)
    cell's runs drawn on their own."""
    rng = np.random.default_rng(seed)
    runs, tasks, zoos = x.shape
    draws = []
    for _ in range(reps):
        sample = np.empty_like(x)
        for t in range(tasks):
            if whole:
                sample[:, t, :] = x[rng.integers(0, runs, runs), t, :]
            else:
                for z in range(zoos):
                    sample[:, t, z] = x[rng.integers(0, runs, runs), t, z]
        draws.append(sample.mean())
    low, high = np.percentile(draws, [2.5, 97.5])
    return float(low), float(high)


def test_a_planted_run_level_effect_widens_the_interval_by_the_root_of_the_zoos() -> None:
    """Each run carries one effect on all its zoos (sd 1, zoo noise sd 0.01): the zoos of a run are one
    observation, not four. Resampling whole runs gives an interval about sqrt(4) = 2 times as wide as
    resampling each (task, zoo) cell's runs on its own, and matches a plain loop of whole-run draws."""
    rng = np.random.default_rng(7)
    runs, tasks, zoos = 10, 2, 4
    x = rng.normal(0.0, 1.0, (runs, tasks, 1)) + rng.normal(0.0, 0.01, (runs, tasks, zoos))
    mean = lambda s: float(s.mean())
    _, low, high = stats.bootstrap_interval(x, mean, 4000, seed=0)
    whole_low, whole_high = _plain_interval(x, whole=True, reps=4000, seed=1)
    cell_low, cell_high = _plain_interval(x, whole=False, reps=4000, seed=2)
    width, whole_width, cell_width = high - low, whole_high - whole_low, cell_high - cell_low
    assert width == pytest.approx(whole_width, rel=0.1)
    assert 1.7 < width / cell_width < 2.3


def test_the_probability_of_improvement_interval_resamples_whole_runs() -> None:
    """Two methods whose runs differ by a run-level effect only: the interval of P(X > Y) with whole runs is
    wider than with each cell's runs drawn on their own (rliable's own class, draws seeded globally here)."""
    rng = np.random.default_rng(11)
    x = rng.normal(0.3, 1.0, (8, 2, 1)) + rng.normal(0.0, 0.01, (8, 2, 4))
    y = rng.normal(0.0, 1.0, (8, 2, 1)) + rng.normal(0.0, 0.01, (8, 2, 4))
    value, low, high = stats.poi_interval(x, y, 600, seed=3)
    assert low <= value <= high
    library, _ = stats.rliable_modules()
    state = np.random.get_state()
    try:
        np.random.seed(4)  # rliable 1.2.0 draws from the global state
        split = library.StratifiedIndependentBootstrap(x, y).conf_int(
            lambda a, b: np.array([stats.pair_share(a, b)]), reps=600, method="percentile"
        )
    finally:
        np.random.set_state(state)
    assert (high - low) > 1.4 * float(split[1, 0] - split[0, 0])


def test_the_performance_profile_on_a_worked_example() -> None:
    """Two runs x one task x two zoos: scores 0.1, 0.6 / 0.4, 0.9. Above tau = 0: all four; 0.5: 0.6 and
    0.9 (one half); 0.95: none; the band holds the profile, and with one run repeated it is a point."""
    x = np.array([[[0.1, 0.6]], [[0.4, 0.9]]])
    taus = np.array([0.0, 0.5, 0.95])
    assert stats.performance_profile(x, taus) == pytest.approx([1.0, 0.5, 0.0])
    profile, low, high = stats.profile_interval(x, 300, seed=0, taus=taus)
    assert profile == pytest.approx([1.0, 0.5, 0.0])
    assert (low <= profile).all() and (profile <= high).all()
    assert low[1] == pytest.approx(0.5) and high[1] == pytest.approx(0.5)  # each run has one of two above 0.5
    same = np.array([[[0.1, 0.6]], [[0.1, 0.6]]])
    _, low, high = stats.profile_interval(same, 100, seed=0, taus=taus)
    assert low == pytest.approx(high)


def test_aggregate_intervals_hold_iqm_and_mean_per_method() -> None:
    rng = np.random.default_rng(5)
    scores = {"a": rng.random((4, 2, 3)), "b": rng.random((4, 2, 3)) + 1.0}
    out = stats.aggregate_intervals(scores, 300, seed=0)
    for method, x in scores.items():
        iqm, low, high = out[method]["IQM"]
        assert iqm == pytest.approx(stats.iqm(x)) and low <= iqm <= high
        assert out[method]["mean"][0] == pytest.approx(x.mean())
    assert out["b"]["IQM"][1] > out["a"]["IQM"][2]  # b is a whole point higher


@pytest.mark.filterwarnings("ignore:random_state is deprecated:FutureWarning")  # arch 7, on rliable's call
def test_rliables_own_interval_ignores_its_random_state_and_ours_does_not() -> None:
    """Why the bootstraps are subclassed: rliable 1.2.0 draws from numpy's global state, so two calls with the
    same RandomState differ; ours, given one seed, repeat exactly."""
    library, metrics = stats.rliable_modules()
    x = np.random.default_rng(2).random((5, 3))
    iqm = lambda s: np.array([metrics.aggregate_iqm(s)])
    state = np.random.get_state()
    try:
        _, first = library.get_interval_estimates({"a": x}, iqm, reps=300, random_state=np.random.RandomState(0))
        _, second = library.get_interval_estimates({"a": x}, iqm, reps=300, random_state=np.random.RandomState(0))
    finally:
        np.random.set_state(state)
    assert not np.array_equal(first["a"], second["a"])
    assert stats.bootstrap_interval(x, stats.iqm, 300, seed=0) == stats.bootstrap_interval(x, stats.iqm, 300, seed=0)
