"""Does torch.compile pay off for the PPO update on the CPU? (issue 26)

Times the local trainer's update (default preset, 4p2e1o self-play, one torch thread) with the
library's eager kernels against ``torch.compile`` (inductor) of the model's ``dist`` and ``value``,
the two methods an update's forward runs (with torch's own tanh in them: numpy's kernel is no op
dynamo can trace). Alternating subprocess rounds; prints JSON: per round the first update (which
compiles) and the median of the next ``--updates``, and the ratio compiled / eager.

Usage: python benchmarks/update_compile.py [--rounds 2] [--updates 4]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from typing import Any

import numpy as np


def measure(mode: str, updates: int) -> dict[str, Any]:
    import torch

    import atdrone.models.networks as networks
    from atdrone.learn.trainer import Trainer, load_train_config

    torch.set_num_threads(1)
    with tempfile.TemporaryDirectory() as tmp:
        trainer = Trainer(load_train_config({"name": "bench", "task": "4p2e1o", "mode": "self_play", "out_dir": tmp}))
        if mode == "compile":
            networks.tanh = torch.tanh  # type: ignore[assignment]  # the probe's process only
            model: Any = trainer.learner.model
            model.dist = torch.compile(model.dist, dynamic=False)
            model.value = torch.compile(model.value, dynamic=False)
        t0 = time.perf_counter()
        trainer.update_once()
        first = time.perf_counter() - t0
        rows = [trainer.update_once() for _ in range(updates)]
    return {
        "mode": mode,
        "first_update_s": round(first, 2),
        "update_s": round(float(np.median([r["perf/update_s"] for r in rows])), 3),
        "inference_s": round(float(np.median([r["perf/inference_s"] for r in rows])), 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--updates", type=int, default=4)
    parser.add_argument("--mode", choices=["eager", "compile"], help=argparse.SUPPRESS)  # one measurement
    args = parser.parse_args()
    if args.mode:
        print(json.dumps(measure(args.mode, args.updates)))
        return
    rounds = []
    for _ in range(args.rounds):
        row = {}
        for mode in ("eager", "compile"):
            cmd = [sys.executable, __file__, "--mode", mode, "--updates", str(args.updates)]
            row[mode] = json.loads(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout)
        rounds.append(row)
    ratio = [r["compile"]["update_s"] / r["eager"]["update_s"] for r in rounds]
    print(json.dumps({"rounds": rounds, "update_ratio_compiled_over_eager": [round(x, 3) for x in ratio]}, indent=2))


if __name__ == "__main__":
    main()
