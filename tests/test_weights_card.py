"""A published weight's model card: its setting, partners, intervals over the episodes and the commands that
reproduce it, in the manifest and as Markdown beside the checkpoint."""

from __future__ import annotations

import json

import pytest
from test_benchmark_report import _zoos_unchecked, made_up  # noqa: F401  (the fixtures)

from atdrone.benchmark.weights import keep_weights
from atdrone.teams.evaluation import wilson_interval


def test_the_model_card_names_setting_partners_intervals_and_reproduction(made_up) -> None:  # noqa: F811
    cfg, records = made_up
    for r in records:
        r["zoo_version"] = f"zv-{r['cell']['task']}"
    (manifest, *_) = keep_weights(cfg, records)
    n = cfg.eval_episodes
    zoo = cfg.zoos[0]
    suc = manifest["metrics"][zoo]["SUC"]
    assert manifest["metrics_ci95"][zoo]["SUC"] == pytest.approx(list(wilson_interval(round(suc * n / 100), n)))
    assert manifest["zoo_version"] == f"zv-{manifest['task']}" and manifest["ppo"] == cfg.experiment.get("ppo", {})
    seed = manifest["eval_seed"]
    assert f"--episodes {n} --seeds {seed}" in manifest["reproduce"]["evaluate"]
    path = cfg.results / "weights" / manifest["method"] / f"{manifest['task']}.md"
    text = path.read_text()
    assert f"weights:{manifest['method']}/{manifest['task']}" in text and f"| {zoo} | {suc:.1f} [" in text
    assert json.loads(path.with_suffix(".json").read_text())["reproduce"] == manifest["reproduce"]
