"""benchmarks/hola_archive.py: a long study's finished runs survive a lost reports/ folder."""

from __future__ import annotations

import json
from pathlib import Path
from types import ModuleType

import pytest

ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def archive_mod(load_script) -> ModuleType:
    return load_script(ROOT / "benchmarks" / "hola_archive.py")


def _run(out: Path, name: str, algorithm: dict[str, list[str]], samples: int, members: list[str]) -> Path:
    run = out / "runs" / name
    (run / "members").mkdir(parents=True)
    state = {"coordinator": {"algorithm": algorithm, "budget": {"learner_samples": samples}}}
    (run / "service_state.json").write_text(json.dumps(state))
    (run / "population.csv").write_text("member\n" + "\n".join(members) + "\n")
    (run / "compute.json").write_text('{"wall_s": 1.0}')
    for g in (0, 1):
        (run / "generations" / str(g)).mkdir(parents=True)
        (run / "generations" / str(g) / "hypergraph.json").write_text(json.dumps({"g": g}))
        (run / "generations" / str(g) / "summary.json").write_text("{}")
    (run / "generations" / "0" / "pi0.json").write_text('{"levels": [8, 8]}')
    for m in members:
        (run / "members" / f"{m}.pt").write_bytes(m.encode() * 100)
    return run


@pytest.fixture
def study(tmp_path: Path) -> Path:
    out = tmp_path / "reports"
    # HOLA: the final learner is the last of 'learners'; its 600 samples pick SP's member 2 of 4 (300 each)
    _run(out, "4p2e5o-hola-s0", {"learners": ["h0", "h1"], "population": ["p0", "h0", "h1"]}, 600, ["p0", "h0", "h1"])
    _run(out, "4p2e5o-sp-s0", {"population": ["s0", "s1", "s2", "s3"]}, 1200, ["s0", "s1", "s2", "s3"])
    unfinished = _run(out, "4p2e5o-sp-s1", {"population": ["t0"]}, 10, ["t0"])
    (unfinished / "population.csv").unlink()
    (out / "eval").mkdir()
    (out / "eval" / "4p2e5o-sp-s0.json").write_text('{"rows": []}')
    return out


def test_save_keeps_what_the_later_phases_read_and_only_that(archive_mod: ModuleType, study: Path) -> None:
    archive = study.parent / "archive"
    written = archive_mod.save(study, archive)
    kept = sorted(str(p.relative_to(archive)) for p in archive.rglob("*") if p.is_file())
    files = ("compute.json", "generations/0/hypergraph.json", "generations/0/pi0.json", "generations/1/hypergraph.json")
    runs = [
        f"runs/4p2e5o-{alg}-s0/{f}" for alg in ("hola", "sp") for f in (*files, "population.csv", "service_state.json")
    ]
    members = [f"runs/4p2e5o-{run}/members/{m}.pt" for run, m in (("hola-s0", "h1"), ("sp-s0", "s1"), ("sp-s0", "s3"))]
    assert kept == sorted([*runs, *members, "eval/4p2e5o-sp-s0.json"])
    assert written == len(kept)
    assert archive_mod.save(study, archive) == 0  # idempotent: nothing rewritten


def test_restore_fills_a_lost_reports_folder_and_never_overwrites(archive_mod: ModuleType, study: Path) -> None:
    archive = study.parent / "archive"
    archive_mod.save(study, archive)
    fresh = study.parent / "fresh"
    (fresh / "eval").mkdir(parents=True)
    (fresh / "eval" / "4p2e5o-sp-s0.json").write_text('{"rows": ["newer"]}')
    archive_mod.restore(archive, fresh)
    for path in archive.rglob("*"):
        if path.is_file() and path.name != "4p2e5o-sp-s0.json":
            assert (fresh / path.relative_to(archive)).read_bytes() == path.read_bytes()
    assert (fresh / "eval" / "4p2e5o-sp-s0.json").read_text() == '{"rows": ["newer"]}'
    # the restored runs are finished runs to hola_report: their members are where its evaluate phase looks
    assert (fresh / "runs" / "4p2e5o-hola-s0" / "population.csv").exists()
    assert not (fresh / "runs" / "4p2e5o-sp-s1").exists()
