"""benchmarks/protocol_report.py's statistics: the SUC a team change costs, paired by training seed, and which
method loses least, checked on planted cells against hand computations."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def report_mod(load_script) -> ModuleType:
    return load_script(ROOT / "benchmarks" / "protocol_report.py")


def _cell(label: str, seed: int, zoo3: float, after: float) -> dict[str, Any]:
    protocols = {"zoo3": {"SUC": zoo3, "REC": float("nan")}}
    protocols.update(
        {p: {"SUC": after, "SUC_post": after, "REC": 40.0} for p in ("zoo3+swap", "zoo3+drop", "zoo3+drop+join")}
    )
    return {
        "learner": label,
        "task": "4p2e5o",
        "seed": seed,
        "protocols": protocols,
        "splits": {"1": {"SUC": 50.0}},
        "sizes": {"6p2e1o": {"SUC": 30.0}},
    }


def test_the_cost_of_a_change_is_paired_by_seed_and_the_least_loss_needs_an_interval_below_zero(report_mod):
    # A loses 10, 12, 11 points on seeds 0-2; B loses 2, 3, 2; C loses 9, 1, 5 (B - C: -7, +2, -3)
    cells = [_cell("A", s, 60.0 + s, 60.0 + s - lost) for s, lost in enumerate((10.0, 12.0, 11.0))]
    cells += [_cell("B", s, 50.0, 50.0 - lost) for s, lost in enumerate((2.0, 3.0, 2.0))]
    cells += [_cell("C", s, 40.0, 40.0 - lost) for s, lost in enumerate((9.0, 1.0, 5.0))]
    summary = report_mod.summarise(cells)
    a = summary["learners"]["A|4p2e5o"]["loss"]["zoo3+drop"]
    assert a["per_seed"] == [10.0, 12.0, 11.0]
    mean, _, high = a["t95"]
    # mean 11, sd 1, t(0.975, 2) = 4.3027: half-width 4.3027 / sqrt(3) = 2.4841
    assert mean == pytest.approx(11.0) and high - mean == pytest.approx(2.4841, abs=1e-4)
    least = summary["least_loss"]["4p2e5o|zoo3+drop"]
    assert least["method"] == "B"
    assert least["versus"]["A"]["verdict"] == "less" and least["versus"]["A"]["diff_t95"][2] < 0
    # against C: differences -7, +2, -3, mean -8/3, sd sqrt(61/3) = 4.5092, half-width 11.20: undecided
    diff = least["versus"]["C"]["diff_t95"]
    assert diff[0] == pytest.approx(-8 / 3) and least["versus"]["C"]["verdict"] == "undecided"
    assert diff[2] - diff[0] == pytest.approx(4.3027 * 4.5092 / 3**0.5, abs=1e-3)
    md = report_mod.markdown(summary, 500, 100)
    assert "| 4p2e5o | zoo3+drop | B | A: -8.7" in md
    # A's SUC after the event: 50, 49, 51 (mean 50, sd 1, half-width 2.4841); REC 40 on every seed
    assert "| A | 4p2e5o | 50.0 [47.5, 52.5] | 50.0 [47.5, 52.5] | 50.0 [47.5, 52.5] | 40.0 [40.0, 40.0] |" in md


def test_the_report_names_the_build_its_cells_were_played_with_and_warns_when_they_mix(report_mod):
    one = [{**_cell("A", s, 60.0, 50.0), "build": "python 3.12.3, numpy 2.3.5, torch 2.13.0"} for s in (0, 1)]
    md = report_mod.markdown(report_mod.summarise(one), 500, 100)
    assert "Every cell was played with python 3.12.3, numpy 2.3.5, torch 2.13.0." in md
    mixed = [*one, {**_cell("A", 2, 60.0, 50.0), "build": "python 3.11.9, numpy 2.5.2, torch 2.11.0"}]
    md = report_mod.markdown(report_mod.summarise(mixed), 500, 100)
    assert "**The cells come from 2 builds**" in md and "numpy 2.5.2" in md
    assert "Every cell" not in md


def test_one_learner_on_two_builds_is_compared_number_by_number(load_script):
    cross = load_script(ROOT / "benchmarks" / "protocol_cross_build.py")
    a = {"policy": "p", "task": "4p2e5o", "seed": 0, "episodes": 500, "build": "one", **_cell("sp", 0, 60.0, 50.0)}
    b = {**a, "build": "two", "protocols": {k: dict(v) for k, v in a["protocols"].items()}}
    b["protocols"]["zoo3+drop"]["SUC"] = 52.5  # only this SUC moves: +2.5, so the drop costs 7.5 on B
    b["sizes"] = {"6p2e1o": {"SUC": 29.0}}  # and a size: -1.0
    found = cross.compare(a, b)
    assert found["builds"] == {"A": "one", "B": "two"}
    # SUC numbers: 4 protocols, 1 split, 1 size; mean of (0, 0, +2.5, 0, 0, -1) = 0.25
    assert found["SUC_difference"] == {"numbers": 6, "mean": 0.25, "max_abs": 2.5, "unchanged": 4}
    assert found["protocol_cost"]["A"] == {"zoo3+swap": 10.0, "zoo3+drop": 10.0, "zoo3+drop+join": 10.0}
    assert found["protocol_cost"]["B"]["zoo3+drop"] == 7.5
    assert found["metrics"]["protocols/zoo3+drop/SUC"] == {"A": 50.0, "B": 52.5, "B-A": 2.5}
    with pytest.raises(SystemExit, match="seed"):
        cross.compare(a, {**b, "seed": 1})
