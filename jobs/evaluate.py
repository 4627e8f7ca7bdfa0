"""Ray job entrypoint: evaluate one policy with a zoo of unseen partners on one task.

    ray job submit --address http://HEAD:8265 --working-dir . -- \
        python jobs/evaluate.py --policy greedy|vicsek|PATH --task 4p2e1o --zoo zoo1 --episodes 500 --out DIR

Plays --episodes episodes per seed with the policy in the task's learner slots and
partners drawn from the zoo (``atdrone.evaluation.evaluate``), prints SUC / COL / AST /
REW and writes ``DIR/<policy>_<task>_<zoo>.json`` (summary and per-seed metrics) and
``.csv`` (one row per episode). The evaluation runs in the job's driver process; on a
cluster, give --out a path on storage that you can read afterwards. Bad input exits
with status 2 and a one-line error.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parent.parent
if str(REPO_ROOT) not in sys.path:  # `--working-dir .` on nodes that only have the dependencies
    sys.path.insert(0, str(REPO_ROOT))

PROG = "jobs/evaluate.py"
EXIT_USAGE = 2


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=PROG, description=__doc__.split("\n\n")[0])
    p.add_argument("--policy", required=True, help="the learner: greedy, vicsek or a checkpoint PATH")
    p.add_argument("--task", default="4p2e1o", help="task name (4p2e1o, 4p2e3o, 4p2e5o, 4p3e5o) or JSON path")
    p.add_argument("--zoo", default="zoo1", help="zoo name (zoo1, zoo2, zoo3) or JSON path")
    p.add_argument("--episodes", type=_positive_int, default=500, help="episodes per seed (default 500)")
    p.add_argument("--seeds", type=int, nargs="+", default=[0], help="evaluation seeds (default: 0)")
    p.add_argument("--out", type=Path, default=Path("eval_out"), help="output folder (default eval_out)")
    return p


def _finite(value: float) -> float | None:
    return value if math.isfinite(value) else None


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from atdrone.checkpoint import CheckpointError, atomic_write_bytes, load_policy
    from atdrone.config import ConfigError, load_task
    from atdrone.evaluation import METRICS, evaluate
    from atdrone.policies.zoo import RULES, ZooError, load_zoo

    try:
        task = load_task(args.task)
        zoo = load_zoo(args.zoo)
        if args.policy in RULES:
            learner, label = RULES[args.policy](), args.policy
            learner.name = label
        else:
            learner, label = load_policy(args.policy), Path(args.policy).stem
        result = evaluate(learner, task, zoo, episodes=args.episodes, seeds=args.seeds)
    except (ConfigError, CheckpointError, ZooError) as exc:
        print(f"{PROG}: error: {exc}".splitlines()[0], file=sys.stderr)
        return EXIT_USAGE
    summary = {k: (_finite(v) if isinstance(v, float) else v) for k, v in result.summary().items()}
    summary.update({"policy": args.policy, "seed_list": list(args.seeds)})
    per_seed = [
        {"seed": int(s), **{m: _finite(float(row[m])) for m in METRICS}} for s, row in result.per_seed.iterrows()
    ]
    stem = args.out / f"{label}_{task.name}_{zoo.name}"
    try:
        atomic_write_bytes(f"{stem}.json", json.dumps({"summary": summary, "per_seed": per_seed}, indent=2).encode())
        atomic_write_bytes(f"{stem}.csv", result.records.to_csv(index=False).encode())
    except OSError as exc:
        print(f"{PROG}: error: cannot write {stem}.*: {exc}", file=sys.stderr)
        return 1
    mean, std = result.mean, result.std
    cells = ", ".join(f"{m} {mean[m]:.2f} ± {std[m]:.2f}" for m in METRICS)
    print(f"evaluate {label} on {task.name} with {zoo.name}: {len(result.records)} episodes; {cells}")
    print(f"wrote {stem}.json and {stem}.csv")
    return 0


if __name__ == "__main__":
    sys.exit(main())
