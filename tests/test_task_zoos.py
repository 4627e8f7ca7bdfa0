"""The partner zoos made per task: every trained member resolves to a drone of the task it is played on, a
drone of another task is refused unless marked cross-task (and then labelled), the manifest versions the zoos
and its digests are checked at load, and Zoo 4 holds ten partners of its own."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from atdrone.config import TASK_NAMES, ConfigError
from atdrone.models.checkpoint import read_header
from atdrone.policies import GreedyPolicy
from atdrone.policies import manifest as manifest_module
from atdrone.policies.manifest import ManifestError, build_manifest, load_manifest
from atdrone.policies.zoo import ZooError, checkpoint_path, load_zoo
from atdrone.teams.evaluation import evaluate
from atdrone.teams.pools import identity, load_pool

REPO = Path(__file__).resolve().parent.parent
TRAINED_SETS = ("zoo2", "zoo3", "zoo4", "validation")
HIGH = "configs/zoos/checkpoints/4p2e1o/sp_high.pt"


def _sets(task: str) -> list:
    return [load_zoo(z, task) for z in TRAINED_SETS] + [load_pool("train_pool").resolve(task)]


@pytest.mark.parametrize("task", TASK_NAMES)
def test_every_trained_member_resolves_to_a_drone_trained_on_the_task_it_plays(task: str) -> None:
    missing = []
    for zoo in _sets(task):
        for spec in zoo.spec.members:
            if spec.kind != "checkpoint":
                continue
            assert f"checkpoints/{task}/" in spec.checkpoint, (zoo.name, spec.name)
            path = checkpoint_path(spec)
            if not path.is_file():
                missing.append(f"{zoo.name}:{spec.name}")
                continue
            assert read_header(path)["task"] == task, (zoo.name, spec.name)
    if missing:
        pytest.skip(f"not trained yet on {task} (benchmarks/train_task_zoos.py): {', '.join(missing)}")


def _zoo_doc(tmp_path: Path, **member: str) -> Path:
    doc = {"name": "mixed", "members": [{"name": "sp_high", "kind": "checkpoint", "checkpoint": HIGH, **member}]}
    path = tmp_path / "mixed.json"
    path.write_text(json.dumps(doc))
    return path


def test_a_drone_of_another_task_is_refused_in_one_line_naming_both_tasks(tmp_path: Path) -> None:
    zoo = load_zoo(_zoo_doc(tmp_path), "4p2e3o")
    with pytest.raises(ZooError) as err:
        zoo.policies()
    message = str(err.value)
    assert "\n" not in message and "trained on 4p2e1o, not on 4p2e3o" in message and "cross_task" in message
    assert load_zoo(_zoo_doc(tmp_path), "4p2e1o").policies()[0].name == "sp_high"  # its own task plays


def test_a_cross_task_partner_plays_and_is_labelled_in_the_records(tmp_path: Path) -> None:
    zoo = load_zoo(_zoo_doc(tmp_path, cross_task="4p2e1o"), "4p2e3o")
    assert [p.name for p in zoo.policies()] == ["sp_high@4p2e1o"]
    result = evaluate(GreedyPolicy(), "4p2e3o", zoo, episodes=4)
    assert result.cross_task == ("sp_high@4p2e1o",)
    assert set(result.records["partners"].str.split(",").explode()) == {"sp_high@4p2e1o"}
    assert result.summary()["cross_task_partners"] == ["sp_high@4p2e1o"]


def test_a_cross_task_mark_must_name_the_task_the_drone_was_trained_on(tmp_path: Path) -> None:
    with pytest.raises(ZooError, match="not on its cross_task 4p2e5o"):
        load_zoo(_zoo_doc(tmp_path, cross_task="4p2e5o", checkpoint=HIGH), "4p2e3o").policies()


def test_a_learner_of_another_task_is_refused_unless_asked_for() -> None:
    from atdrone.policies.zoo import load_checkpoint

    learner = load_checkpoint(REPO / HIGH)
    with pytest.raises(ConfigError, match="trained on 4p2e1o, not on 4p2e3o"):
        evaluate(learner, "4p2e3o", "zoo1", episodes=2)
    assert evaluate(learner, "4p2e3o", "zoo1", episodes=2, cross_task=True).task == "4p2e3o"


def test_an_evaluation_records_the_zoo_version_of_its_task() -> None:
    result = evaluate(GreedyPolicy(), "4p2e1o", "zoo1", episodes=2)
    assert result.zoo_version == load_manifest()["tasks"]["4p2e1o"]["version"]  # type: ignore[index]
    assert result.summary()["zoo_version"].startswith("zv-")


def test_the_committed_manifest_is_the_one_the_documents_and_files_make() -> None:
    committed = load_manifest()
    assert committed is not None, "configs/zoos/manifest.json is missing: atdrone zoos --write"
    assert committed == build_manifest(), "the zoo manifest is stale: atdrone zoos --write"


def test_a_changed_checkpoint_is_refused_at_load_in_one_line(tmp_path: Path, monkeypatch) -> None:
    drone = tmp_path / "drone.pt"
    drone.write_bytes((REPO / HIGH).read_bytes())
    doc = {"format": 1, "version": "x", "tasks": {"4p2e1o": {"version": "x", "sets": {"zoo2": [
        {"name": "sp_high", "kind": "checkpoint", "checkpoint": str(drone), "sha256": "0" * 64}
    ]}}}}  # fmt: skip
    path = tmp_path / "manifest.json"
    path.write_text(json.dumps(doc))
    monkeypatch.setattr(manifest_module, "MANIFEST", str(path))
    zoo_doc = _zoo_doc(tmp_path, checkpoint=str(drone))
    with pytest.raises(ManifestError) as err:
        load_zoo(zoo_doc, "4p2e1o").policies()
    assert "\n" not in str(err.value) and "differs from the zoo manifest" in str(err.value)
    doc["tasks"]["4p2e1o"]["sets"]["zoo2"][0]["sha256"] = manifest_module.file_sha256(drone)  # type: ignore[index]
    path.write_text(json.dumps(doc))
    assert load_zoo(zoo_doc, "4p2e1o").policies()[0].name == "sp_high"


def test_zoo4_holds_ten_partners_none_shared_with_another_zoo_the_validation_zoo_or_the_pool() -> None:
    zoo4 = load_zoo("zoo4")
    assert len(zoo4) >= 10
    kinds = {m.kind for m in zoo4.spec.members}
    assert {"checkpoint", "greedy", "vicsek"} <= kinds
    others = [load_zoo(z) for z in ("zoo1", "zoo2", "zoo3", "validation")] + [load_pool("train_pool")]
    seen = {identity(m) for zoo in others for m in zoo.spec.members}
    assert not [m.name for m in zoo4.spec.members if identity(m) in seen]


def test_a_per_task_zoo_cannot_play_before_it_is_resolved_for_a_task() -> None:
    with pytest.raises(ZooError, match="resolve it for a task"):
        load_zoo("zoo2").policies()
    with pytest.raises(ZooError, match="resolved for task 4p2e1o, not 4p2e3o"):
        load_zoo("zoo2", "4p2e1o").resolve("4p2e3o")


def test_a_benchmark_folder_made_with_other_partners_is_refused_and_its_cells_not_counted(tmp_path, monkeypatch):
    from atdrone.benchmark import job
    from atdrone.benchmark.config import parse_benchmark
    from atdrone.errors import UserError

    cfg = parse_benchmark("quick", tasks=["4p2e1o"], zoos=["zoo1"], out_dir=str(tmp_path))
    job._check_folder(cfg)
    saved = json.loads((cfg.folder / job.CONFIG_FILE).read_text())
    assert saved["zoo_versions"] == {"4p2e1o": load_manifest()["tasks"]["4p2e1o"]["version"]}  # type: ignore[index]
    before = cfg.digest()
    monkeypatch.setattr(manifest_module, "task_version", lambda task: "zv-retrained")
    assert cfg.digest() != before  # a finished cell's record names the digest: it no longer counts
    with pytest.raises(UserError, match=r"holds other partners \(zoo versions .*zv-retrained"):
        job._check_folder(cfg)
