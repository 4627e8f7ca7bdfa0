"""The population registry: members, matches, generations, pandas views, export, CLI, and the Ray actor."""

from __future__ import annotations

import json
import math
import os
import shutil
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest

from atdrone.cli import main
from atdrone.registry import Registry, RegistryError, default_path

TASK = "4p2e5o"
RESULT = {"SUC": 50.0, "COL": 10.0, "AST": 80.0, "REW": 1.5}


@pytest.fixture
def registry(tmp_path: Path) -> Registry:
    with Registry(tmp_path / "registry.db") as reg:
        yield reg


def _add(reg: Registry, generation: int = 0, parents: tuple[str, ...] = (), **fields) -> str:
    fields.setdefault("run", "hola-quick")
    fields.setdefault("algorithm", "hola")
    fields.setdefault("task", TASK)
    return reg.add_member(generation=generation, parents=parents, **fields)


def _metrics(suc: float, ast: float = 80.0) -> dict[str, float]:
    return {**RESULT, "SUC": suc, "AST": ast}


# ------------------------------------------------------------------ members
def test_add_member_generates_an_id_and_reads_back_every_field(registry: Registry) -> None:
    mid = registry.add_member(
        run="hola-quick",
        algorithm="HOLA-Drone V2",
        generation=3,
        task=TASK,
        checkpoint=Path("runs/a.pt"),
        sha256="ab" * 32,
        mlflow_run_id="r1",
        tags={"role": "learner"},
        metrics={"eta": 0.25},
    )
    assert mid.startswith("hola-drone-v2-g3-") and len(mid.rsplit("-", 1)[1]) == 6
    member = registry.member(mid)
    assert member["generation"] == 3 and member["parents"] == [] and member["status"] == "active"
    assert member["checkpoint"] == "runs/a.pt" and member["sha256"] == "ab" * 32 and member["mlflow_run_id"] == "r1"
    assert member["tags"] == {"role": "learner"} and member["metrics"] == {"eta": 0.25}
    other = registry.add_member(
        run="r", algorithm="sp", generation=np.int64(0), task=TASK, metrics={"loss": np.float32(0.5), "v": np.ones(2)}
    )
    assert other != mid and registry.member(other)["metrics"] == {"loss": 0.5, "v": [1.0, 1.0]}


def test_duplicate_id_is_refused_and_the_first_member_kept(registry: Registry) -> None:
    _add(registry, member_id="m1", tags={"first": True})
    with pytest.raises(RegistryError, match="'m1' is already registered with other tags"):
        _add(registry, member_id="m1", tags={"first": False})
    with pytest.raises(RegistryError, match="'m1' is already registered with other generation, sha256"):
        _add(registry, generation=1, member_id="m1", sha256="ab" * 32, tags={"first": True})
    assert registry.member("m1")["tags"] == {"first": True} and len(registry.members()) == 1


def test_registering_a_member_again_with_the_same_fields_is_a_no_op(registry: Registry) -> None:
    """A replayed add_member (Ray retries a call whose reply was lost) returns the id and changes nothing,
    also after updates merged metrics into the row and changed its status and MLflow run id."""
    fields = {"checkpoint": "runs/m.pt", "sha256": "cd" * 32, "metrics": {"train/loss": 0.5}, "member_id": "m2"}
    _add(registry, member_id="m1")
    assert _add(registry, parents=("m1",), **fields) == "m2"
    registry.update_member("m2", metrics={"zoo1/SUC": 40.0}, status="retired", mlflow_run_id="r9")
    before = registry.member("m2")
    assert _add(registry, parents=("m1",), **fields) == "m2"
    assert registry.member("m2") == before and len(registry.members()) == 2
    with pytest.raises(RegistryError, match="other parents"):
        _add(registry, **fields)
    with pytest.raises(RegistryError, match="other metrics"):
        _add(registry, parents=("m1",), **{**fields, "metrics": {"train/loss": 0.25}})


def test_update_member_merges_metrics_and_tags_and_replaces_the_rest(registry: Registry) -> None:
    mid = _add(registry, metrics={"eta": 0.5, "SUC": 10.0}, tags={"a": 1})
    updated = registry.update_member(mid, metrics={"SUC": 20.0, "COL": 5.0}, tags={"b": 2}, status="retired")
    assert updated["metrics"] == {"eta": 0.5, "SUC": 20.0, "COL": 5.0} and updated["tags"] == {"a": 1, "b": 2}
    registry.update_member(mid, mlflow_run_id="run-9", checkpoint="b.pt", sha256="cd" * 32)
    member = registry.member(mid)
    assert (member["status"], member["mlflow_run_id"], member["checkpoint"]) == ("retired", "run-9", "b.pt")
    assert member["sha256"] == "cd" * 32


def test_unknown_ids_bad_fields_and_unregistered_parents_get_clear_errors(registry: Registry) -> None:
    with pytest.raises(KeyError, match="no member 'ghost'"):
        registry.member("ghost")
    with pytest.raises(KeyError, match="no member 'ghost'"):
        registry.update_member("ghost", status="retired")
    mid = _add(registry)
    with pytest.raises(RegistryError, match="status must be one of"):
        registry.update_member(mid, status="lost")
    with pytest.raises(RegistryError, match=r"parents \['ghost'\] are not registered"):
        _add(registry, generation=1, parents=("ghost",))
    with pytest.raises(RegistryError, match="generation must be an integer"):
        _add(registry, generation=1.5)


def test_members_filter_by_run_task_and_status(registry: Registry) -> None:
    a = _add(registry, run="r1")
    b = _add(registry, run="r2", task="4p2e1o")
    registry.update_member(b, status="retired")
    assert registry.members()["id"].tolist() == [a, b]
    assert registry.members(run="r1")["id"].tolist() == [a]
    assert registry.members(task="4p2e1o")["id"].tolist() == [b]
    assert registry.members(status="active")["id"].tolist() == [a]
    assert registry.members(run="r1", status="retired").empty


def test_add_checkpoint_takes_task_algorithm_and_sha256_from_the_header(registry: Registry, tmp_path: Path) -> None:
    from atdrone.models.checkpoint import save_checkpoint
    from atdrone.models.networks import ActorCritic, NetConfig

    path = tmp_path / "learner.pt"
    header = save_checkpoint(
        path,
        ActorCritic(NetConfig(entity_dim=8, hidden=8)),
        {"task": "4p2e1o", "num_p": 4, "num_e": 2, "algorithm": "ippo"},
    )
    mid = registry.add_checkpoint(path, run="r", generation=2, tags={"from": "file"})
    member = registry.member(mid)
    assert (member["task"], member["algorithm"], member["sha256"]) == ("4p2e1o", "ippo", header["sha256"])
    assert member["checkpoint"] == str(path) and mid.startswith("ippo-g2-")


# -------------------------------------------------------- matches, crossplay
@pytest.fixture
def played(registry: Registry) -> tuple[Registry, str, str, str]:
    """Three members and five matches; the cross-play values are worked out in the test below."""
    a, b, c = (_add(registry, member_id=m) for m in "abc")
    registry.add_match([a, a, a, a], TASK, "hola-quick", 0, [0], 10, _metrics(40.0))
    registry.add_match([a, a, a, a], TASK, "hola-quick", 0, [1], 10, _metrics(60.0))
    registry.add_match([a, a, b, b], TASK, "hola-quick", 1, [0, 1], 20, _metrics(30.0, ast=math.nan))
    registry.add_match([a, b, c, c], TASK, "hola-quick", 1, [0], 10, _metrics(90.0, ast=100.0))
    registry.add_match([b, b, b, b], "4p2e1o", "hola-quick", 1, [0], 10, _metrics(10.0))
    return registry, a, b, c


def test_matches_are_recorded_with_team_order_seeds_and_metrics(played: tuple[Registry, str, str, str]) -> None:
    registry, a, b, c = played
    frame = registry.matches(task=TASK)
    assert frame["id"].tolist() == [1, 2, 3, 4]
    assert frame["team"][3] == [a, b, c, c] and frame["seeds"][2] == [0, 1] and frame["episodes"][2] == 20
    assert frame["SUC"].tolist() == [40.0, 60.0, 30.0, 90.0] and math.isnan(frame["AST"][2])
    assert len(registry.matches()) == 5 and len(registry.matches(run="other")) == 0


def test_crossplay_matrix_matches_the_hand_computed_means(played: tuple[Registry, str, str, str]) -> None:
    registry, a, b, c = played
    nan = math.nan
    # a alone: (40 + 60) / 2; a with b: (30 + 90) / 2; a-c and b-c only share match 4; b and c never alone on 4p2e5o
    expected = pd.DataFrame(
        [[50.0, 60.0, 90.0], [60.0, nan, 90.0], [90.0, 90.0, nan]], index=[a, b, c], columns=[a, b, c]
    )
    got = registry.crossplay(task=TASK)
    pd.testing.assert_frame_equal(got, expected, check_names=False)
    assert (got.index.name, got.columns.name) == ("member", "partner")
    assert registry.crossplay()[b][b] == 10.0  # the 4p2e1o self-play match counts without a task filter
    ast = registry.crossplay(task=TASK, metric="AST")
    assert ast[a][b] == 100.0 and ast[a][a] == 80.0  # NaN AST (no success) is left out of the mean
    with pytest.raises(RegistryError, match="metric must be one of"):
        registry.crossplay(metric="WIN")
    assert registry.crossplay(task="4p3e5o").empty


def test_a_match_recorded_again_is_the_same_match_and_other_results_are_refused(registry: Registry) -> None:
    """A match's natural key is (run, generation, team, task, seeds): a replay returns the first id (NaN AST
    included), the key with other results is an error, and another seed or generation is another match."""
    nan_ast = _metrics(0.0, ast=math.nan)
    first = registry.add_match(["a", "b"], TASK, "r", 0, [7], 10, nan_ast)
    assert registry.add_match(["a", "b"], TASK, "r", 0, [7], 10, {**nan_ast, "extra": 1.0}) == first
    for episodes, result in ((10, _metrics(10.0, ast=math.nan)), (10, _metrics(0.0, ast=5.0)), (11, nan_ast)):
        with pytest.raises(RegistryError, match=f"match {first} already records team"):
            registry.add_match(["a", "b"], TASK, "r", 0, [7], episodes, result)
    others = [(["b", "a"], 0, [7]), (["a", "b"], 1, [7]), (["a", "b"], 0, [8])]
    ids = [registry.add_match(team, TASK, "r", g, seeds, 10, nan_ast) for team, g, seeds in others]
    assert ids == [first + 1, first + 2, first + 3] and len(registry.matches()) == 4


def test_add_match_refuses_missing_metrics_and_empty_teams(registry: Registry) -> None:
    with pytest.raises(RegistryError, match=r"lack \['REW'\]"):
        registry.add_match(["a"], TASK, "r", 0, [0], 1, {"SUC": 1.0, "COL": 0.0, "AST": 3.0})
    with pytest.raises(RegistryError, match="at least one member"):
        registry.add_match([], TASK, "r", 0, [0], 1, RESULT)
    with pytest.raises(RegistryError, match="episodes must be an integer >= 1"):
        registry.add_match(["a"], TASK, "r", 0, [0], 0, RESULT)


# ------------------------------------------------------------------ lineage
def test_lineage_walks_three_generations_of_parents(registry: Registry) -> None:
    p1, p2, p3 = (_add(registry, 0, member_id=m) for m in ("p1", "p2", "p3"))
    c1 = _add(registry, 1, (p1, p2), member_id="c1")
    c2 = _add(registry, 1, (p2,), member_id="c2")
    _add(registry, 1, (p3,), member_id="c3")  # not an ancestor
    d = _add(registry, 2, (c1, c2), member_id="d")
    frame = registry.lineage(d)
    assert frame["id"].tolist() == [d, c1, c2, p1, p2]
    assert frame["depth"].tolist() == [0, 1, 1, 2, 2]  # p2 is reached twice, at depth 2 both times
    assert frame["generation"].tolist() == [2, 1, 1, 0, 0]
    assert frame["parents"][0] == [c1, c2]
    assert registry.lineage(p3)["id"].tolist() == [p3]
    with pytest.raises(KeyError, match="no member 'ghost'"):
        registry.lineage("ghost")


# -------------------------------------------------------------- generations
def test_generations_and_the_last_completed_one(registry: Registry) -> None:
    assert registry.last_completed_generation("r") is None
    registry.start_generation("r", 0, {"profiles": 4})
    assert registry.last_completed_generation("r") is None
    registry.finish_generation("r", 0, {"members": 6})
    registry.start_generation("r", 1)
    registry.start_generation("other", 5)
    registry.finish_generation("other", 5)
    assert registry.last_completed_generation("r") == 0 and registry.last_completed_generation("other") == 5
    frame = registry.generations("r")
    assert frame["idx"].tolist() == [0, 1] and frame["info"][0] == {"profiles": 4, "members": 6}
    assert frame["finished"].notna().tolist() == [True, False]
    registry.finish_generation("r", 1)
    registry.start_generation("r", 1)  # a restarted generation is no longer finished
    assert registry.last_completed_generation("r") == 0
    with pytest.raises(RegistryError, match="never started"):
        registry.finish_generation("r", 7)


# ------------------------------------------------------------------- export
def _loaded(path: Path, fmt: str, table: str) -> pd.DataFrame:
    frame = pd.read_csv(path) if fmt == "csv" else pd.read_parquet(path)
    columns = {"members": ("parents", "tags", "metrics"), "matches": ("team", "seeds"), "generations": ("info",)}
    for col in columns[table]:
        frame[col] = [json.loads(v) for v in frame[col]]
    return frame


def _comparable(frame: pd.DataFrame) -> pd.DataFrame:
    frame = frame.astype(object)
    return frame.where(frame.notna(), None).reset_index(drop=True)


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_export_round_trips_every_table(played: tuple[Registry, str, str, str], tmp_path: Path, fmt: str) -> None:
    registry, a, *_ = played
    registry.update_member(a, metrics={"eta": 1 / 3}, tags={"x": [1, 2]})
    registry.start_generation("hola-quick", 0, {"n": 1})
    views = {"members": registry.members(), "matches": registry.matches(), "generations": registry.generations()}
    for table, view in views.items():
        out = registry.export(tmp_path / "out" / f"{table}.{fmt}", format=fmt, table=table)
        pd.testing.assert_frame_equal(_comparable(_loaded(out, fmt, table)), _comparable(view), check_dtype=False)


def test_failed_export_leaves_the_old_file_and_no_temp_file(
    registry: Registry, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    _add(registry)
    out = tmp_path / "members.parquet"
    out.write_bytes(b"old")

    def broken(self: pd.DataFrame, target: Any, **kwargs: object) -> None:
        target.write(b"half")  # part of the file reaches the temp file, then the disk fills
        raise OSError("disk full")

    monkeypatch.setattr(pd.DataFrame, "to_parquet", broken)
    with pytest.raises(OSError, match="disk full"):
        registry.export(out, format="parquet")
    assert out.read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".members")] == []  # the temp file is gone
    with pytest.raises(RegistryError, match="format must be one of"):
        registry.export(out, format="xlsx")


# -------------------------------------------------------------------- sqlite
def test_the_file_is_in_wal_mode_with_a_schema_version(registry: Registry) -> None:
    conn = sqlite3.connect(registry.path)
    try:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
        assert conn.execute("SELECT version FROM schema_version").fetchall() == [(1,)]
    finally:
        conn.close()
    assert registry.journal_mode == "wal"


def test_a_file_from_a_newer_schema_or_not_a_registry_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "r.db"
    Registry(path).close()
    conn = sqlite3.connect(path)
    conn.execute("UPDATE schema_version SET version = 99")
    conn.commit()
    conn.close()
    with pytest.raises(RegistryError, match="schema v99"):
        Registry(path)
    other = tmp_path / "other.db"
    other.write_bytes(b"")  # an empty sqlite database
    with pytest.raises(RegistryError, match="not an atdrone registry"):
        Registry(other, create=False)
    with pytest.raises(FileNotFoundError, match="no registry at"):
        Registry(tmp_path / "missing.db", create=False)


def test_a_registry_belongs_to_the_run_that_claimed_it(registry: Registry) -> None:
    assert registry.owners() == {}
    registry.claim("a1b2", "hola-quick")
    registry.claim("a1b2", "hola-quick")  # the run's own resume: nothing changes
    with pytest.raises(
        RegistryError, match=r"is the registry of hola-quick \(run id a1b2\), not of other \(run id c3\)"
    ):
        registry.claim("c3", "other")
    assert registry.owners() == {"a1b2": "hola-quick"}


def test_after_a_checkpoint_the_file_alone_holds_every_commit(registry: Registry, tmp_path: Path) -> None:
    """The writer is never closed (a Ray actor is killed): after :meth:`Registry.checkpoint` the .db file copied
    without its -wal holds every member and match; copied before, it is not even a registry."""
    ids = [_add(registry, generation=g) for g in range(3)]
    registry.add_match([ids[0]], TASK, "hola-quick", 0, [1], 4, RESULT)
    before = tmp_path / "before" / "registry.db"
    before.parent.mkdir()
    shutil.copyfile(registry.path, before)
    assert registry.checkpoint()
    assert registry.path.with_name("registry.db-wal").stat().st_size == 0
    after = tmp_path / "after" / "registry.db"
    after.parent.mkdir()
    shutil.copyfile(registry.path, after)
    with Registry(after, create=False) as copy:
        assert list(copy.members()["id"]) == ids and len(copy.matches()) == 1
    with pytest.raises(RegistryError, match="not an atdrone registry"):
        Registry(before, create=False)


def test_concurrent_writers_on_one_file_lose_nothing(tmp_path: Path) -> None:
    path = tmp_path / "shared.db"
    first, second = Registry(path), Registry(path)
    shared = first.add_member(run="r", algorithm="sp", generation=0, task=TASK)
    n = 40

    def work(reg: Registry, name: str) -> None:
        for i in range(n):
            reg.add_member(run=name, algorithm="sp", generation=i, task=TASK)
            reg.update_member(shared, metrics={f"{name}{i}": i})  # read-modify-write: must not drop the other's keys
            reg.add_match([shared], TASK, name, i, [i], 1, RESULT)

    threads = [threading.Thread(target=work, args=(reg, name)) for reg, name in ((first, "x"), (second, "y"))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    with Registry(path) as fresh:
        assert len(fresh.members(run="x")) == n and len(fresh.members(run="y")) == n
        assert len(fresh.member(shared)["metrics"]) == 2 * n
        assert len(fresh.matches()) == 2 * n
    first.close()
    second.close()


def test_default_path_honours_the_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.delenv("ATDRONE_REGISTRY", raising=False)
    assert default_path() == Path("registry.db")
    monkeypatch.setenv("ATDRONE_REGISTRY", str(tmp_path / "pop.db"))
    assert default_path() == tmp_path / "pop.db"


def test_importing_the_registry_does_not_import_ray() -> None:
    code = "import sys, atdrone.registry; assert 'ray' not in sys.modules"
    subprocess.run([sys.executable, "-c", code], check=True)


# ---------------------------------------------------------------------- CLI
def test_cli_list_show_crossplay_lineage(
    played: tuple[Registry, str, str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    registry, a, b, _ = played
    child = _add(registry, 1, (a, b), member_id="child", run="r2")
    db = str(registry.path)
    assert main(["registry", "--db", db, "list"]) == 0
    out = capsys.readouterr().out
    assert all(m in out for m in ("a", "b", "c", child)) and "generation" in out
    assert main(["registry", "list", "--db", db, "--run", "r2"]) == 0
    assert capsys.readouterr().out.splitlines()[1].split()[0] == child
    assert main(["registry", "--db", db, "list", "--status", "retired"]) == 0
    assert capsys.readouterr().out.strip() == "(no members)"
    assert main(["registry", "--db", db, "show", child]) == 0
    out = capsys.readouterr().out
    assert "parents: a, b\n" in out and "run: r2\n" in out
    assert main(["registry", "--db", db, "crossplay", "--task", TASK]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["partner", "a", "b", "c"] and lines[2].split() == ["a", "50.0", "60.0", "90.0"]
    assert main(["registry", "--db", db, "lineage", child]) == 0
    assert [line.split()[0] for line in capsys.readouterr().out.splitlines()[1:]] == [child, "a", "b"]


def test_cli_export_writes_a_readable_file(
    played: tuple[Registry, str, str, str], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    registry, *_ = played
    out = tmp_path / "m.parquet"
    argv = ["registry", "--db", str(registry.path), "export", "--format", "parquet", "--table", "matches"]
    assert main([*argv, "--out", str(out)]) == 0
    assert f"wrote {out}" in capsys.readouterr().out
    assert pd.read_parquet(out)["SUC"].tolist() == registry.matches()["SUC"].tolist()


def test_cli_reports_unknown_ids_and_missing_files_in_one_line(
    registry: Registry, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["registry", "--db", str(registry.path), "show", "ghost"]) == 2
    assert (
        capsys.readouterr().err.strip()
        == f"atdrone registry: error: no member 'ghost' in the registry at {registry.path}"
    )
    missing = tmp_path / "nowhere.db"
    assert main(["registry", "--db", str(missing), "list"]) == 2
    assert capsys.readouterr().err.strip() == f"atdrone registry: error: no registry at {missing}"
    assert not missing.exists()
    assert main(["registry", "--db", str(registry.path), "crossplay", "--metric", "WIN"]) == 2
    assert "metric must be one of" in capsys.readouterr().err


# ------------------------------------------------------- read-only reader
def _raw(path: Path, *statements: str) -> None:
    """Run SQL on a file directly (to make foreign, rollback-mode or damaged files)."""
    conn = sqlite3.connect(path)
    try:
        for statement in statements:
            conn.execute(statement)
        conn.commit()
    finally:
        conn.close()


def _files(folder: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_the_reader_refuses_an_empty_or_foreign_sqlite_file_and_leaves_it_byte_identical(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    for name, make in (("empty", lambda p: p.write_bytes(b"")), ("foreign", lambda p: _raw(p, "CREATE TABLE foo (x)"))):
        folder = tmp_path / name
        folder.mkdir()
        path = folder / "x.db"
        make(path)
        before = _files(folder)
        with pytest.raises(RegistryError, match="not an atdrone registry"):
            Registry(path, create=False)
        assert main(["registry", "--db", str(path), "list"]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and "not an atdrone registry" in err, err
        assert _files(folder) == before  # no WAL switch, no schema, no -wal/-shm files


def _skip_unless_permissions_apply(folder: Path) -> None:
    """Root (with its usual capabilities) writes anywhere, so a read-only folder proves nothing."""
    probe = folder / ".probe"
    try:
        probe.write_bytes(b"")
    except PermissionError:
        return
    probe.unlink()
    if os.geteuid() == 0:
        pytest.skip("running as root: file permissions are not enforced")
    raise AssertionError(f"{folder} is writable after chmod 555")


@pytest.mark.parametrize("journal", ["wal", "delete"])
def test_a_registry_it_may_not_write_can_be_listed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], journal: str
) -> None:
    folder = tmp_path / "ro"
    path = folder / "registry.db"
    with Registry(path) as reg:
        _add(reg, member_id="m1", metrics={"zoo1/SUC": 40.0})
    if journal == "delete":
        _raw(path, "PRAGMA journal_mode=DELETE")
    path.chmod(0o444)
    folder.chmod(0o555)
    try:
        _skip_unless_permissions_apply(folder)
        with Registry(path, create=False) as reader:
            assert reader.members()["id"].tolist() == ["m1"] and reader.journal_mode == journal
        assert main(["registry", "--db", str(path), "list"]) == 0
        out = capsys.readouterr().out
        assert out.splitlines()[1].split()[0] == "m1" and "40" in out
    finally:
        folder.chmod(0o755)
        path.chmod(0o644)


def test_reading_keeps_a_rollback_mode_registry_in_rollback_mode(tmp_path: Path) -> None:
    path = tmp_path / "registry.db"
    with Registry(path) as reg:
        _add(reg, member_id="m1")
    _raw(path, "PRAGMA journal_mode=DELETE")
    before = path.read_bytes()
    with Registry(path, create=False) as reader:
        assert reader.journal_mode == "delete" and reader.member("m1")["run"] == "hola-quick"
    assert main(["registry", "--db", str(path), "list"]) == 0
    conn = sqlite3.connect(path)
    try:
        assert conn.execute("PRAGMA journal_mode").fetchone()[0] == "delete"
    finally:
        conn.close()
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["registry.db"]


def test_a_reader_refuses_to_write_and_the_writer_still_writes(tmp_path: Path) -> None:
    path = tmp_path / "registry.db"
    with Registry(path) as writer:
        _add(writer, member_id="m1")
        with Registry(path, create=False) as reader:
            with pytest.raises(RegistryError, match="read-only"):
                _add(reader, member_id="m2")
            with pytest.raises(RegistryError, match="read-only"):
                reader.update_member("m1", status="retired")
            _add(writer, member_id="m3")  # the writer goes on while a reader is open
            assert reader.members()["id"].tolist() == ["m1", "m3"]
        assert writer.journal_mode == "wal"


def test_a_file_that_is_not_sqlite_is_refused_in_one_line_and_kept(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "notes.txt"
    path.write_text("these are my notes, not a database\n" * 10)
    before = path.read_bytes()
    assert main(["registry", "--db", str(path), "list"]) == 2
    assert (
        capsys.readouterr().err
        == f"atdrone registry: error: {path} is not a sqlite database, so not an atdrone registry\n"
    )
    with pytest.raises(RegistryError, match="not a sqlite database"):
        Registry(path)  # the writer does not clobber it either
    assert path.read_bytes() == before


@pytest.mark.parametrize(
    ("column", "text", "query", "expected"),
    [
        ("metrics", "not json {", "list", "metrics is not valid JSON"),
        ("parents", '"a"', "show", "parents is not a JSON list of member ids"),
        ("tags", "[1, 2]", "list", "tags is not a JSON object"),
    ],
)
def test_a_malformed_row_is_a_one_line_error_naming_the_row(
    registry: Registry, capsys: pytest.CaptureFixture[str], column: str, text: str, query: str, expected: str
) -> None:
    _add(registry, member_id="good")
    _add(registry, member_id="bad")
    _raw(registry.path, f"UPDATE members SET {column} = '{text}' WHERE id = 'bad'")
    with pytest.raises(RegistryError, match=f"members row 'bad': {expected}"):
        registry.members()
    argv = ["registry", "--db", str(registry.path), query] + (["bad"] if query == "show" else [])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert (
        err.count("\n") == 1 and err.startswith("atdrone registry: error: malformed registry row") and expected in err
    )


def test_list_refuses_an_unknown_status_in_one_line(registry: Registry, capsys: pytest.CaptureFixture[str]) -> None:
    _add(registry)
    assert main(["registry", "--db", str(registry.path), "list", "--status", "bogus"]) == 2
    assert capsys.readouterr().err == (
        "atdrone registry: error: status must be one of active, retired, missing, got 'bogus'\n"
    )
    with pytest.raises(RegistryError, match="status must be one of"):
        registry.members(status="bogus")


# ------------------------------------------------------------ list and show
LONG_CHECKPOINT = "/data/atdrone/runs/hola_quick_with_a_long_name/checkpoints/generation_0003/" + "x" * 120 + ".pt"


def _population(reg: Registry, run: str = "hola-quick") -> list[str]:
    """Three members with 200 training metrics each, eta, and zoo1/zoo2 SUC/COL on two of them."""
    train = {f"train/metric_{i:03d}": i / 7 for i in range(200)}
    first = _add(reg, 0, member_id=f"{run}-g0-0", run=run, metrics={**train, "eta": 0.25})
    second = _add(reg, 0, member_id=f"{run}-g0-1", run=run, metrics=train)
    child = _add(
        reg,
        1,
        (first, second),
        member_id=f"{run}-g1-0",
        run=run,
        checkpoint=LONG_CHECKPOINT,
        sha256="0123456789abcdef" * 4,
        metrics=train,
    )
    reg.update_member(first, metrics={"zoo1/SUC": 20.5, "zoo1/COL": 70.0, "zoo2/SUC": 11.0})
    reg.update_member(child, metrics={"zoo1/SUC": 31.25, "zoo1/COL": 60.0, "zoo2/SUC": 15.0, "zoo2/COL": 55.5})
    return [first, second, child]


def test_list_is_a_compact_table_that_fits_the_terminal(
    registry: Registry, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    ids = _population(registry)
    monkeypatch.setenv("COLUMNS", "140")
    assert main(["registry", "--db", str(registry.path), "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    header = ["id", "run", "algorithm", "generation", "status", "parents", "eta"]
    assert lines[0].split() == [*header, "zoo1/SUC", "zoo1/COL", "zoo2/SUC", "zoo2/COL"]
    assert len(lines) == 4 and all(len(line) <= 140 for line in lines)
    assert [line.split()[0] for line in lines[1:]] == ids
    assert lines[1].split()[6:] == ["0.25", "20.5", "70", "11", "-"]
    assert lines[3].split()[5:] == [f"{ids[0]},{ids[1]}", "-", "31.25", "60", "15", "55.5"]
    assert "train/" not in "\n".join(lines)

    monkeypatch.setenv("COLUMNS", "60")
    assert main(["registry", "--db", str(registry.path), "list"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert all(len(line) <= 60 for line in lines), lines
    assert [line.split()[0] for line in lines[1:4]] == ids  # ids are never cut
    assert lines[-1] == "(+6 columns: use --columns or --format csv)"


def test_list_columns_and_formats_give_every_value_in_full(
    registry: Registry, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import csv
    import io

    ids = _population(registry)
    monkeypatch.setenv("COLUMNS", "40")
    base = ["registry", "--db", str(registry.path), "list", "--columns", "id,checkpoint,zoo1/SUC,parents"]
    assert main([*base, "--format", "csv"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["id"] for r in rows] == ids and rows[2]["checkpoint"] == LONG_CHECKPOINT
    assert rows[0]["zoo1/SUC"] == "20.5" and rows[1]["zoo1/SUC"] == "" and json.loads(rows[2]["parents"]) == ids[:2]
    assert main([*base, "--format", "json"]) == 0
    records = json.loads(capsys.readouterr().out)
    assert list(records[2]) == ["id", "checkpoint", "zoo1/SUC", "parents"]
    assert records[2] == {"id": ids[2], "checkpoint": LONG_CHECKPOINT, "zoo1/SUC": 31.25, "parents": ids[:2]}
    assert records[1]["zoo1/SUC"] is None
    assert main(["registry", "--db", str(registry.path), "list", "--columns", "id,wins"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown column wins" in err


def test_show_prints_every_field_in_full(registry: Registry, capsys: pytest.CaptureFixture[str]) -> None:
    ids = _population(registry)
    registry.update_member(ids[2], tags={"role": "learner"})
    assert main(["registry", "--db", str(registry.path), "show", ids[2]]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert f"checkpoint: {LONG_CHECKPOINT}" in lines and f"sha256: {'0123456789abcdef' * 4}" in lines
    assert f"parents: {ids[0]}, {ids[1]}" in lines and "mlflow_run_id: (none)" in lines
    assert lines[lines.index("tags:") + 1] == "  role: learner"
    start = lines.index("metrics:") + 1
    metric_lines = lines[start : start + 204]
    assert [line.split(": ")[0].strip() for line in metric_lines] == sorted(registry.member(ids[2])["metrics"])
    assert "  zoo1/SUC: 31.25" in metric_lines and f"  train/metric_001: {1 / 7}" in metric_lines


def test_list_sorts_by_any_column_with_missing_values_last(
    registry: Registry, capsys: pytest.CaptureFixture[str]
) -> None:
    first, second, child = _population(registry)  # zoo1/SUC: 20.5, none, 31.25
    base = ["registry", "--db", str(registry.path), "list", "--columns", "id", "--format", "csv"]
    for extra, expected in (([], [first, child, second]), (["--desc"], [child, first, second])):
        assert main([*base, "--sort", "zoo1/SUC", *extra]) == 0  # a key outside --columns still orders the rows
        assert capsys.readouterr().out.split() == ["id", *expected]
    assert main(["registry", "--db", str(registry.path), "list", "--sort", "id", "--desc"]) == 0
    rows = [line for line in capsys.readouterr().out.splitlines()[1:] if not line.startswith("(")]  # "(+3 columns"
    assert [line.split()[0] for line in rows] == sorted([first, second, child], reverse=True)
    assert main([*base, "--sort", "wins"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown column wins" in err


def test_csv_from_list_and_export_is_tidy_one_column_per_metric(
    registry: Registry, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import csv
    import io

    ids = _population(registry)
    assert main(["registry", "--db", str(registry.path), "list", "--format", "csv"]) == 0
    listed = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    out = tmp_path / "members.csv"
    assert main(["registry", "--db", str(registry.path), "export", "--out", str(out)]) == 0
    exported = list(csv.DictReader(out.open()))
    for rows in (listed, exported):
        assert [r["id"] for r in rows] == ids and "metrics" not in rows[0]
        assert {"run", "generation", "parents", "checkpoint", "sha256", "tags", "eta", "zoo2/COL"} <= set(rows[0])
        assert len([k for k in rows[0] if k.startswith("train/")]) == 200
        assert (rows[0]["zoo1/SUC"], rows[2]["zoo2/COL"], rows[1]["zoo1/SUC"]) == ("20.5", "55.5", "")
        assert float(rows[2]["train/metric_007"]) == 1.0


def test_matches_lists_the_teams_filtered_by_member_and_sorted(
    played: tuple[Registry, str, str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    import csv
    import io

    registry, a, b, c = played
    base = ["registry", "--db", str(registry.path), "matches", "--format", "csv"]
    assert main(base) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [r["id"] for r in rows] == ["1", "2", "3", "4", "5"]
    assert rows[3]["team"] == f"{a},{b},{c},{c}" and rows[2]["seeds"] == "0,1" and rows[2]["AST"] == ""
    assert main([*base, "--member", c]) == 0
    assert [r["id"] for r in csv.DictReader(io.StringIO(capsys.readouterr().out))] == ["4"]
    assert main([*base, "--member", b, "--sort", "SUC", "--desc"]) == 0
    rows = list(csv.DictReader(io.StringIO(capsys.readouterr().out)))
    assert [float(r["SUC"]) for r in rows] == [90.0, 30.0, 10.0]
    assert main(["registry", "--db", str(registry.path), "matches", "--task", "4p2e1o"]) == 0
    assert capsys.readouterr().out.splitlines()[1].split()[:4] == ["5", "hola-quick", "1", "4p2e1o"]


def test_show_says_what_a_member_trained_against_and_its_budget(
    registry: Registry, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from atdrone.models.checkpoint import save_checkpoint
    from atdrone.models.networks import ActorCritic, NetConfig

    partners = {
        "kind": "Profiles",
        "members": ["p0", "p1", "p2"],
        "profiles": ["p0|p1", "p1|p2"],
        "probs": [0.75, 0.25],
    }
    path = tmp_path / "m.pt"
    header = {"task": TASK, "num_p": 4, "num_e": 2, "partners": partners, "step": 98_304, "seed": 3}
    save_checkpoint(path, ActorCritic(NetConfig(entity_dim=8, hidden=16)), header)
    member = registry.add_checkpoint(path, run="r", generation=2, member_id="hola-g2-0")
    registry.add_match([member, member, "p0", "p1"], TASK, "r", 2, [0], 12, _metrics(50.0))
    registry.add_match(["p0", "p0", "p1", "p1"], TASK, "r", 2, [0], 40, _metrics(50.0))
    assert main(["registry", "--db", str(registry.path), "show", member]) == 0
    out = capsys.readouterr().out
    assert "trained against:\n  kind: Profiles\n  profiles: p0|p1 (0.75), p1|p2 (0.25)\n  members: p0, p1, p2\n" in out
    assert "budget:\n  training env steps: 98,304 (seed 3)\n  evaluation: 1 match(es), 12 episodes" in out


# ---------------------------------------------------------------- discovery
def _runs_folder(root: Path) -> tuple[Path, Path]:
    """runs/hola_quick (zoo metrics, two finished generations) and runs/sp_base (none): two registries."""
    hola, sp = root / "runs" / "hola_quick" / "registry.db", root / "runs" / "sp_base" / "registry.db"
    with Registry(hola) as reg:
        for idx in (0, 1, 2):
            reg.start_generation("hola_quick", idx)
        reg.finish_generation("hola_quick", 0)
        reg.finish_generation("hola_quick", 1)
        _population(reg, run="hola_quick")
    with Registry(sp) as reg:
        _add(reg, 0, member_id="sp-g0-0", run="sp_base", algorithm="sp", task="4p2e1o")
        _add(reg, 1, ("sp-g0-0",), member_id="sp-g1-0", run="sp_base", algorithm="sp", task="4p2e1o")
        reg.start_generation("sp_base", 0)
        reg.finish_generation("sp_base", 0)
    return hola, sp


@pytest.fixture
def in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Work in tmp_path with no $ATDRONE_REGISTRY and no terminal width limit."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("ATDRONE_REGISTRY", raising=False)
    monkeypatch.delenv("COLUMNS", raising=False)
    return tmp_path


def test_runs_lists_the_registries_under_runs_with_their_best_member(
    in_tmp: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    hola, sp = _runs_folder(in_tmp)
    assert main(["registry", "runs"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].split() == ["run", "algorithm", "task", "generations", "members", "best", "best_by", "registry"]
    hola, sp = hola.relative_to(in_tmp), sp.relative_to(in_tmp)
    assert lines[1].split() == ["hola_quick", "hola", TASK, "2", "3", "hola_quick-g1-0", "zoo1/SUC", "31.25", str(hola)]
    assert lines[2].split() == ["sp_base", "sp", "4p2e1o", "1", "2", "sp-g1-0", "last", "member", str(sp)]
    assert main(["registry", "runs", "--format", "json", "--runs-dir", str(in_tmp / "runs")]) == 0
    records = json.loads(capsys.readouterr().out)
    assert [(r["run"], r["generations"], r["members"], r["best"]) for r in records] == [
        ("hola_quick", 2, 3, "hola_quick-g1-0"),
        ("sp_base", 1, 2, "sp-g1-0"),
    ]


def test_without_db_list_reads_every_registry_and_the_others_need_one(
    in_tmp: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    hola, sp = _runs_folder(in_tmp)
    assert main(["registry", "list"]) == 0
    rows = [line.split()[:2] for line in capsys.readouterr().out.splitlines()[1:]]
    assert [run for _, run in rows] == ["hola_quick"] * 3 + ["sp_base"] * 2
    for argv in (["crossplay"], ["export", "--out", "m.csv"]):
        assert main(["registry", *argv]) == 2
        assert capsys.readouterr().err == (
            f"atdrone registry: error: several registries under runs/: pass --run RUN or --db FILE "
            f"({hola.relative_to(in_tmp)}, "
            f"{sp.relative_to(in_tmp)})\n"
        )
    # a member id is looked up in every registry found: the one that holds it answers
    assert main(["registry", "show", "sp-g0-0"]) == 0
    assert "algorithm: sp" in capsys.readouterr().out
    assert main(["registry", "lineage", "sp-g1-0"]) == 0
    assert capsys.readouterr().out.splitlines()[1].split()[0] == "sp-g1-0"
    assert main(["registry", "show", "sp-g0-0", "--db", str(sp)]) == 0
    assert "algorithm: sp" in capsys.readouterr().out
    assert main(["registry", "show", "sp-g0-0", "--db", str(hola)]) == 2
    assert capsys.readouterr().err == f"atdrone registry: error: no member 'sp-g0-0' in the registry at {hola}\n"
    assert not (in_tmp / "m.csv").exists()


def test_without_db_one_registry_is_used_and_none_is_a_clear_error(
    in_tmp: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    assert main(["registry", "list"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--db" in err and "`atdrone registry runs`" in err
    assert main(["registry", "runs"]) == 0
    assert capsys.readouterr().out.startswith("(no registries under runs/")
    with Registry(in_tmp / "runs" / "only" / "registry.db") as reg:
        _add(reg, member_id="m1", run="only")
    assert main(["registry", "show", "m1"]) == 0
    assert "run: only" in capsys.readouterr().out
    assert main(["registry", "lineage", "m1"]) == 0
    assert capsys.readouterr().out.splitlines()[1].split()[0] == "m1"
    elsewhere = in_tmp / "elsewhere.db"
    with Registry(elsewhere) as reg:
        _add(reg, member_id="env-member")
    monkeypatch.setenv("ATDRONE_REGISTRY", str(elsewhere))  # the environment wins over discovery
    assert main(["registry", "list"]) == 0
    assert capsys.readouterr().out.splitlines()[1].split()[0] == "env-member"


def test_list_over_several_registries_skips_an_unreadable_one_with_a_warning(
    in_tmp: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _runs_folder(in_tmp)
    broken = in_tmp / "runs" / "broken" / "registry.db"
    broken.parent.mkdir()
    broken.write_text("not sqlite")
    assert main(["registry", "list"]) == 0
    captured = capsys.readouterr()
    assert len(captured.out.splitlines()) == 6
    assert captured.err == (
        "atdrone registry: warning: skipped runs/broken/registry.db: "
        "runs/broken/registry.db is not a sqlite database, so not an atdrone registry\n"
    )


# ---------------------------------------------------------------------- Ray
@pytest.fixture
def ray_cluster(local_ray):
    """The session's Ray (tests/conftest.py), as the ray module."""
    import ray

    return ray


def test_actor_serves_the_registry_and_a_second_driver_finds_it_by_name(ray_cluster, tmp_path: Path) -> None:
    from atdrone.registry import REGISTRY_NAMESPACE
    from atdrone.registry_ray import RegistryActor, registry_actor

    ray = ray_cluster
    path = tmp_path / "served.db"
    actor = registry_actor(path, name="registry-test")
    try:
        assert isinstance(actor, ray.actor.ActorHandle) and RegistryActor is not None
        mid = ray.get(actor.add_member.remote(run="svc", algorithm="hola", generation=0, task=TASK, tags={"k": 1}))
        ray.get(actor.add_match.remote([mid], TASK, "svc", 0, [0], 4, RESULT))
        assert ray.get(actor.member.remote(mid))["tags"] == {"k": 1}
        assert ray.get(actor.crossplay.remote())[mid][mid] == RESULT["SUC"]
        with pytest.raises(KeyError):
            ray.get(actor.member.remote("ghost"))
        with Registry(path, create=False) as direct:  # written through to the file
            assert direct.member(mid)["run"] == "svc"
        assert registry_actor(path, name="registry-test")._actor_id == actor._actor_id  # get-or-create
        with pytest.raises(RegistryError, match="already serves"):
            registry_actor(tmp_path / "other.db", name="registry-test")

        code = (
            "import ray\n"
            f"ray.init(address={ray.get_runtime_context().gcs_address!r}, log_to_driver=False)\n"
            f"actor = ray.get_actor('registry-test', namespace={REGISTRY_NAMESPACE!r})\n"
            f"print('ALGORITHM', ray.get(actor.member.remote({mid!r}))['algorithm'])\n"
        )
        env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
        second = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, env=env)
        assert second.returncode == 0, second.stderr[-2000:]
        assert "ALGORITHM hola" in second.stdout
    finally:
        ray.kill(actor, no_restart=True)


def test_killed_actor_restarts_and_reloads_the_members_from_sqlite(ray_cluster, tmp_path: Path) -> None:
    from atdrone.registry_ray import registry_actor

    ray = ray_cluster
    actor = registry_actor(tmp_path / "restart.db", name="registry-restart")
    try:
        ids = [ray.get(actor.add_member.remote(run="svc", algorithm="sp", generation=g, task=TASK)) for g in range(3)]
        pid = ray.get(actor.__ray_call__.remote(lambda self: os.getpid()))
        ray.kill(actor, no_restart=False)
        deadline = time.monotonic() + 30  # the kill is asynchronous: wait for the new process
        while ray.get(actor.__ray_call__.remote(lambda self: os.getpid())) == pid:
            assert time.monotonic() < deadline, "the registry actor was not restarted"
            time.sleep(0.05)
        assert ray.get(actor.members.remote())["id"].tolist() == ids  # the new process reads every member back
        assert ray.get(actor.last_completed_generation.remote("svc")) is None
    finally:
        ray.kill(actor, no_restart=True)


def _die_after_the_next_commit(registry: Registry) -> None:
    """In the actor's process: its next write transaction commits, then the process dies before replying."""
    write = registry._write

    @contextmanager
    def commit_then_die() -> Iterator[sqlite3.Connection]:
        with write() as conn:
            yield conn
        os._exit(1)

    registry._write = commit_then_die  # type: ignore[method-assign]


def test_a_write_replayed_by_ray_after_the_actor_died_is_recorded_once(ray_cluster, tmp_path: Path) -> None:
    """The actor dies after committing and before replying; Ray restarts it and retries the call (as it does
    for every call in flight): add_member returns its id, add_match the first match's id, nothing doubles."""
    from atdrone.registry_ray import registry_actor

    ray = ray_cluster
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])  # the patch travels by value
    actor = registry_actor(tmp_path / "replay.db", name="registry-replay")
    try:
        pid = ray.get(actor.__ray_call__.remote(lambda self: os.getpid()))
        ray.get(actor.__ray_call__.remote(_die_after_the_next_commit))
        mid = ray.get(actor.add_member.remote(run="svc", algorithm="sp", generation=0, task=TASK, member_id="sp-g0-0"))
        assert mid == "sp-g0-0"
        restarted = ray.get(actor.__ray_call__.remote(lambda self: os.getpid()))
        assert restarted != pid  # the first attempt's process died: the answer came from the retry
        ray.get(actor.__ray_call__.remote(_die_after_the_next_commit))
        match = ray.get(actor.add_match.remote([mid], TASK, "svc", 0, [3], 4, RESULT))
        assert ray.get(actor.__ray_call__.remote(lambda self: os.getpid())) not in (pid, restarted)
        with Registry(tmp_path / "replay.db", create=False) as reg:
            assert reg.members()["id"].tolist() == [mid]
            assert reg.matches()["id"].tolist() == [match] == [1]
    finally:
        ray.kill(actor, no_restart=True)
