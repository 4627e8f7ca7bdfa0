"""HOLA-Drone V2's min step: what each replay rule spends and what signal it keeps, on planted preferences.

    python benchmarks/hola_replay.py [--effect -20 -5] [--seeds 20]

One candidate partner makes every team ``effect`` points worse (returns drawn with a 15-point sd per
episode, tests/test_hola_signal.py's PlantedOracle); G'_t of one learner and 5 or 8 candidates (10 or 28
hyperedges), 32 episodes a hyperedge then replays up to 256. Prints JSON: per rule the mean episodes
played and the softmin rho's mass on the planted worst partner (mean and worst seed; 0.5 is the most a
member can hold with two distinct partners an episode).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--effect", type=float, nargs="+", default=[-20.0, -5.0])
    parser.add_argument("--seeds", type=int, default=20)
    args = parser.parse_args()
    from test_hola_signal import _min_step

    from atdrone.population.hola import HolaConfig

    out: dict[str, object] = {"benchmark": "hola_replay", "seeds": args.seeds, "sd": 15.0, "cells": []}
    for effect in args.effect:
        for candidates in (5, 8):
            effects = {f"p{i}": 0.0 for i in range(candidates - 1)}
            worst = f"p{candidates - 1}"
            effects[worst] = effect
            for replay in ("partners", "softmin"):
                runs = [_min_step(HolaConfig(replay=replay, null_trials=0), effects, s) for s in range(args.seeds)]
                masses = [algo.rho[worst] for algo, _ in runs]
                cell = {
                    "effect": effect,
                    "candidates": candidates,
                    "replay": replay,
                    "episodes_mean": float(np.mean([o.episodes for _, o in runs])),
                    "worst_mass_mean": float(np.mean(masses)),
                    "worst_mass_min": float(np.min(masses)),
                }
                out["cells"].append(cell)  # type: ignore[attr-defined]
                print(json.dumps(cell), file=sys.stderr)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
