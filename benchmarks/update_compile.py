"""Does torch.compile, or bfloat16 matrix products, pay off for the PPO update on the CPU? (issue 26)

Times the local trainer's update (default preset, 4p2e1o self-play, one torch thread) with the
library's eager kernels against a variant:

- ``compile``: ``torch.compile`` (inductor) of the model's ``dist`` and ``value``, the two methods an
  update's forward runs (with torch's own tanh in them: numpy's kernel is no op dynamo can trace);
- ``bf16``: every linear layer's three products (forward, input and weight gradients) in bfloat16
  with float32 results, as autocast would run them (oneDNN's AVX512-BF16 kernels where the CPU has
  them); activations, losses and the optimiser stay float32. This changes the numbers an update
  computes, so it is a probe of the speed at stake, not a kernel the library could take as it is.

Alternating subprocess rounds; prints JSON: per round the first update (which compiles) and the
median of the next ``--updates``, and the ratio variant / eager.

Usage: python benchmarks/update_compile.py [--variant compile|bf16] [--rounds 2] [--updates 4]
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


def bf16_linear() -> Any:
    """A drop-in for ``atdrone.models.networks._LinearFn`` whose products run in bfloat16."""
    import torch
    import torch.nn.functional as F

    class Bf16Linear(torch.autograd.Function):
        @staticmethod
        def forward(ctx: Any, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
            xb, wb = x.bfloat16(), weight.bfloat16()
            ctx.save_for_backward(xb, wb)
            return F.linear(xb, wb).float() + bias

        @staticmethod
        def backward(ctx: Any, grad: torch.Tensor) -> tuple[torch.Tensor | None, ...]:
            xb, wb = ctx.saved_tensors
            g = grad.reshape(-1, grad.shape[-1])
            gb = g.bfloat16()
            grad_x = (gb @ wb).float().reshape(xb.shape) if ctx.needs_input_grad[0] else None
            grad_w = xb.reshape(-1, xb.shape[-1]).t().mm(gb).t().float() if ctx.needs_input_grad[1] else None
            grad_b = g.sum(0) if ctx.needs_input_grad[2] else None
            return grad_x, grad_w, grad_b

    return Bf16Linear


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
        elif mode == "bf16":
            networks._LinearFn = bf16_linear()  # type: ignore[misc]  # the probe's process only
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
    parser.add_argument("--variant", choices=["compile", "bf16"], default="compile")
    parser.add_argument("--mode", choices=["eager", "compile", "bf16"], help=argparse.SUPPRESS)  # one measurement
    args = parser.parse_args()
    if args.mode:
        print(json.dumps(measure(args.mode, args.updates)))
        return
    rounds = []
    for _ in range(args.rounds):
        row = {}
        for mode in ("eager", args.variant):
            cmd = [sys.executable, __file__, "--mode", mode, "--updates", str(args.updates)]
            row[mode] = json.loads(subprocess.run(cmd, capture_output=True, text=True, check=True).stdout)
        rounds.append(row)
    ratio = [r[args.variant]["update_s"] / r["eager"]["update_s"] for r in rounds]
    key = f"update_ratio_{args.variant}_over_eager"
    print(json.dumps({"variant": args.variant, "rounds": rounds, key: [round(x, 3) for x in ratio]}, indent=2))


if __name__ == "__main__":
    main()
