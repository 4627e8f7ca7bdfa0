"""The Unseen Zoo 2 drones measured by the evaluation protocol, printed as JSON.

For each self-play drone (configs/zoos/checkpoints/<task>/*.pt): its self-play metrics (the
drone in every pursuer slot, the number the zoo's skill levels refer to: about 70 % and
54 % SUC) and its metrics as the learner with each zoo's partners, on the task it was
trained on. Optionally compares a best response (--br PATH) with self-play policies
(--sp PATH ..., default sp_high) on a zoo (--br-zoo), with the standard error of SUC,
the paired difference of SUC (BR minus SP over the same episode starts) and its
standard error, the share of episodes ended by a learner's collision or by the partners alone, and
what collided (learner/partner with learner/partner, wall or obstacle).
Usage: python benchmarks/zoo_drones.py [--episodes 500] [--seeds 0] [--br runs/br_zoo1/last.pt] [--drones A.pt ...]
       python benchmarks/zoo_drones.py --only-br --br BR.pt --sp SP.pt --episodes 1000 --seeds 0 1 --out F.json
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
    parser.add_argument("--br", default=None, help="a best-response checkpoint to compare with --sp")
    parser.add_argument("--br-zoo", default="zoo1")
    parser.add_argument("--sp", nargs="+", default=[str(CHECKPOINTS / "sp_high.pt")], help="self-play checkpoints")
    parser.add_argument("--only-br", action="store_true", help="skip the zoo drones, compare --br and --sp only")
    parser.add_argument("--drones", nargs="+", type=Path, default=None, help="checkpoints instead of the zoo's")
    parser.add_argument("--out", default=None, help="also write the JSON to this file")
    args = parser.parse_args()

    from atdrone.fileio import atomic_write_bytes
    from atdrone.models.checkpoint import read_header
    from atdrone.policies.neural import load_policy
    from atdrone.teams.evaluation import METRICS, crash_breakdown, crash_shares, evaluate, metrics, run_episodes

    def self_play(path: Path) -> dict[str, float]:
        policy = load_policy(path)
        per_seed = [metrics(run_episodes(policy, task, [policy], args.episodes, seed=s)) for s in args.seeds]
        return {m: float(np.mean([p[m] for p in per_seed])) for m in METRICS}

    out: dict[str, object] = {"benchmark": "zoo_drones", "episodes": args.episodes, "seeds": args.seeds}
    drones = args.drones if args.drones is not None else sorted(CHECKPOINTS.glob("*/*.pt"))
    for path in [] if args.only_br else drones:
        name = path.parent.name if path.stem == "last" else path.stem  # a run's runs/NAME/last.pt is NAME
        header = read_header(path)
        task = header["task"]
        entry: dict[str, object] = {"task": task, "seed": header["seed"], "env_steps": header["step"]}
        entry["self_play"] = self_play(path)
        for zoo in args.zoos:
            entry[zoo] = evaluate(load_policy(path), task, zoo, episodes=args.episodes, seeds=args.seeds).mean
        out[name] = entry
        print(json.dumps({name: entry}), flush=True)
    if args.br:
        task = read_header(args.br)["task"]

        def on_zoo(path: str) -> tuple[dict[str, object], np.ndarray]:
            result = evaluate(load_policy(path), task, args.br_zoo, episodes=args.episodes, seeds=args.seeds)
            suc = result.records["success"].to_numpy(float)
            se = 100.0 * float(np.sqrt(suc.mean() * (1 - suc.mean()) / len(suc)))
            shares = {**crash_shares(result.records), "crash_kinds": crash_breakdown(result.records)}
            return {**result.mean, "SUC_se": se, **shares, "checkpoint": path}, suc

        br, br_suc = on_zoo(args.br)
        out["best_response"] = {"task": task, "zoo": args.br_zoo, "br": br, "self_play": []}
        for path in args.sp:
            entry, suc = on_zoo(path)
            # the same seeds give both policies the same episode starts: a paired difference
            diff = 100.0 * (br_suc - suc)
            entry["BR_minus_SP_SUC"] = float(diff.mean())
            entry["BR_minus_SP_SUC_se"] = float(diff.std(ddof=1) / np.sqrt(len(diff)))
            out["best_response"]["self_play"].append(entry)
    text = json.dumps(out, indent=2)
    print(text)
    if args.out:
        atomic_write_bytes(Path(args.out), (text + "\n").encode())


if __name__ == "__main__":
    main()
