"""The local single-process PPO trainer behind ``atdrone train CONFIG``.

Modes: ``self_play`` (IPPO, one network shared by every pursuer), ``mappo`` (the
same with a centralised critic) and ``best_response`` (num_ctrl learners with zoo
partners). A run lives in ``<out_dir>/<name>/``: the config, ``last.pt`` (policy
checkpoint), ``trainer_state.pt`` (optimizer, counters, RNG, MLflow run id),
``history.csv`` and ``curve.png``; ``--resume`` continues from the last checkpoint.
"""

from __future__ import annotations

import io
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import torch

from atdrone.config import OPTIONAL, ConfigError, check_task_field, load_config, load_task, repo_path, require_at_least
from atdrone.fileio import atomic_write_bytes
from atdrone.learn.ppo import PPOConfig, learning_rate, net_config, ppo_config, ppo_update
from atdrone.learn.rollout import RolloutWorker
from atdrone.models.checkpoint import save_checkpoint
from atdrone.models.networks import ActorCritic
from atdrone.policies.base import Policy
from atdrone.policies.neural import NeuralPolicy
from atdrone.policies.zoo import load_zoo
from atdrone.teams.evaluation import metrics, run_episodes

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class TrainConfig:
    """A training run. ``ppo`` overrides the ``preset`` (see atdrone.learn.ppo.PRESETS).

    torch_threads: torch threads of the rollout (inference); update_threads: of the PPO
    update, which runs while the rollout is idle (set both to 1 when sharing the cores).
    init_checkpoint: start from this policy's weights (e.g. a best response fine-tuned
    from a self-play drone); its architecture must match the PPO config's, except that
    the new network may be wider (a centralised critic, more past frames: ppo.history);
    the new inputs start with zero weights, so it starts acting as the checkpoint does.
    start_std: start from this exploration noise (the Gaussian's std in pre-squash
    units), overriding the initial checkpoint's (0: keep it). A fine-tune at low noise
    optimises what a deterministic evaluation plays.
    centralised_critic: give a best_response learner MAPPO's critic over the global
    state (mode mappo always has one); the actor still sees only its own observation.
    stop_at_suc: stop once a periodic evaluation reaches this SUC % (0: off), to train a
    drone of a given skill level (the Zoo 2 drones).
    """

    name: str
    task: str
    mode: Literal["self_play", "mappo", "best_response"] = "self_play"
    zoo: str = field(default="", metadata=OPTIONAL)
    seed: int = 0
    total_env_steps: int = 2_000_000
    max_minutes: float = 0.0
    preset: str = "default"
    ppo: dict[str, Any] = field(default_factory=dict)
    eval_every: int = 10
    eval_episodes: int = 200
    checkpoint_every: int = 10
    out_dir: str = "runs"
    torch_threads: int = 1
    update_threads: int = 2
    device: str = "auto"
    experiment: str = field(default="", metadata=OPTIONAL)
    init_checkpoint: str = field(default="", metadata=OPTIONAL)
    stop_at_suc: float = 0.0
    centralised_critic: bool = False
    start_std: float = 0.0


def load_train_config(path_or_doc: str | Path | dict[str, Any], **overrides: Any) -> TrainConfig:
    """A validated TrainConfig from a JSON file or mapping (plus overrides)."""
    cfg: TrainConfig = load_config(TrainConfig, path_or_doc, "train", **overrides)
    check_task_field(cfg.task)
    ppo_config(cfg.ppo, cfg.preset)
    if cfg.mode == "best_response" and not cfg.zoo:
        raise ConfigError("zoo", "best_response training needs a zoo")
    require_at_least(
        cfg, ("total_env_steps", "eval_every", "eval_episodes", "checkpoint_every", "torch_threads", "update_threads")
    )
    if cfg.max_minutes < 0:
        raise ConfigError("max_minutes", f"must be >= 0, got {cfg.max_minutes}")
    if cfg.start_std < 0:
        raise ConfigError("start_std", f"must be >= 0, got {cfg.start_std}")
    if not 0 <= cfg.stop_at_suc <= 100:
        raise ConfigError("stop_at_suc", f"must be a percentage in [0, 100], got {cfg.stop_at_suc}")
    return cfg


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


class Trainer:
    """Collect -> PPO update -> evaluate -> checkpoint, in one process."""

    def __init__(self, cfg: TrainConfig, tracker: Any | None = None) -> None:
        self.cfg = cfg
        self.task = load_task(cfg.task)
        self.ppo: PPOConfig = ppo_config(cfg.ppo, cfg.preset)
        self.net = net_config(self.ppo, centralised_critic=cfg.mode == "mappo" or cfg.centralised_critic)
        self.run_dir = Path(cfg.out_dir) / cfg.name
        self.device = pick_device(cfg.device)
        torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(cfg.seed)
        self.model = ActorCritic(self.net).to(self.device)
        if cfg.init_checkpoint:
            from atdrone.models.checkpoint import load_checkpoint

            path = Path(cfg.init_checkpoint)
            if not path.exists():  # repository-relative, like zoo checkpoints
                path = repo_path(path)
            if not path.is_file():
                raise ConfigError("init_checkpoint", f"no checkpoint at {cfg.init_checkpoint} (train that run first)")
            start, _ = load_checkpoint(path, expect_task=self.task.name)
            try:
                if start.cfg == self.net:
                    self.model.load_state_dict(start.state_dict())
                else:
                    self.model.widen_from(start)  # the new inputs get zero weights, else ValueError
            except ValueError:
                raise ConfigError("init_checkpoint", f"architecture {start.cfg} does not match {self.net}") from None
        if cfg.start_std > 0:
            with torch.no_grad():
                self.model.log_std.fill_(math.log(cfg.start_std))
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=self.ppo.lr, eps=1e-5)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.partners: list[Policy] = load_zoo(cfg.zoo).policies() if cfg.mode == "best_response" else []
        self.worker = RolloutWorker(
            self.task,
            self.ppo.num_envs,
            cfg.seed,
            self.net,
            partners=self.partners,
            gamma=self.ppo.gamma,
            collision_credit=self.ppo.collision_credit,
            collision_scale=self.ppo.collision_scale,
        )
        self.tracker = tracker
        self.env_steps = 0
        self.updates = 0
        self.history: list[dict[str, float]] = []
        self.run_id: str | None = None

    # ------------------------------------------------------------ persistence
    def save(self, metrics_now: dict[str, float] | None = None) -> Path:
        """Write last.pt and trainer_state.pt atomically; returns the checkpoint path."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        ckpt = self.run_dir / "last.pt"
        save_checkpoint(ckpt, self.model, self.header(metrics_now))
        buf = io.BytesIO()
        torch.save(
            {
                "optimizer": self.optimizer.state_dict(),
                "env_steps": self.env_steps,
                "updates": self.updates,
                "generator": self.generator.get_state(),
                "history": self.history,
                "run_id": self.run_id,
            },
            buf,
        )
        atomic_write_bytes(self.run_dir / "trainer_state.pt", buf.getvalue())
        return ckpt

    def header(self, metrics_now: dict[str, float] | None = None) -> dict[str, Any]:
        return {
            "name": self.cfg.name,
            "task": self.task.name,
            "num_p": self.task.players.num_p,
            "num_e": self.task.players.num_e,
            "algorithm": {"self_play": "SP-IPPO", "mappo": "MAPPO", "best_response": "BR"}[self.cfg.mode],
            "config": asdict(self.cfg),
            "ppo": asdict(self.ppo),
            "seed": self.cfg.seed,
            "step": self.env_steps,
            "metrics": metrics_now or (self.history[-1] if self.history else {}),
        }

    def resume(self) -> bool:
        """Load last.pt and trainer_state.pt when present; True when resumed."""
        state_path = self.run_dir / "trainer_state.pt"
        if not state_path.is_file():
            return False
        from atdrone.models.checkpoint import load_checkpoint

        model, header = load_checkpoint(self.run_dir / "last.pt", expect_task=self.task.name)
        self.model.load_state_dict(model.state_dict())
        state = torch.load(state_path, weights_only=False, map_location=self.device)
        self.optimizer.load_state_dict(state["optimizer"])
        self.env_steps, self.updates = state["env_steps"], state["updates"]
        self.generator.set_state(state["generator"])
        self.history, self.run_id = state["history"], state["run_id"]
        if header["step"] != self.env_steps:
            raise RuntimeError(f"{self.run_dir}: checkpoint step {header['step']} != trainer state {self.env_steps}")
        log.info("resumed %s at %d env steps", self.run_dir, self.env_steps)
        return True

    # --------------------------------------------------------------- training
    def policy(self, deterministic: bool = True) -> NeuralPolicy:
        cpu = ActorCritic(self.net)
        cpu.load_state_dict({k: v.cpu() for k, v in self.model.state_dict().items()})
        cpu.eval()
        return NeuralPolicy(cpu, name=self.cfg.name, deterministic=deterministic)

    def evaluate(self, episodes: int, seed: int = 12345) -> dict[str, float]:
        """SUC/COL/AST/REW of the current policy: self-play (all slots) or with the zoo."""
        policy = self.policy()
        partners = self.partners or [policy]
        records = run_episodes(policy, self.task, partners, episodes, seed=seed)
        return metrics(records)

    def update_once(self) -> dict[str, float]:
        """One rollout and one PPO update; returns train/ and perf/ metrics."""
        t0 = time.perf_counter()
        self.worker.set_weights({k: v.cpu() for k, v in self.model.state_dict().items()})
        frag = self.worker.collect(self.ppo.rollout_steps)
        t1 = time.perf_counter()
        torch.set_num_threads(self.cfg.update_threads)  # the rollout is idle while the update runs
        progress = self.env_steps / self.cfg.total_env_steps
        stats = ppo_update(
            self.model,
            self.optimizer,
            frag.batch(self.ppo.gamma, self.ppo.gae_lambda),
            self.ppo,
            self.task.players.num_e,
            self.task.players.num_p,
            self.generator,
            lr=learning_rate(self.ppo, progress),
        )
        torch.set_num_threads(self.cfg.torch_threads)
        t2 = time.perf_counter()
        self.env_steps += frag.dones.size
        self.updates += 1
        eps = frag.episodes
        out = {f"train/{k}": v for k, v in stats.items()}
        if eps:
            out["train/episodes"] = len(eps)
            out["train/success"] = float(np.mean([e["outcome"] == "captured" for e in eps]))
            out["train/collision"] = float(np.mean([e["collided"] for e in eps]))
            out["train/episode_return"] = float(np.mean([e["return"] for e in eps]))
            out["train/episode_length"] = float(np.mean([e["length"] for e in eps]))
        out["train/lr"] = learning_rate(self.ppo, progress)
        out["train/log_std"] = float(self.model.log_std.detach().cpu())
        total = t2 - t0
        out["perf/pursuer_steps_per_s"] = frag.samples / total
        out["perf/simulation_s"] = frag.timings["simulation"]
        out["perf/inference_s"] = frag.timings["inference"]
        out["perf/update_s"] = t2 - t1
        return out

    def train(self, progress: bool = True) -> dict[str, float]:
        """Run to total_env_steps (or max_minutes); returns the last evaluation."""
        from tqdm import tqdm

        started = time.perf_counter()
        last_eval: dict[str, float] = {}
        bar = tqdm(total=self.cfg.total_env_steps, initial=self.env_steps, unit="env-step", disable=not progress)
        while self.env_steps < self.cfg.total_env_steps:
            row = self.update_once()
            bar.update(self.ppo.num_envs * self.ppo.rollout_steps)
            timed_out = self.cfg.max_minutes and time.perf_counter() - started > self.cfg.max_minutes * 60
            done = self.env_steps >= self.cfg.total_env_steps or timed_out
            reached = False
            if self.updates % self.cfg.eval_every == 0 or done:
                last_eval = {f"eval/{k}": v for k, v in self.evaluate(self.cfg.eval_episodes).items()}
                row.update(last_eval)
                bar.set_postfix(SUC=f"{last_eval['eval/SUC']:.0f}%", COL=f"{last_eval['eval/COL']:.0f}%")
                reached = 0 < self.cfg.stop_at_suc <= last_eval["eval/SUC"]
                done = done or reached
            row.update({"env_steps": self.env_steps, "wall_s": time.perf_counter() - started})
            self.history.append(row)
            if self.tracker is not None:
                self.tracker.log_metrics({k: v for k, v in row.items() if "/" in k}, step=self.env_steps)
            if self.updates % self.cfg.checkpoint_every == 0 or done:
                self.save(last_eval)
                self.write_history()
            if timed_out or reached:
                log.info("stopping: %s", "max_minutes reached" if timed_out else f"eval SUC >= {self.cfg.stop_at_suc}")
                break
        bar.close()
        return last_eval

    def write_history(self) -> None:
        frame = pd.DataFrame(self.history)
        atomic_write_bytes(self.run_dir / "history.csv", frame.to_csv(index=False).encode())
        plot_curve(frame, self.run_dir / "curve.png", title=f"{self.cfg.name} ({self.task.name})")


def plot_curve(history: pd.DataFrame, path: Path, title: str = "") -> None:
    """Learning curve: evaluation SUC/COL and training success vs env steps."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5), dpi=100)
    if "train/success" in history:
        ax.plot(history["env_steps"], 100 * history["train/success"], color="0.7", lw=1, label="train success %")
    ev = history.dropna(subset=["eval/SUC"]) if "eval/SUC" in history else history.iloc[0:0]
    if len(ev):
        ax.plot(ev["env_steps"], ev["eval/SUC"], "o-", color="tab:blue", label="eval SUC %")
        ax.plot(ev["env_steps"], ev["eval/COL"], "s-", color="tab:red", label="eval COL %")
    ax.set_xlabel("environment steps")
    ax.set_ylabel("%")
    ax.set_ylim(0, 100)
    ax.grid(alpha=0.3)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(title, fontsize=9)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def run_training(cfg: TrainConfig, resume: bool = False, progress: bool = True, uri: str | None = None) -> Trainer:
    """Train with MLflow tracking: params, namespaced metrics, config, checkpoint and curve."""
    from atdrone.tracking import Tracker

    tracker = Tracker(uri)
    trainer = Trainer(cfg, tracker=tracker)
    if resume:
        if not trainer.resume():
            log.info("nothing to resume in %s: starting fresh", trainer.run_dir)
    elif (trainer.run_dir / "trainer_state.pt").exists():
        raise FileExistsError(f"{trainer.run_dir} holds a run: pass --resume to continue it, or pick another name")
    experiment = cfg.experiment or cfg.name
    with tracker.run(experiment, f"{cfg.name}-seed{cfg.seed}", run_id=trainer.run_id) as run_id:
        trainer.run_id = run_id
        tracker.log_params({"config": asdict(cfg), "ppo": asdict(trainer.ppo), "task": trainer.task.name})
        trainer.run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(trainer.run_dir / "config.json", json.dumps(asdict(cfg), indent=2).encode())
        trainer.train(progress=progress)
        trainer.write_history()
        for name in ("config.json", "last.pt", "history.csv", "curve.png"):
            tracker.log_artifact(trainer.run_dir / name)
    return trainer
