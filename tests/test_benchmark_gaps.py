"""Where ours differs from the paper: the episode summaries a cell keeps and the report's section built from them,
on hand-made episodes and made-up cell records (no Ray)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from atdrone.benchmark.cells import cells, load_benchmark
from atdrone.benchmark.episodes import episode_summary
from atdrone.benchmark.paper import TABLE2
from atdrone.benchmark.report import write_report
from atdrone.config import load_task

DOC: dict[str, Any] = {
    "name": "gaps",
    "tasks": ["4p2e1o", "4p2e5o"],
    "seeds": [0, 1],
    "zoos": ["zoo1", "zoo2"],
    "env_steps": 1024,
    "updates_per_generation": 2,
    "eval_episodes": 8,
    "bootstrap_reps": 100,
    "methods": {"sp": {"experiment": "sp_quick"}, "pbt": {"experiment": "pbt_quick"}},
    "best_response": False,
}


@pytest.fixture(autouse=True)
def _zoos_unchecked(monkeypatch: pytest.MonkeyPatch) -> None:
    """The report reads records and plays no partner: the config's check of the zoos on disk is skipped."""
    from atdrone.benchmark import config

    monkeypatch.setattr(config, "_check_zoo", lambda zoo, path, tasks: None)


def test_an_episode_summary_splits_the_return_into_the_rewards_terms_and_the_collisions_by_who_was_in_them() -> None:
    """Four episodes of 4p2e1o (capture +10 per evader, collision -10 once): a success (2 captured, return 35),
    a learner's crash (1 captured, 5), a crash of partners alone (0 captured, -8), a timeout (0 captured, 4).
    By hand: REW 9; capture 10 x 0.75 = 7.5; collision -10 x 0.5 = -5; the rest 9 - 7.5 + 5 = 6.5."""
    records = pd.DataFrame(
        {
            "return": [35.0, 5.0, -8.0, 4.0],
            "captured": [2, 1, 0, 0],
            "length": [200, 100, 50, 1000],
            "collided": [False, True, True, False],
            "outcome": ["captured", "collision", "collision", "timeout"],
            "learner_crashed": [False, True, False, False],
            "partner_crashed": [False, True, True, False],  # a learner-partner crash counts for the learner
        }
    )
    s = episode_summary(records, load_task("4p2e1o"))
    assert s == pytest.approx(
        {
            "learner_crash": 25.0,
            "partner_only_crash": 25.0,
            "captured": 0.75,
            "length": 337.5,
            "return_capture": 7.5,
            "return_collision": -5.0,
            "return_rest": 6.5,
        }
    )
    assert s["return_capture"] + s["return_collision"] + s["return_rest"] == pytest.approx(records["return"].mean())


PLANTED = {  # per method: (learner_crash, partner_only_crash, captured); COL is their sum
    "sp": (10.0, 20.0, 1.0),
    "pbt": (30.0, 10.0, 0.5),
}


def _records(cfg: Any) -> list[dict[str, Any]]:
    """Method records with metrics and episode summaries as run_cell writes them (seed 1 of pbt on 4p2e5o keeps
    no summaries, as a record written before they were kept); no best responses or floors."""
    out = []
    for cell in cells(cfg):
        if cell.kind != "method":
            continue
        learner, partners, captured = PLANTED[cell.method]
        zoos = [*cfg.zoos, cfg.select_zoo]
        rew = 10.0 * captured - 0.1 * (learner + partners) + 3.0 + cell.seed
        metrics = {z: {"SUC": 50.0, "COL": learner + partners, "AST": 250.0 + cell.seed, "REW": rew} for z in zoos}
        episodes = {
            z: {"learner_crash": learner, "partner_only_crash": partners, "captured": captured, "length": 200.0}
            | {"return_capture": 10.0 * captured, "return_collision": -0.1 * (learner + partners)}
            | {"return_rest": 3.0 + cell.seed}
            for z in zoos
        }
        record: dict[str, Any] = {"cell": cell.to_dict(), "name": cell.name, "benchmark": cfg.digest()}
        budget = {"env_steps": 1024, "learner_samples": 2048, "eval_env_steps": 0, "benchmark_eval_env_steps": 9}
        record.update(metrics=metrics, budget=budget, timing={"wall_s": 1.0, "cpu_s": 2.0}, generations=1)
        if (cell.method, cell.task, cell.seed) != ("pbt", "4p2e5o", 1):
            record["episodes"] = episodes
        out.append(record)
    return out


def test_the_gap_section_splits_rew_and_col_over_the_papers_methods_beside_their_table_2_mean(
    tmp_path: Path,
) -> None:
    cfg = load_benchmark({**DOC, "out_dir": str(tmp_path / "bench"), "results_dir": str(tmp_path / "results")})
    files = write_report(cfg, _records(cfg))
    gaps = pd.read_csv(files["gaps.csv"])
    assert len(gaps) == 2 * 2  # tasks x test zoos; the selection zoo is no test zoo
    row = gaps[(gaps.task == "4p2e5o") & (gaps.zoo == "zoo2")].iloc[0]
    # runs: sp seeds 0, 1 and pbt seed 0 (pbt seed 1 keeps no summaries)
    assert (row.methods, row.runs) == ("sp pbt", 3)
    # each method's mean over its runs, then the mean over the methods (as the paper's columns): sp, then pbt
    assert row.learner_crash == pytest.approx((10 + 30) / 2)
    assert row.partner_only_crash == pytest.approx((20 + 10) / 2)
    assert row["COL"] == pytest.approx((30 + 40) / 2)
    assert row.return_capture == pytest.approx((10 + 5) / 2)
    assert row.return_rest == pytest.approx(((3 + 4) / 2 + 3) / 2)
    assert row["REW"] == pytest.approx(row.return_capture + row.return_collision + row.return_rest)
    assert row.capture_at_most == 20.0  # two evaders at +10
    paper = TABLE2["4p2e5o"]["zoo2"]
    assert row.paper_REW == pytest.approx(np.mean([paper["sp"]["REW"][0], paper["pbt"]["REW"][0]]))
    assert row.paper_COL == pytest.approx(np.mean([paper["sp"]["COL"][0], paper["pbt"]["COL"][0]]))
    text = files["report.md"].read_text()
    section = text[text.index("## Where ours differs from the paper") :]
    assert "the 7 run(s) of the paper's methods that keep episode summaries" in section  # 4 on 4p2e1o, 3 on 4p2e5o
    assert "| 4p2e5o | zoo2 | sp pbt | 3 | " in section
    # partners alone: sp 20 of 30, pbt 10 of 40; every cell the methods' means (20 + 10) / (30 + 40)
    low = high = (20 + 10) / (30 + 40)
    assert f"partner drones alone ended {low:.0%} to {high:.0%} of our collision episodes" in section
    assert "REW: the paper's REW is above the most our capture term can pay in 4 of 4" in section
    assert text.index("## Beside the paper (Table 2)") < text.index("## Where ours differs from the paper")


def test_without_episode_summaries_the_section_says_the_split_is_missing(tmp_path: Path) -> None:
    cfg = load_benchmark({**DOC, "out_dir": str(tmp_path / "bench"), "results_dir": str(tmp_path / "results")})
    records = _records(cfg)
    for r in records:
        r.pop("episodes", None)
    text = write_report(cfg, records)["report.md"].read_text()
    assert "No run of the paper's methods keeps episode summaries" in text
    assert "- REW: ours below the paper's in" in text  # how the gaps fall needs only the metrics
