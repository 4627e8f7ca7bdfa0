"""A zoo whose checkpoint file is absent, through the evaluation entry points that promise to skip it.

The committed zoos have all their checkpoints, so the ``zoo.missing`` branches run only with a zoo
document of the test's own (in tmp_path) that names a file that is not there. ``atdrone evaluate`` and
``jobs/evaluate.py`` promise to skip such a zoo's cells with a warning naming the missing members (and
to refuse, with an error, when no zoo is left). The service's coordinator is tested in test_service.py.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from conftest import missing_zoo

from atdrone.cli import main
from atdrone.config import load_task
from atdrone.policies import zoo as zoo_module
from atdrone.policies.zoo import ZooError, load_zoo

REPO = Path(__file__).resolve().parent.parent


def _short_task(tmp_path: Path) -> Path:
    doc = load_task("4p2e1o").to_dict()
    doc["task"]["task_horizon"] = 30
    path = tmp_path / "task.json"
    path.write_text(json.dumps(doc))
    return path


def test_the_zoo_loads_names_its_missing_member_and_refuses_to_play(tmp_path):
    zoo = load_zoo(missing_zoo(tmp_path))
    assert zoo.names == ["greedy", "ghost"] and zoo.missing == ["ghost"]
    with pytest.raises(ZooError, match=rf"zoo 'ghosts' is incomplete: 'ghost' needs {tmp_path}/ghost\.pt"):
        zoo.policies()


@pytest.mark.parametrize("entry", ["atdrone evaluate", "jobs/evaluate.py"])
def test_evaluate_all_zoos_plays_the_complete_one_and_skips_the_incomplete_one_saying_so(
    entry, tmp_path, capsys, monkeypatch, load_script
):
    """--zoo all with zoo1 and the incomplete zoo: zoo1's cell is played, the other is listed as missing
    (table, JSON report) and a warning names the missing member."""
    ghosts, load = missing_zoo(tmp_path), zoo_module.load_zoo
    monkeypatch.setattr(zoo_module, "ZOO_NAMES", ("zoo1", "ghosts"))  # "all": zoo1 and the incomplete zoo
    monkeypatch.setattr(
        zoo_module, "load_zoo", lambda name, task=None: load(ghosts if name == "ghosts" else name, task)
    )
    out = tmp_path / "out"
    args = ["--policy", "greedy", "--task", str(_short_task(tmp_path)), "--zoo", "all", "--episodes", "3"]
    if entry == "atdrone evaluate":
        rc = main(["evaluate", *args, "--out-dir", str(out), "--no-progress"])
        warning = "atdrone evaluate: warning: zoo ghosts is missing ghost; its cells are skipped"
    else:
        rc = load_script(REPO / "jobs" / "evaluate.py").main([*args, "--out-dir", str(out)])
        warning = "jobs/evaluate.py: warning: zoo ghosts is missing ghost; skipped"
    captured = capsys.readouterr()
    assert rc == 0, captured.err
    assert captured.err.splitlines() == [warning]
    lines = captured.out.splitlines()
    header, row = lines[2].split(), lines[4].split()
    assert header == ["task", "metric", "zoo1", "ghosts"]
    assert row[:3] == ["4p2e1o", "SUC", "%"] and row[-2:] == ["missing:", "ghost"]  # zoo1 played, ghosts not
    if entry == "jobs/evaluate.py":
        assert "greedy evaluated on 1 of 2 task x zoo cells, 3 episodes" in captured.out
    doc = json.loads((out / "greedy_4p2e1o_all.json").read_text())
    assert [(c["zoo"], c["status"], c.get("missing")) for c in doc["cells"]] == [
        ("zoo1", "ok", None),
        ("ghosts", "missing", ["ghost"]),
    ]
    assert doc["cells"][0]["summary"]["episodes"] == 3


def test_jobs_evaluate_with_only_an_incomplete_zoo_refuses_in_one_line(tmp_path, capsys, load_script):
    """The job's counterpart of the CLI's refusal (tested in test_inputs.py): usage status 2, a warning
    and one error line, and no report written."""
    job = load_script(REPO / "jobs" / "evaluate.py")
    out = tmp_path / "out"
    rc = job.main(["--policy", "greedy", "--zoo", str(missing_zoo(tmp_path)), "--episodes", "2", "--out-dir", str(out)])
    err = capsys.readouterr().err.splitlines()
    assert rc == job.EXIT_USAGE == 2
    assert err == [
        "jobs/evaluate.py: warning: zoo ghosts is missing ghost; skipped",
        "jobs/evaluate.py: error: no zoo has all its members (ghosts); nothing to evaluate",
    ]
    assert not out.exists()
