"""benchmarks/bounds_report.py: the bounds of the (task, zoo)s whose floor and every seed's best response are done,
with self-play beside them paired by seed (worked example)."""

from __future__ import annotations

from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def bounds_mod(load_script) -> ModuleType:
    return load_script(ROOT / "benchmarks" / "bounds_report.py")


def _record(kind: str, method: str, seed: int, zoo: str, suc: dict[str, float]) -> dict[str, Any]:
    cell = {"kind": kind, "method": method, "seed": seed, "task": "4p2e1o", "zoo": zoo}
    samples = {"br": 2048, "method": 4096}.get(kind, 0)
    return {
        "cell": cell,
        "metrics": {z: {"SUC": v} for z, v in suc.items()},
        "zoo_version": "zv-test",
        "budget": {"learner_samples": samples},
    }


def test_a_best_response_below_self_play_is_measured_by_seed_and_said(bounds_mod):
    config = {"seeds": [0, 1, 2], "eval_episodes": 500, "env_steps": 1000}
    records = [_record("floor", "floor", 0, "zoo1", {"zoo1": 1.0}), _record("floor", "floor", 0, "zoo2", {"zoo2": 2.0})]
    # zoo1: BR 60, 62, 64 against SP 70, 71, 75: BR - SP = -10, -9, -11 (mean -10, sd 1, t(2) = 4.3027)
    records += [_record("br", "br", s, "zoo1", {"zoo1": v}) for s, v in enumerate((60.0, 62.0, 64.0))]
    records += [_record("method", "sp", s, "", {"zoo1": v, "zoo2": 50.0}) for s, v in enumerate((70.0, 71.0, 75.0))]
    records.append(_record("br", "br", 0, "zoo2", {"zoo2": 90.0}))  # zoo2: one seed of three, no bound yet
    rows = bounds_mod.table(config, records, bounds_mod.bounds(config, records))
    assert [(r["task"], r["zoo"]) for r in rows] == [("4p2e1o", "zoo1")]
    row = rows[0]
    assert row["floor_suc"] == pytest.approx(1.0) and row["br_suc"] == [60.0, 62.0, 64.0] and row["usable"]
    half = 4.302653 / 3**0.5
    assert row["br_minus_sp"]["diff"] == pytest.approx(-10.0)
    assert row["br_minus_sp"]["ci95"] == pytest.approx([-10.0 - half, -10.0 + half], abs=1e-4)
    text = bounds_mod.markdown(config, rows, ROOT / "x")
    assert "| 4p2e1o | zoo1 | 1.0 | 62.0 ± 2.0 |" in text and "-10.0 [-12.5, -7.5]" in text
    assert "**The best response is below self-play** (4p2e1o zoo1" in text
    assert "(4p2e1o zoo1: 2,048 against 4,096)" in text
