"""benchmarks/grid_learners.py: a grid's final learners kept beside its records and put back where the records
name them, each checked against its record's sha256."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def grid(load_script) -> ModuleType:
    return load_script(ROOT / "benchmarks" / "grid_learners.py")


def _cell(cells: Path, folder: Path, name: str, kind: str, data: bytes) -> Path:
    path = folder / "runs" / f"x-{name}" / "members" / "m.pt"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(data)
    record = {"name": name, "cell": {"kind": kind}, "checkpoint": str(path.relative_to(folder)),
              "sha256": hashlib.sha256(data).hexdigest()}  # fmt: skip
    (cells / f"{name}.json").write_text(json.dumps(record))
    return path


def test_learners_are_saved_and_restored_by_their_records_digests_and_a_changed_one_is_refused(grid, tmp_path):
    cells, folder, kept = tmp_path / "cells", tmp_path / "runs", tmp_path / "learners"
    cells.mkdir()
    (cells / "_config.json").write_text("{}")
    learner = _cell(cells, folder, "sp-4p2e1o-s0", "method", b"weights of sp")
    _cell(cells, folder, "br-zoo1-4p2e1o-s0", "br", b"weights of a best response")
    gone = _cell(cells, folder, "sp-4p2e1o-s1", "method", b"weights lost")
    gone.unlink()  # a learner lost before it was kept: named, the others copied
    assert grid.sync("save", cells, folder, kept) == (["sp-4p2e1o-s0"], ["sp-4p2e1o-s1"])  # no best responses
    assert sorted(p.name for p in kept.iterdir()) == ["sp-4p2e1o-s0.pt"]
    assert grid.sync("save", cells, folder, kept) == ([], ["sp-4p2e1o-s1"])  # already there: nothing copied
    (cells / "sp-4p2e1o-s1.json").unlink()
    learner.unlink()  # a fresh checkout: the run folder is gone
    assert grid.sync("restore", cells, folder, kept) == (["sp-4p2e1o-s0"], [])
    assert learner.read_bytes() == b"weights of sp"
    learner.unlink()
    (kept / "sp-4p2e1o-s0.pt").write_bytes(b"other weights")
    with pytest.raises(ValueError, match=r"sp-4p2e1o-s0: .* has sha256 .* its record says"):
        grid.sync("restore", cells, folder, kept)
    assert not learner.exists()
