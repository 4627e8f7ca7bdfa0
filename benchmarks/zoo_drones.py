"""The Unseen Zoo 2 drones measured by the evaluation protocol, printed as JSON.

For each self-play drone (configs/zoos/checkpoints/*.pt): its self-play metrics (the
drone in every pursuer slot, the number the zoo's skill levels refer to: about 70 % and
54 % SUC) and its metrics as the learner with each zoo's partners, on the task it was
trained on. Optionally compares a best response (--br PATH) with self-play on a zoo.
Usage: python benchmarks/zoo_drones.py [--episodes 500] [--seeds 0] [--br runs/br_zoo1/last.pt]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

CHECKPOINTS = Path(__file__).resolve().parent.parent / "configs" / "zoos" / "checkpoints"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=500)
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--zoos", nargs="+", default=["zoo1", "zoo2", "zoo3"])
    parser.add_argument("--br", default=None, help="a best-response checkpoint to compare with sp_high")
    parser.add_argument("--br-zoo", default="zoo1")
    args = parser.parse_args()

    from atdrone.checkpoint import load_policy, read_header
    from atdrone.evaluation import METRICS, evaluate, metrics, run_episodes

    def self_play(path: Path) -> dict[str, float]:
        policy = load_policy(path)
        per_seed = [metrics(run_episodes(policy, task, [policy], args.episodes, seed=s)) for s in args.seeds]
        return {m: float(np.mean([p[m] for p in per_seed])) for m in METRICS}

    out: dict[str, object] = {"benchmark": "zoo_drones", "episodes": args.episodes, "seeds": args.seeds}
    for path in sorted(CHECKPOINTS.glob("*.pt")):
        header = read_header(path)
        task = header["task"]
        entry: dict[str, object] = {"task": task, "seed": header["seed"], "env_steps": header["step"]}
        entry["self_play"] = self_play(path)
        for zoo in args.zoos:
            entry[zoo] = evaluate(load_policy(path), task, zoo, episodes=args.episodes, seeds=args.seeds).mean
        out[path.stem] = entry
        print(json.dumps({path.stem: entry}), flush=True)
    if args.br:
        br = Path(args.br)
        task = read_header(br)["task"]
        out["best_response"] = {
            "zoo": args.br_zoo,
            "br": evaluate(load_policy(br), task, args.br_zoo, episodes=args.episodes, seeds=args.seeds).mean,
            "sp_high": evaluate(
                load_policy(CHECKPOINTS / "sp_high.pt"), task, args.br_zoo, episodes=args.episodes, seeds=args.seeds
            ).mean,
        }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
