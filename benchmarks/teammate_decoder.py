"""Can NAHT-D's decoder predict greedy partners' turns? Held-out error against the mean turn's.

An untrained NAHT-D learner (two drones) plays 4p2e1o with two greedy partners; the
rollout records each partner's executed turn. For every ``--history`` k the decoder
(with its encoder) is fitted on the decoder loss alone, and, as an upper reference, an
MLP (256 x 256) on the network's raw input (k frames and own turns, plus which teammate
slot) is fitted on the squared error. Both are scored on held-out fragments: the mean
squared error of the predicted turn on the partners' turns, beside that of predicting
the held-out mean turn. Prints JSON.

Usage: python benchmarks/teammate_decoder.py [--histories 1 2] [--decoder-steps 600]
       [--mlp-history 2] [--mlp-steps 4000] [--out benchmarks/results/teammate_decoder.json]
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import torch

from atdrone.fileio import atomic_write_text
from atdrone.learn.ppo import PPOConfig
from atdrone.learn.rollout import RolloutWorker
from atdrone.models.teammate import TeammateActorCritic, TeammateConfig
from atdrone.policies.rules import GreedyPolicy


def rollouts(history: int, envs: int, train: int, test: int, seed: int) -> tuple[RolloutWorker, tuple, tuple]:
    """A worker of an untrained NAHT-D learner with greedy partners; (inputs, mates) of train and test fragments."""
    torch.manual_seed(seed)
    arch = TeammateActorCritic.header(TeammateConfig(history=history, entity_dim=16, hidden=32))
    worker = RolloutWorker("4p2e1o", seed, arch, PPOConfig(num_envs=envs), partners=[GreedyPolicy()], num_ctrl=2)

    def data(n: int) -> tuple[torch.Tensor, torch.Tensor]:
        batches = [worker.collect(64).batch(0.99, 0.95) for _ in range(n)]
        return (
            torch.from_numpy(np.concatenate([b["obs"] for b in batches])),
            torch.from_numpy(np.concatenate([b["mates"] for b in batches])),
        )

    return worker, data(train), data(test)


def rule_turns(mates: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(mask of the rule-based teammates' entries, their executed turns)."""
    rule = ~torch.isfinite(mates[..., 2])
    return rule, mates[..., 0][rule]


def decoder_error(history: int, steps: int, seed: int) -> dict[str, float]:
    worker, (x, m), (xt, mt) = rollouts(history, 32, 8, 2, seed)
    model = worker.model
    assert isinstance(model, TeammateActorCritic) and model.decoder is not None
    rule, turns = rule_turns(mt)
    opt = torch.optim.Adam([*model.encoder.parameters(), *model.decoder.parameters()], lr=3e-3)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = torch.randint(len(x), (256,), generator=g)
        loss = model.decoder_loss(x[idx], m[idx])
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        mean, _ = model.decode(xt)
    return {
        "history": history,
        "train_samples": len(x),
        "test_samples": len(xt),
        "decoder_mse": float(((torch.tanh(mean)[rule] - turns) ** 2).mean()),
        "mean_turn_mse": float(((turns - turns.mean()) ** 2).mean()),
        "share_below_half_limit": float((turns.abs() < 0.5).float().mean()),
    }


def mlp_error(history: int, steps: int, seed: int) -> dict[str, float]:
    _, (x, m), (xt, mt) = rollouts(history, 64, 16, 3, seed)

    def per_teammate(x: torch.Tensor, m: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        n, mates, _ = m.shape
        inputs = torch.cat([x[:, None].expand(n, mates, x.shape[-1]), torch.eye(mates)[None].expand(n, -1, -1)], -1)
        rule = ~torch.isfinite(m[..., 2])
        return inputs[rule], m[..., 0][rule]

    X, Y = per_teammate(x, m)
    Xt, Yt = per_teammate(xt, mt)
    torch.manual_seed(seed)
    net = torch.nn.Sequential(
        torch.nn.Linear(X.shape[1], 256),
        torch.nn.ReLU(),
        torch.nn.Linear(256, 256),
        torch.nn.ReLU(),
        torch.nn.Linear(256, 1),
    )
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    g = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = torch.randint(len(X), (512,), generator=g)
        loss = ((net(X[idx]).squeeze(-1) - Y[idx]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        train = float(((net(X[:20_000]).squeeze(-1) - Y[:20_000]) ** 2).mean())
        test = float(((net(Xt).squeeze(-1) - Yt) ** 2).mean())
    return {
        "history": history,
        "train_samples": len(X),
        "test_samples": len(Xt),
        "mlp_train_mse": train,
        "mlp_test_mse": test,
        "mean_turn_mse": float(((Yt - Yt.mean()) ** 2).mean()),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--histories", type=int, nargs="+", default=[1, 2])
    parser.add_argument("--decoder-steps", type=int, default=600)
    parser.add_argument("--mlp-history", type=int, default=2)
    parser.add_argument("--mlp-steps", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="", help="also write the JSON here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    t0 = time.process_time()
    result = {
        "task": "4p2e1o",
        "partners": "greedy x 2",
        "decoder": [decoder_error(k, args.decoder_steps, args.seed) for k in args.histories],
        "mlp_on_raw_input": mlp_error(args.mlp_history, args.mlp_steps, args.seed),
    }
    result["cpu_s"] = time.process_time() - t0
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        atomic_write_text(args.out, text + "\n")


if __name__ == "__main__":
    main()
