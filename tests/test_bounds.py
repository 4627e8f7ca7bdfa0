"""The bounds of the normalised scores: a best response significantly above the floor is usable, one that is
not is kept and marked; bounds are kept with their zoo version and answer only for today's."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import scipy.stats

from atdrone.benchmark.bounds import (
    above_floor,
    bounds_from_records,
    load_bounds,
    make_bound,
    usable_bound,
    write_bounds,
)
from atdrone.policies.manifest import task_version


def test_the_p_value_is_welchs_one_sided_test_worked_by_hand() -> None:
    # runs 40, 50, 60 % (mean 0.5, var 0.01, /3); floor 10 of 100 (p 0.1, var 0.0009)
    var_br, var_floor = 0.01 / 3, 0.1 * 0.9 / 100
    se = math.sqrt(var_br + var_floor)
    df = (var_br + var_floor) ** 2 / (var_br**2 / 2 + var_floor**2 / 99)
    expected = scipy.stats.t.sf((0.5 - 0.1) / se, df)
    assert above_floor([40.0, 50.0, 60.0], 10, 100) == pytest.approx(expected, rel=1e-12)
    assert math.isnan(above_floor([50.0], 10, 100))  # one run: no test


def test_a_best_response_within_noise_of_the_floor_is_marked_and_normalises_nothing() -> None:
    weak = make_bound("4p2e1o", "zoo1", "zv-x", [12.0, 30.0, 3.0], 30, 200)  # mean 15 against a 15 % floor
    assert not weak.usable and math.isnan(weak.normalise(20.0))
    strong = make_bound("4p2e1o", "zoo1", "zv-x", [60.0, 62.0, 58.0], 30, 200)
    assert strong.usable and strong.normalise(37.5) == pytest.approx(0.5)


def test_bounds_from_cells_are_stored_with_their_zoo_version_and_answer_only_for_it(tmp_path: Path) -> None:
    version = task_version("4p2e1o")
    records = [
        {
            "cell": {"kind": "br", "task": "4p2e1o", "zoo": "zoo1"},
            "zoo_version": version,
            "metrics": {"zoo1": {"SUC": s}},
        }
        for s in (60.0, 64.0, 62.0)
    ] + [
        {
            "cell": {"kind": "floor", "task": "4p2e1o", "zoo": "zoo1"},
            "zoo_version": version,
            "metrics": {"zoo1": {"SUC": 6.0}},
        }
    ]
    (bound,) = bounds_from_records(records, episodes=500)
    assert bound.floor_successes == 30 and bound.br_suc == (60.0, 64.0, 62.0) and bound.usable
    path = write_bounds([bound], tmp_path / "bounds.json")
    assert load_bounds(path)[("4p2e1o", "zoo1")] == bound
    assert usable_bound("4p2e1o", "zoo1", path) == bound
    old = make_bound("4p2e1o", "zoo2", "zv-older", [60.0, 64.0, 62.0], 30, 500)
    write_bounds([old], path)
    assert usable_bound("4p2e1o", "zoo2", path) is None  # measured with other partners
    assert usable_bound("4p2e1o", "zoo1", path) == bound  # merged, not replaced
    assert np.isfinite(load_bounds(path)[("4p2e1o", "zoo2")].p_value)
