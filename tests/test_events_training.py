"""benchmarks/events_training.py's report: what a team change costs each recipe, and the part of the gain that
is the events', paired by seed (worked example)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def events_mod(load_script) -> ModuleType:
    return load_script(ROOT / "benchmarks" / "events_training.py")


def test_the_events_part_of_the_gain_is_the_difference_of_the_paired_costs_of_a_change(events_mod):
    # SUC on zoo3 / zoo3+drop per seed 0-2: without 40/30, 42/34, 41/32 (costs -10, -8, -9);
    # with 55/52, 57/51, 53/50 (costs -3, -6, -3); difference +7, +2, +6: mean 5, sd 2.646, t(2) 4.303
    suc = {
        ("without", "zoo3"): (40.0, 42.0, 41.0),
        ("without", "zoo3+drop"): (30.0, 34.0, 32.0),
        ("with", "zoo3"): (55.0, 57.0, 53.0),
        ("with", "zoo3+drop"): (52.0, 51.0, 50.0),
    }
    cells = {f"{v}|{s}|{p}": {"SUC": values[s]} for (v, p), values in suc.items() for s in range(3)}
    doc: dict = {}
    lines = events_mod._loss_rows(cells, [0, 1, 2], doc)
    drop = doc["loss"]["zoo3+drop"]
    assert drop["without"]["diff"] == pytest.approx(-9.0) and drop["with"]["diff"] == pytest.approx(-4.0)
    half = 4.302653 * 2.6457513 / 3**0.5
    assert drop["difference"]["diff"] == pytest.approx(5.0)
    assert drop["difference"]["ci95"] == pytest.approx([5.0 - half, 5.0 + half], abs=1e-4)
    assert "| zoo3+drop | -9.0 [" in "\n".join(lines)
    assert doc["loss"]["zoo3+swap"]["difference"]["n"] == 0  # no swap cells: nothing measured, nothing claimed
    assert "| zoo3+swap | - | - | - |" in lines
