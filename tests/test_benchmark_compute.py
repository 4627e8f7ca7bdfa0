"""The compute table of the benchmark report: a cell that sat out a pause of its machine is counted as measured
and marked, and the totals also give what the grid would have cost without its stalls."""

from __future__ import annotations

from types import SimpleNamespace
from typing import Any

from atdrone.benchmark.cells import Cell, cell_cpu, experiment
from atdrone.benchmark.config import parse_benchmark
from atdrone.benchmark.report import budget
from atdrone.benchmark.report_text import BUDGET_KEYS


def _record(method: str, task: str, seed: int, wall: float) -> dict[str, Any]:
    spent = dict.fromkeys(BUDGET_KEYS, 1000)
    timing = {"train_wall_s": wall - 10.0, "eval_wall_s": 10.0, "wall_s": wall, "cpu_s": 2 * wall}
    return {"cell": {"method": method, "task": task}, "name": f"{method}-{task}-s{seed}", "budget": spent,
            "timing": timing}  # fmt: skip


def test_a_cell_over_twice_its_methods_median_wall_time_is_marked_stalled_and_counted_at_the_median() -> None:
    # sp: 300, 360, 330 on 4p2e1o and 340, 1500 on 4p2e5o; the method's median is 340 s, so only the 1,500 s cell
    # (over 680 s) stalled; hola has two cells: no median one stall cannot move, nothing marked
    records = [
        *(_record("sp", "4p2e1o", s, w) for s, w in enumerate((300.0, 360.0, 330.0))),
        *(_record("sp", "4p2e5o", s, w) for s, w in enumerate((340.0, 1500.0))),
        *(_record("hola", "4p2e5o", s, w) for s, w in enumerate((450.0, 2000.0))),
    ]
    table, timing = budget(SimpleNamespace(methods=["sp", "hola"]), records)  # type: ignore[arg-type]
    rows = table.set_index(["method", "task"])
    assert rows.loc[("sp", "4p2e1o"), "stalled"] == 0 and rows.loc[("sp", "4p2e5o"), "stalled"] == 1
    assert rows.loc[("hola", "4p2e5o"), "stalled"] == 0
    assert rows.loc[("sp", "4p2e5o"), "wall_s"] == 920.0  # measured: (340 + 1,500) / 2
    assert rows.loc[("sp", "4p2e5o"), "wall_median_s"] == 920.0
    assert rows.loc[("sp", "4p2e5o"), "steady_wall_s"] == 340.0  # the stalled cell at the median: (340 + 340) / 2
    assert rows.loc[("hola", "4p2e5o"), "steady_wall_s"] == 1225.0
    assert list(timing.loc[timing["stalled"], "cell"]) == ["sp-4p2e5o-s1"]
    assert timing.set_index("cell").loc["sp-4p2e5o-s1", "cell_wall_s"] == 1500.0  # generations + evaluation


def test_a_resumed_cell_counts_its_earlier_attempts_generations_at_one_cpu_per_rollout_worker() -> None:
    # last attempt: 50 s of wall time, 130 CPU-s; its generations over both attempts 990 s and its evaluation 10 s,
    # so the first attempt's generations took 1,000 - 50 = 950 s: 2 workers x 950 s = 1,900 CPU-s more
    resumed = _record("sp", "4p2e1o", 0, 1000.0)
    resumed["timing"].update(wall_s=50.0, cpu_s=130.0, workers=2)
    records = [resumed, _record("sp", "4p2e1o", 1, 1000.0)]
    table, timing = budget(SimpleNamespace(methods=["sp"]), records)  # type: ignore[arg-type]
    assert timing.set_index("cell")["cell_cpu_s"].to_dict() == {"sp-4p2e1o-s0": 2030.0, "sp-4p2e1o-s1": 2000.0}
    assert table.loc[0, "cpu_s"] == 2015.0
    # a record made before the workers were kept: its cell's experiment says how many
    cfg = parse_benchmark("quick")
    cell = Cell("method", next(iter(cfg.methods)), cfg.tasks[0], 0)
    workers = experiment(cfg, cell).num_workers
    timing = {"train_wall_s": 990.0, "eval_wall_s": 10.0, "wall_s": 50.0, "cpu_s": 130.0}
    old = {"cell": cell.to_dict(), "timing": timing}
    assert workers > 0 and cell_cpu(cfg, old) == 130.0 + workers * 950.0
