"""A GIF of one episode of a protocol with team events; each frame's title names the event once it happened.

Usage: python benchmarks/protocol_gif.py [--protocol zoo3+swap] [--task 4p2e1o] [--seed 3] [--out docs/img/swap.gif]
The learner slots fly greedy drones (blue), the zoo's partners green; the episode is the
first of the seed whose event happens before it ends.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from atdrone.envs.core import BatchedPursuit
from atdrone.envs.events import EVENT_KINDS
from atdrone.envs.render import FrameRenderer, save_gif
from atdrone.policies.rules import GreedyPolicy
from atdrone.policies.zoo import load_zoo
from atdrone.teams.match import Match
from atdrone.teams.protocols import load_protocol


def record(protocol: str, task: str, seed: int, max_steps: int, every: int) -> list[np.ndarray]:
    """Frames of the first episode (of those numbered from 0 under ``seed``) that lives to its first event."""
    proto = load_protocol(protocol)
    partners = load_zoo(proto.zoo, task).policies()
    learner = GreedyPolicy()
    for episode in range(50):
        core = BatchedPursuit(task, 1, seed=seed, events=proto.plan)
        match = Match(core, partners, seed=seed)
        match.reset(episodes=np.array([episode]))
        renderer = FrameRenderer(core, 0, partner_slots=match.partner_slots[0])
        frames, note, happened, fresh = [], "", False, False
        names = match.partner_names
        for _ in range(max_steps):
            before = match.members[0].copy()
            title = f"{proto.name} - step {int(core.state.t[0])}" + (f" - {note}" if note else "")
            if int(core.state.t[0]) % every == 0 or fresh:
                frames.append(renderer.draw(title=title))
            fresh = False
            _, _, done, info = match.step(learner.act(match.learner_batch()).reshape(1, -1))
            if done[0]:
                break
            changed = np.flatnonzero(info["team_changed"][0])
            for slot in changed:
                k = int(np.flatnonzero(core.state.ev_slot[0] == slot)[0])
                kind = EVENT_KINDS[int(core.state.ev_kind[0, k])]
                j = int(np.flatnonzero(match.partner_slots[0] == slot)[0])
                who = f"{names[before[j]]} -> {names[match.members[0, j]]}" if kind == "swap" else names[before[j]]
                note = f"{kind} at step {int(core.state.t[0])}: slot {slot} {who}"
                happened = fresh = True
        renderer.close()
        if happened:
            return frames
    raise RuntimeError(f"no episode of seed {seed} lived to its event")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--protocol", default="zoo3+swap")
    parser.add_argument("--task", default="4p2e1o")
    parser.add_argument("--seed", type=int, default=3)
    parser.add_argument("--max-steps", type=int, default=400)
    parser.add_argument("--every", type=int, default=3, help="draw every n-th step (and the event's)")
    parser.add_argument("--out", type=Path, default=Path("docs/img/swap.gif"))
    args = parser.parse_args()
    frames = record(args.protocol, args.task, args.seed, args.max_steps, args.every)
    print(save_gif(frames, args.out, fps=10), len(frames), "frames")


if __name__ == "__main__":
    main()
