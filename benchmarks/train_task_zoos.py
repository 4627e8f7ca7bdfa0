"""Train every trained partner drone of the zoos, the validation zoo and the default pool, per task.

    python benchmarks/train_task_zoos.py [--tasks 4p2e3o ...] [--jobs 2] [--only NAME ...]

One recipe per drone (configs/train/<name>.json, written for 4p2e1o) is trained on each task with
``atdrone train --task``. The drone lands in configs/zoos/checkpoints/<task>/<name>.pt (pool drones:
configs/pools/checkpoints/<task>/<name>.pt), where the zoo documents' ``{task}`` paths find it.

Skill levels per task (the rule): the recipes stop at a self-play SUC (``stop_at_suc``), set for
4p2e1o. On a task where self-play does not reach those levels they are scaled by
``r = min(1, L / 70)``, where ``L`` is the SUC that the ``sp_high`` recipe (seed 1, stop at 70 %)
reaches within the paper's budget, 1,048,576 env steps (its run is capped there). ``sp_high`` is
trained first on every task; ``r`` and ``L`` are written to
configs/zoos/checkpoints/<task>/levels.json. Every other recipe keeps its own budget (3M env steps).

Resumable: a drone whose file exists is skipped; an interrupted run resumes from its last
checkpoint (runs live in runs_partners/<task>/<name>/). Each finished drone's cost (env steps,
wall seconds) is appended to benchmarks/results/task_zoos_cost.jsonl. Meant for the background:
``nohup nice -n 10 .venv/bin/python benchmarks/train_task_zoos.py &``.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TASKS = ("4p2e1o", "4p2e3o", "4p2e5o", "4p3e5o")
PAPER_BUDGET = 1_048_576
HIGH_LEVEL = 70.0
REFERENCE = "sp_high"
# recipe -> where its drone goes (the zoos' folder or the pool's)
ZOO_RECIPES = ("sp_high", "sp_low", "val_sp_s5", "val_sp_s6")
ZOO4_RECIPES = ("zoo4_mappo", "zoo4_wide", "zoo4_entropy", "zoo4_own_credit", "zoo4_br_greedy", "zoo4_narrow")
POOL_RECIPES = ("pool_sp_s3", "pool_sp_s4")
RECIPES = ZOO_RECIPES + POOL_RECIPES + ZOO4_RECIPES
COST_LOG = ROOT / "benchmarks" / "results" / "task_zoos_cost.jsonl"


def destination(task: str, name: str) -> Path:
    folder = "pools" if name in POOL_RECIPES else "zoos"
    return ROOT / "configs" / folder / "checkpoints" / task / f"{name}.pt"


def levels_path(task: str) -> Path:
    return ROOT / "configs" / "zoos" / "checkpoints" / task / "levels.json"


def read_levels(task: str) -> dict | None:
    path = levels_path(task)
    return json.loads(path.read_text()) if path.is_file() else None


def atomic_write(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def header(path: Path) -> dict:
    with path.open("rb") as f:
        f.readline()
        return json.loads(f.readline())


def write_levels(task: str) -> dict:
    """L and r of a task from its finished sp_high drone."""
    head = header(destination(task, REFERENCE))
    suc = float(head["metrics"]["eval/SUC"])
    level = min(HIGH_LEVEL, suc)
    doc = {
        "task": task,
        "reference": REFERENCE,
        "reference_sha256": head["sha256"],
        "env_steps": int(head.get("step", 0)),
        "L": round(level, 3),
        "r": round(min(1.0, level / HIGH_LEVEL), 4),
        "rule": "r = min(1, L / 70); L = sp_high's self-play SUC within 1,048,576 env steps; "
        "every recipe's stop_at_suc is multiplied by r",
    }
    atomic_write(levels_path(task), json.dumps(doc, indent=2) + "\n")
    return doc


def task_config(task: str, name: str, r: float) -> dict:
    recipe = json.loads((ROOT / "configs" / "train" / f"{name}.json").read_text())
    recipe.update(task=task, torch_threads=1, update_threads=1)
    if name == REFERENCE and task != "4p2e1o":
        recipe["total_env_steps"] = PAPER_BUDGET
    recipe["stop_at_suc"] = round(float(recipe.get("stop_at_suc", 0.0)) * r, 2)
    return recipe


def train(task: str, name: str, r: float, log: Path) -> None:
    runs = ROOT / "runs_partners" / task
    runs.mkdir(parents=True, exist_ok=True)
    config = runs / f"{name}.json"
    atomic_write(config, json.dumps(task_config(task, name, r), indent=2) + "\n")
    cmd = [str(Path(sys.executable).parent / "atdrone"), "train", str(config), "--out-dir", str(runs), "--no-progress"]
    if (runs / name).is_dir():
        cmd.append("--resume")
    env = dict(os.environ, MLFLOW_TRACKING_URI=f"sqlite:///{runs / 'mlflow.db'}", OMP_NUM_THREADS="1")
    start = time.time()
    with log.open("a") as out:
        out.write(f"\n=== {time.strftime('%F %T')} {task}/{name}: {' '.join(cmd)}\n")
        out.flush()
        subprocess.run(cmd, cwd=ROOT, env=env, stdout=out, stderr=subprocess.STDOUT, check=True)
    dest = destination(task, name)
    dest.parent.mkdir(parents=True, exist_ok=True)
    tmp = dest.with_suffix(".pt.tmp")
    tmp.write_bytes((runs / name / "last.pt").read_bytes())
    os.replace(tmp, dest)
    head = header(dest)
    record = {
        "task": task,
        "name": name,
        "env_steps": int(head.get("step", 0)),
        "wall_s_this_session": round(time.time() - start, 1),
        "stop_at_suc": head["config"]["stop_at_suc"],
        "SUC": head["metrics"].get("eval/SUC"),
        "sha256": head["sha256"],
        "finished": time.strftime("%FT%T"),
    }
    with COST_LOG.open("a") as f:
        f.write(json.dumps(record) + "\n")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=TASKS)
    parser.add_argument("--only", nargs="+", default=list(RECIPES), choices=RECIPES)
    parser.add_argument("--jobs", type=int, default=2, help="runs at a time (one core each)")
    parser.add_argument("--log", type=Path, default=ROOT / "runs_partners" / "train_task_zoos.log")
    args = parser.parse_args()
    args.log.parent.mkdir(parents=True, exist_ok=True)
    # sp_high of every task first (it sets the task's levels), then the rest recipe by recipe
    todo = [(t, n) for n in RECIPES for t in args.tasks if n in args.only and not destination(t, n).is_file()]
    lock = threading.Lock()
    running: set[tuple[str, str]] = set()
    failed: list[str] = []

    def ready(task: str, name: str) -> float | None:
        if name == REFERENCE:
            return 1.0
        if read_levels(task) is None and destination(task, REFERENCE).is_file():
            write_levels(task)
        levels = read_levels(task)
        return None if levels is None else float(levels["r"])

    def worker() -> None:
        while True:
            with lock:
                pick = None
                for item in list(todo):
                    if destination(*item).is_file():  # made meanwhile (another invocation)
                        todo.remove(item)
                        continue
                    r = ready(*item)
                    if r is not None:
                        pick = (item, r)
                        break
                if pick is None:
                    if not todo or not running:
                        return
                else:
                    todo.remove(pick[0])
                    running.add(pick[0])
            if pick is None:
                time.sleep(5)
                continue
            (task, name), r = pick
            print(f"{time.strftime('%T')} start {task}/{name} (r={r})", flush=True)
            try:
                train(task, name, r, args.log)
                if name == REFERENCE:
                    write_levels(task)
                print(f"{time.strftime('%T')} done {task}/{name}", flush=True)
            except subprocess.CalledProcessError as exc:
                failed.append(f"{task}/{name}")
                print(f"{time.strftime('%T')} FAILED {task}/{name}: exit {exc.returncode} (see {args.log})", flush=True)
            finally:
                with lock:
                    running.discard((task, name))

    threads = [threading.Thread(target=worker) for _ in range(max(1, args.jobs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    print(f"left: {len(todo)}; failed: {failed or 'none'}")
    return 1 if failed or todo else 0


if __name__ == "__main__":
    sys.exit(main())
