"""Does a NAHT-D embedding tell partner types apart? A linear probe on embeddings after 20 steps.

Episodes of 4p2e1o whose two partners are both greedy, both VICSEK or both sp_high
(Zoo 3's drones: a diagnostic, not a training pool) are played by a NAHT-D learner; the
embedding of every learner drone at step ``--step`` of the episodes still running then
is labelled with the partner type. A logistic regression is fitted on the episodes of
``--train-share`` and scored on the others (held-out episodes, not held-out steps).
Reported beside it: the probe on the embedding averaged over steps 1..step, and on the
network's raw input at that step (what the encoder was given), so a low score can be
told apart from an encoder that threw the information away.

The encoder is a NAHT-D member's (``--checkpoint``), or one fitted here on the decoder
loss alone with partners drawn from the same three types (``--fit-steps`` Adam steps on
``--fit-fragments`` fragments). Prints JSON.

Usage: python benchmarks/teammate_probe.py [--checkpoint runs/naht_d/members/naht-d-g3-0.pt]
       [--history 1] [--episodes 256] [--step 20] [--out benchmarks/results/teammate_probe.json]
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
from atdrone.models.checkpoint import load_checkpoint
from atdrone.models.teammate import TeammateActorCritic, TeammateConfig
from atdrone.policies.zoo import load_zoo

TYPES = ("greedy", "vicsek", "sp_high")


def fitted_model(args: argparse.Namespace, partners: list) -> TeammateActorCritic:
    """A NAHT-D network whose encoder and decoder are fitted on the decoder loss, partners of every type."""
    torch.manual_seed(args.seed)
    arch = TeammateActorCritic.header(TeammateConfig(history=args.history))
    worker = RolloutWorker("4p2e1o", args.seed, arch, PPOConfig(num_envs=32), partners=partners, num_ctrl=2)
    model = worker.model
    assert isinstance(model, TeammateActorCritic) and model.decoder is not None
    batches = [worker.collect(64).batch(0.99, 0.95) for _ in range(args.fit_fragments)]
    x = torch.from_numpy(np.concatenate([b["obs"] for b in batches]))
    m = torch.from_numpy(np.concatenate([b["mates"] for b in batches]))
    opt = torch.optim.Adam([*model.encoder.parameters(), *model.decoder.parameters()], lr=3e-3)
    g = torch.Generator().manual_seed(args.seed)
    for _ in range(args.fit_steps):
        idx = torch.randint(len(x), (512,), generator=g)
        loss = model.decoder_loss(x[idx], m[idx])
        opt.zero_grad()
        loss.backward()
        opt.step()
    return model


def features(model: TeammateActorCritic, partners: list, args: argparse.Namespace) -> dict[str, np.ndarray]:
    """Per (episode, learner): embedding at ``step``, mean embedding over 1..step, raw input; type; episode id."""
    out: dict[str, list] = {"at_step": [], "mean": [], "raw": [], "label": [], "episode": []}
    for label in range(len(TYPES)):
        profile = np.array([label, label])
        worker = RolloutWorker(
            "4p2e1o",
            args.seed + 100 + label,
            model.architecture(),
            PPOConfig(num_envs=args.episodes),
            partners=partners,
            num_ctrl=2,
            sampler=lambda rng, n, p=profile: np.tile(p, (n, 1)),
        )
        worker.set_weights(model.state_dict())
        frag = worker.collect(args.step + 1)
        running = ~frag.dones[: args.step].any(0)  # episodes that reached the step
        with torch.no_grad():
            z = model.encoder(torch.from_numpy(frag.obs[: args.step + 1]))  # (T, B, k, E)
        for b in np.flatnonzero(running):
            for i in range(frag.obs.shape[2]):
                out["at_step"].append(z[args.step, b, i].numpy())
                out["mean"].append(z[1 : args.step + 1, b, i].mean(0).numpy())
                out["raw"].append(frag.obs[args.step, b, i])
                out["label"].append(label)
                out["episode"].append(label * 100_000 + b)
    return {k: np.asarray(v) for k, v in out.items()}


def probe(x: np.ndarray, y: np.ndarray, episodes: np.ndarray, share: float, seed: int) -> dict[str, float]:
    """Held-out-episode accuracy of a multinomial logistic regression (standardised inputs)."""
    rng = np.random.default_rng(seed)
    ids = np.unique(episodes)
    train_ids = set(rng.choice(ids, size=int(share * len(ids)), replace=False).tolist())
    train = np.array([e in train_ids for e in episodes])
    mu, sd = x[train].mean(0), x[train].std(0) + 1e-6
    xt = torch.tensor((x - mu) / sd, dtype=torch.float32)
    yt = torch.tensor(y)
    lin = torch.nn.Linear(x.shape[1], len(TYPES))
    opt = torch.optim.Adam(lin.parameters(), lr=1e-2, weight_decay=1e-4)
    for _ in range(1000):
        loss = torch.nn.functional.cross_entropy(lin(xt[train]), yt[train])
        opt.zero_grad()
        loss.backward()
        opt.step()
    with torch.no_grad():
        pred = lin(xt).argmax(-1).numpy()
    return {"train": float((pred[train] == y[train]).mean()), "held_out": float((pred[~train] == y[~train]).mean())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", default="", help="a NAHT-D member's checkpoint (default: fit one here)")
    parser.add_argument("--history", type=int, default=1, help="k of the encoder fitted here")
    parser.add_argument("--fit-steps", type=int, default=600)
    parser.add_argument("--fit-fragments", type=int, default=4)
    parser.add_argument("--episodes", type=int, default=256, help="episodes per partner type")
    parser.add_argument("--step", type=int, default=20)
    parser.add_argument("--train-share", type=float, default=0.6)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default="", help="also write the JSON here")
    args = parser.parse_args()
    torch.set_num_threads(1)
    t0 = time.process_time()
    partners = load_zoo("zoo3").policies()
    partners = [partners[[p.name for p in partners].index(t)] for t in TYPES]
    if args.checkpoint:
        model, _ = load_checkpoint(args.checkpoint)
        if not isinstance(model, TeammateActorCritic):
            raise SystemExit(f"{args.checkpoint} is not a NAHT-D network")
    else:
        model = fitted_model(args, partners)
    feats = features(model, partners, args)
    result = {
        "encoder": args.checkpoint or f"fitted here (k={args.history}, {args.fit_steps} steps)",
        "step": args.step,
        "samples_per_type": np.bincount(feats["label"], minlength=len(TYPES)).tolist(),
        "chance": float(np.bincount(feats["label"]).max() / len(feats["label"])),
        **{
            name: probe(feats[name], feats["label"], feats["episode"], args.train_share, args.seed)
            for name in ("at_step", "mean", "raw")
        },
        "cpu_s": time.process_time() - t0,
    }
    text = json.dumps(result, indent=2)
    print(text)
    if args.out:
        atomic_write_text(args.out, text + "\n")


if __name__ == "__main__":
    main()
