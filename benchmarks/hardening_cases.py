"""Bad inputs and planted files against two checkouts of atdrone: how each command answers, before and after.

    python benchmarks/hardening_cases.py --before /tmp/old-checkout --after . [--out cases.json]

Each case builds its files in a fresh temporary folder and runs ``python -m atdrone.cli
...`` with ``PYTHONPATH`` set to the checkout (same virtual environment), with a time
limit. It records the exit code, whether a traceback was printed, the last stderr line,
and a side-effect check where the case has one (a planted pickle executed, a file
modified, a file written outside the output folder). Prints JSON (and a markdown table
with --table); nothing here is a timed test.
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import sqlite3
import subprocess
import sys
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
TINY_PPO = {"num_envs": 8, "rollout_steps": 32, "minibatch_size": 256, "entity_dim": 16, "hidden": 32}
DUPLICATE_KEY = b'{"name": "a", "name": "b", "task": "4p2e1o", "total_env_steps": 256, "eval_every": 1000}'
TINY_TRAIN = {"name": "tiny", "task": "4p2e1o", "total_env_steps": 256, "eval_every": 1000, "eval_episodes": 2}


@dataclass
class Case:
    """A bad input: ``build(tmp) -> argv`` makes its files; ``effect(tmp) -> str`` reports a side effect."""

    name: str
    build: Callable[[Path], list[str]]
    effect: Callable[[Path], str] | None = None
    timeout_s: float = 90.0


class _Touch:
    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self) -> tuple:
        return (Path.touch, (Path(self.path),))


def _json(tmp: Path, name: str, doc: object) -> str:
    path = tmp / name
    path.write_text(json.dumps(doc))
    return str(path)


def _planted_pickle(tmp: Path) -> list[str]:
    run_dir = tmp / "runs" / "tiny"
    run_dir.mkdir(parents=True)
    (run_dir / "trainer_state.pt").write_bytes(pickle.dumps({"optimizer": _Touch(str(tmp / "EXECUTED"))}))
    return ["train", _json(tmp, "t.json", {**TINY_TRAIN, "out_dir": str(tmp / "runs")}), "--resume", "--no-progress"]


def _executed(tmp: Path) -> str:
    return "planted code ran" if (tmp / "EXECUTED").exists() else "not run"


def _eval_out(tmp: Path) -> list[str]:
    """The evaluate output folder flag of the checkout under test (--out before it became --out-dir)."""
    text = subprocess.run(
        [sys.executable, "-m", "atdrone.cli", "evaluate", "--help"],
        capture_output=True,
        text=True,
        env=os.environ.copy(),
        cwd=tmp,
        check=False,
    ).stdout
    return ["--out-dir" if "--out-dir" in text else "--out", str(tmp / "e")]


def _policy(tmp: Path) -> Path:
    """A tiny 4p2e1o checkpoint (trained for one update by the checkout under test)."""
    doc = {**TINY_TRAIN, "out_dir": str(tmp / "runs"), "ppo": TINY_PPO}
    subprocess.run(
        [sys.executable, "-m", "atdrone.cli", "train", _json(tmp, "p.json", doc), "--no-progress"],
        capture_output=True,
        timeout=120,
        env=os.environ.copy(),
        cwd=tmp,
        check=False,
    )
    return tmp / "runs" / "tiny" / "last.pt"


def _edited_header(tmp: Path) -> list[str]:
    path = _policy(tmp)
    data = path.read_bytes()
    path.write_bytes(data.replace(b'"task": "4p2e1o"', b'"task": "4p2e3o"', 1))
    return [
        "evaluate",
        "--policy",
        str(path),
        "--task",
        "4p2e3o",
        "--zoo",
        "zoo1",
        "--episodes",
        "2",
        *_eval_out(tmp),
        "--no-progress",
    ]


def _other_layout(tmp: Path) -> list[str]:
    return [
        "evaluate",
        "--policy",
        str(_policy(tmp)),
        "--task",
        "4p3e5o",
        "--zoo",
        "zoo1",
        "--episodes",
        "2",
        *_eval_out(tmp),
        "--no-progress",
    ]


def _huge_network(tmp: Path) -> list[str]:
    header = {
        "format": 2,
        "architecture": {"class": "ActorCritic", "entity_dim": 1_000_000, "hidden": 1_000_000},
        "obs_layout_version": 2,
        "task": "4p2e1o",
        "num_p": 4,
        "num_e": 2,
        "sha256": "0" * 64,
    }
    path = tmp / "huge.pt"
    path.write_bytes(b"ATDRONE-CHECKPOINT 1\n" + json.dumps(header).encode() + b"\n" + b"\0" * 400)
    return [
        "evaluate",
        "--policy",
        str(path),
        "--task",
        "4p2e1o",
        "--zoo",
        "zoo1",
        "--episodes",
        "2",
        *_eval_out(tmp),
        "--no-progress",
    ]


def _escaping_name(tmp: Path) -> list[str]:
    (tmp / "runs").mkdir()
    doc = {**TINY_TRAIN, "name": "../escaped", "out_dir": str(tmp / "runs"), "ppo": TINY_PPO}
    return ["train", _json(tmp, "t.json", doc), "--no-progress"]


def _escaped(tmp: Path) -> str:
    return "wrote outside runs/" if (tmp / "escaped").exists() else "nothing outside"


def _empty_sqlite(tmp: Path) -> list[str]:
    path = tmp / "empty.db"
    sqlite3.connect(path).close()
    (tmp / "size").write_text(str(path.stat().st_size) + " " + path.read_bytes().hex())
    return ["registry", "--db", str(path), "list"]


def _modified(tmp: Path) -> str:
    path = tmp / "empty.db"
    same = (tmp / "size").read_text() == str(path.stat().st_size) + " " + path.read_bytes().hex()
    return "file unchanged" if same else "file modified"


def _evaluate(*extra: str) -> Callable[[Path], list[str]]:
    def build(tmp: Path) -> list[str]:
        return [
            "evaluate",
            "--policy",
            "greedy",
            "--task",
            "4p2e1o",
            "--zoo",
            "zoo1",
            *_eval_out(tmp),
            "--no-progress",
            *extra,
        ]

    return build


def _task(**fields: object) -> Callable[[Path], list[str]]:
    def build(tmp: Path) -> list[str]:
        doc = json.loads((REPO / "configs" / "tasks" / "4p2e1o.json").read_text())
        for key, value in fields.items():
            section, _, leaf = key.partition(".")
            if leaf:
                doc[section][leaf] = value
            else:
                doc[key] = value
        return ["render", "--task", _json(tmp, "task.json", doc), "--out", str(tmp / "x.gif"), "--max-steps", "2"]

    return build


def _train_raw(content: bytes) -> Callable[[Path], list[str]]:
    def build(tmp: Path) -> list[str]:
        path = tmp / "c.json"
        path.write_bytes(content)
        return ["train", str(path), "--no-progress"]

    return build


def _train(**fields: object) -> Callable[[Path], list[str]]:
    def build(tmp: Path) -> list[str]:
        doc = {**TINY_TRAIN, "out_dir": str(tmp / "runs"), "ppo": TINY_PPO, **fields}
        return ["train", _json(tmp, "t.json", doc), "--no-progress"]

    return build


def _bad_state(tmp: Path) -> list[str]:
    run_dir = tmp / "runs" / "hq"
    run_dir.mkdir(parents=True)
    (run_dir / "service_state.json").write_text("{not json")
    doc = json.loads((REPO / "configs" / "experiments" / "hola_quick.json").read_text())
    doc.update({"name": "hq", "out_dir": str(tmp / "runs")})
    return ["train", _json(tmp, "x.json", doc), "--resume", "--no-progress"]


def _directory_policy(tmp: Path) -> list[str]:
    (tmp / "adir").mkdir()
    return ["evaluate", "--policy", str(tmp / "adir"), "--task", "4p2e1o", "--zoo", "zoo1", *_eval_out(tmp)]


CASES = [
    Case("resume a run dir with a planted pickle", _planted_pickle, _executed),
    Case("checkpoint header edited (task)", _edited_header),
    Case("policy of 4p2e1o evaluated on 4p3e5o", _other_layout),
    Case("600-byte checkpoint declaring a huge network", _huge_network, timeout_s=60),
    Case("run name ../escaped", _escaping_name, _escaped),
    Case("registry list on an empty sqlite file", _empty_sqlite, _modified),
    Case(
        "registry list --status bogus", lambda t: ["registry", "--db", str(_registry(t)), "list", "--status", "bogus"]
    ),
    Case("registry --db a text file", lambda t: ["registry", "--db", _json(t, "x.txt", "hello"), "list"]),
    Case("evaluate --episodes 10**9", _evaluate("--episodes", str(10**9)), timeout_s=30),
    Case("evaluate --seeds -1", _evaluate("--episodes", "2", "--seeds", "-1")),
    Case("evaluate --seeds 0 0", _evaluate("--episodes", "2", "--seeds", "0", "0")),
    Case("task with horizon 10**12", _task(**{"task.task_horizon": 10**12}), timeout_s=30),
    Case("task with num_e 10**9", _task(**{"players.num_e": 10**9}), timeout_s=30),
    Case("task with num_ctrl 0", _task(**{"players.num_ctrl": 0, "players.num_unctrl": 4})),
    Case("train config not UTF-8", _train_raw(b'{"name": "\xff\xfe"}')),
    Case("train config a JSON list", _train_raw(b"[1, 2]")),
    Case("train config nested 100000 deep", _train_raw(b"[" * 100_000 + b"]" * 100_000)),
    Case("train config with a duplicate key", _train_raw(DUPLICATE_KEY)),
    Case("train config seed -1", _train(seed=-1)),
    Case("train config device banana", _train(device="banana")),
    Case("train config hidden 10**6", _train(ppo={**TINY_PPO, "hidden": 10**6}), timeout_s=60),
    Case("resume with a corrupted service_state.json", _bad_state),
    Case("evaluate a policy path that is a directory", _directory_policy),
    Case("atdrone --version", lambda t: ["--version"]),
]


def _registry(tmp: Path) -> Path:
    path = tmp / "r.db"
    code = f"from atdrone.registry import Registry; Registry({str(path)!r}).close()"
    subprocess.run([sys.executable, "-c", code], check=True, env=os.environ.copy(), cwd=tmp, timeout=60)
    return path


def run_case(case: Case, checkout: Path) -> dict[str, object]:
    """Run one case against ``checkout``: exit code, traceback?, last stderr line, side effect."""
    env = {**os.environ, "PYTHONPATH": str(checkout), "MLFLOW_TRACKING_URI": ""}
    with tempfile.TemporaryDirectory() as folder:
        tmp = Path(folder)
        env["MLFLOW_TRACKING_URI"] = f"sqlite:///{tmp}/mlflow.db"
        os.environ.update({"PYTHONPATH": str(checkout), "MLFLOW_TRACKING_URI": env["MLFLOW_TRACKING_URI"]})
        argv = case.build(tmp)
        try:
            proc = subprocess.run(
                [sys.executable, "-m", "atdrone.cli", *argv],
                capture_output=True,
                text=True,
                timeout=case.timeout_s,
                env=env,
                cwd=tmp,
            )
            rc: object = proc.returncode
            err = proc.stderr.strip().splitlines()
            last = err[-1] if err else proc.stdout.strip().splitlines()[-1:] or [""]
            out = {
                "rc": rc,
                "traceback": "Traceback" in proc.stderr,
                "message": str(last if isinstance(last, str) else last[0])[:160],
            }
        except subprocess.TimeoutExpired:
            out = {"rc": f"timeout {case.timeout_s:g}s", "traceback": False, "message": "(still running)"}
        if case.effect is not None:
            out["effect"] = case.effect(tmp)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--before", type=Path, required=True, help="checkout of the old code")
    parser.add_argument("--after", type=Path, default=REPO, help="checkout of the new code (default: this one)")
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    parser.add_argument("--table", action="store_true", help="print a markdown table after the JSON")
    args = parser.parse_args()
    rows = []
    for case in CASES:
        row = {"case": case.name, "before": run_case(case, args.before), "after": run_case(case, args.after)}
        print(json.dumps(row), file=sys.stderr, flush=True)
        rows.append(row)
    text = json.dumps(rows, indent=2)
    print(text)
    if args.out:
        args.out.write_text(text)
    if args.table:
        print("\n| case | before | after |\n|---|---|---|")
        for row in rows:
            cells = []
            for side in ("before", "after"):
                r = row[side]
                tb = ", traceback" if r["traceback"] else ""
                effect = f"; {r['effect']}" if "effect" in r else ""
                cells.append(f"exit {r['rc']}{tb}{effect}: {str(r['message']).replace('|', '/')}")
            print(f"| {row['case']} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
