"""The local single-process PPO trainer behind ``atdrone train CONFIG``.

Modes: ``self_play`` (IPPO, one network shared by every pursuer), ``mappo`` (the
same with a centralised critic) and ``best_response`` (num_ctrl learners with zoo
partners). A run lives in ``<out_dir>/<name>/``: the config, ``last.pt`` (policy
checkpoint), ``learner_state.safetensors`` (the learner's state: weights, optimiser,
RNG, schedule position, plus the run's counters and MLflow run id), ``history.csv`` and
``curve.png``; ``--resume`` continues exactly where the last save stopped.
"""

from __future__ import annotations

import io
import json
import logging
import math
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd
import torch

from atdrone.config import (
    OPTIONAL,
    ConfigError,
    TaskConfig,
    check_run_name,
    check_seed,
    check_task_field,
    load_config,
    load_task,
    repo_path,
    require_at_least,
    require_at_most,
)
from atdrone.fileio import atomic_write_bytes
from atdrone.learn.learner import Learner, LearnerSpec, check_device
from atdrone.learn.ppo import PPOConfig, ppo_config, ppo_document, saved_ppo_document
from atdrone.learn.rollout import RolloutWorker
from atdrone.learn.sizes import MixedSizeWorker, check_sizes, make_worker
from atdrone.models import build_model
from atdrone.models.checkpoint import save_checkpoint
from atdrone.models.networks import ActorCritic
from atdrone.policies.base import Policy
from atdrone.policies.neural import NeuralPolicy
from atdrone.policies.zoo import PolicyError, load_zoo
from atdrone.rundir import RunError, check_resume, refuse_existing
from atdrone.teams.evaluation import metrics, run_episodes
from atdrone.teams.protocols import check_split, load_protocol

log = logging.getLogger(__name__)
STATE_FILE = "learner_state.safetensors"
# what a resume may change; anything else in the run's config.json must match (atdrone.rundir.check_resume)
RESUME_MAY_CHANGE = (
    "total_env_steps",
    "max_minutes",
    "out_dir",
    "torch_threads",
    "update_threads",
    "device",
    "eval_every",
    "eval_episodes",
    "checkpoint_every",
)


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
    protocol: train with the team events of this protocol (configs/protocols/, e.g.
    zoo3+swap: its events only; the partners stay the mode's) drawn in every episode,
    and its split of the team (``learners``: how many of the mode's learner slots the
    learner flies; a copy of the learner, not trained on, or a zoo partner flies the rest).
    Bounds (checked by :func:`load_train_config`): name a run name (letters, digits, '.',
    '_', '-'; see :func:`atdrone.config.check_run_name`), seed in [0, 2**32 - 1],
    sizes within :data:`TRAIN_LIMITS`, device auto, cpu or a CUDA device torch sees.
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
    protocol: str = field(default="", metadata=OPTIONAL)


# upper bounds of a train config's sizes (the paper's runs: 2e6-1e7 env steps, 200 evaluation episodes)
TRAIN_LIMITS = {"total_env_steps": 10**12, "eval_episodes": 100_000, "torch_threads": 256, "update_threads": 256}


def load_train_config(path_or_doc: str | Path | dict[str, Any], **overrides: Any) -> TrainConfig:
    """A validated TrainConfig from a JSON file or mapping (plus overrides).

    Everything a run would trip over later is refused here, before anything is written:
    the run name, seed, bounds (:data:`TRAIN_LIMITS`) and device first, then the task,
    the PPO section, the zoo (best_response only, every checkpoint loaded) and the
    initial checkpoint (loaded, trained on the same task).
    """
    cfg: TrainConfig = load_config(TrainConfig, path_or_doc, "train", **overrides)
    _check_settings(cfg)
    task = check_task_field(cfg.task)
    cfg = replace(cfg, ppo=ppo_document(ppo_config(cfg.ppo, cfg.preset)))  # every value, as the run saves it
    if cfg.mode == "best_response" and not cfg.zoo:
        raise ConfigError("zoo", "best_response training needs a zoo")
    if cfg.zoo and cfg.mode != "best_response":
        raise ConfigError("zoo", f"only best_response trains with zoo partners; {cfg.mode} would ignore {cfg.zoo!r}")
    if cfg.zoo:
        try:
            load_zoo(cfg.zoo, cfg.task).check()
        except (ConfigError, PolicyError) as exc:
            raise ConfigError("zoo", str(exc)) from None
    if cfg.init_checkpoint:
        _check_init_checkpoint(cfg.init_checkpoint, task.name)
    if cfg.protocol:
        try:
            protocol = load_protocol(cfg.protocol)
        except ConfigError as exc:
            raise ConfigError("protocol", str(exc)) from None
        slots = task.players.num_ctrl if cfg.mode == "best_response" else task.players.num_p
        check_split(protocol.split, slots, "protocol")
        check_sizes(protocol.sizes, task, "protocol")
    return cfg


def _check_settings(cfg: TrainConfig) -> None:
    """The settings that need no file: run name, seed, bounds, device."""
    check_run_name(cfg.name)
    check_seed(cfg.seed)
    require_at_least(
        cfg, ("total_env_steps", "eval_every", "eval_episodes", "checkpoint_every", "torch_threads", "update_threads")
    )
    require_at_most(cfg, TRAIN_LIMITS)
    check_device(cfg.device)
    if cfg.max_minutes < 0:
        raise ConfigError("max_minutes", f"must be >= 0, got {cfg.max_minutes}")
    if cfg.start_std < 0:
        raise ConfigError("start_std", f"must be >= 0, got {cfg.start_std}")
    if not 0 <= cfg.stop_at_suc <= 100:
        raise ConfigError("stop_at_suc", f"must be a percentage in [0, 100], got {cfg.stop_at_suc}")


def _check_init_checkpoint(checkpoint: str, task: str) -> None:
    """ConfigError unless ``checkpoint`` (as given, else repository-relative) loads and was trained on ``task``."""
    from atdrone.models.checkpoint import CheckpointError, load_checkpoint

    path = Path(checkpoint)
    if not path.exists():
        path = repo_path(path)
    if not path.is_file():
        what = "is a directory, not a checkpoint file" if path.is_dir() else "no such file (train that run first)"
        raise ConfigError("init_checkpoint", f"{checkpoint}: {what}")
    try:
        load_checkpoint(path, expect_task=task)
    except CheckpointError as exc:
        raise ConfigError("init_checkpoint", str(exc)) from None


class Trainer:
    """Collect -> PPO update (a :class:`~atdrone.learn.learner.Learner`) -> evaluate -> checkpoint, in one process."""

    def __init__(self, cfg: TrainConfig, tracker: Any | None = None) -> None:
        self.cfg = cfg
        self.task = load_task(cfg.task)
        self.ppo: PPOConfig = ppo_config(cfg.ppo, cfg.preset)
        self.run_dir = Path(cfg.out_dir) / cfg.name
        torch.set_num_threads(cfg.torch_threads)
        self.learner = Learner(
            LearnerSpec(
                ppo=self.ppo,
                num_e=self.task.players.num_e,
                num_p=self.task.players.num_p,
                seed=cfg.seed,
                total_updates=cfg.total_env_steps / (self.ppo.num_envs * self.ppo.rollout_steps),
                centralised_critic=cfg.mode == "mappo" or cfg.centralised_critic,
                device=cfg.device,
            )
        )
        self.model = self.learner.model
        if cfg.init_checkpoint:
            self._start_from(cfg.init_checkpoint)
        if cfg.start_std > 0:
            if not isinstance(self.model, ActorCritic):
                raise ConfigError("start_std", f"{self.model.architecture()['class']} has no exploration std to set")
            with torch.no_grad():
                self.model.log_std.fill_(math.log(cfg.start_std))
        self.partners: list[Policy] = load_zoo(cfg.zoo, cfg.task).policies() if cfg.mode == "best_response" else []
        self.worker = self._fresh_worker(0)
        self.tracker = tracker
        self.env_steps = 0
        self.history: list[dict[str, float]] = []
        self.run_id: str | None = None

    def _fresh_worker(self, updates: int) -> RolloutWorker | MixedSizeWorker:
        """The rollout worker of the stretch that starts after ``updates`` updates: new environments, seeded
        from (seed, updates), so a run resumed from a save collects exactly what the uninterrupted run did
        (each save starts the next stretch in both)."""
        seed = (
            self.cfg.seed
            if updates == 0
            else int(np.random.SeedSequence([self.cfg.seed, updates]).generate_state(1)[0])
        )
        protocol = load_protocol(self.cfg.protocol) if self.cfg.protocol else None
        return make_worker(
            self.task,
            seed,
            self.model.architecture(),
            self.ppo,
            sizes=protocol.sizes if protocol is not None else None,
            partners=self._partners,
            events=protocol.plan if protocol is not None else None,
            split=protocol.split if protocol is not None else None,
        )

    def _partners(self, task: TaskConfig) -> list[Policy]:
        """The partner policies of a team of ``task``'s size: the zoo's, loaded once more for each other size
        (a policy keeps per-drone memory)."""
        if task.players.num_p == self.task.players.num_p or self.cfg.mode != "best_response":
            return list(self.partners)
        return list(load_zoo(self.cfg.zoo, self.cfg.task).policies())

    def _start_from(self, checkpoint: str) -> None:
        """Take a checkpoint's weights: the same architecture, or a narrower one widened with zero weights."""
        from atdrone.models.checkpoint import load_checkpoint

        path = Path(checkpoint)
        if not path.exists():  # repository-relative, like zoo checkpoints
            path = repo_path(path)
        if not path.is_file():
            raise ConfigError("init_checkpoint", f"no checkpoint at {checkpoint} (train that run first)")
        start, _ = load_checkpoint(path, expect_task=self.task.name)
        try:
            if start.architecture() == self.model.architecture():
                self.model.load_state_dict(start.state_dict())
            else:
                self.model.widen_from(start)  # the new inputs get zero weights, else ValueError
        except ValueError:
            raise ConfigError(
                "init_checkpoint", f"architecture {start.architecture()} does not match {self.model.architecture()}"
            ) from None

    @property
    def updates(self) -> int:
        return self.learner.updates

    # ------------------------------------------------------------ persistence
    def save(self, metrics_now: dict[str, float] | None = None) -> Path:
        """Write last.pt and the learner state (with the run's counters) atomically; returns the checkpoint path."""
        self.run_dir.mkdir(parents=True, exist_ok=True)
        ckpt = self.run_dir / "last.pt"
        save_checkpoint(ckpt, self.model, self.header(metrics_now))
        extra = {"env_steps": self.env_steps, "history": self.history, "run_id": self.run_id}
        self.learner.save(self.run_dir / STATE_FILE, extra)
        self.worker = self._fresh_worker(self.updates)
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
        """Load the learner state (and its counters) when present; True when resumed."""
        state_path = self.run_dir / STATE_FILE
        if not state_path.is_file():
            if (self.run_dir / "trainer_state.pt").is_file():
                raise RunError(
                    f"{self.run_dir} was saved by an older atdrone (trainer_state.pt, a pickle): it cannot be "
                    "resumed; start a new run from its weights with init_checkpoint: last.pt"
                )
            return False
        extra = self.learner.load(state_path)
        self.env_steps, self.history, self.run_id = extra["env_steps"], extra["history"], extra["run_id"]
        self.worker = self._fresh_worker(self.updates)
        log.info("resumed %s at %d env steps", self.run_dir, self.env_steps)
        return True

    # --------------------------------------------------------------- training
    def policy(self, deterministic: bool = True) -> NeuralPolicy:
        cpu = build_model(self.model.architecture())
        cpu.load_state_dict(self.learner.get_weights())
        cpu.eval()
        players = self.task.players
        return NeuralPolicy(cpu, self.cfg.name, deterministic, num_p=players.num_p, num_e=players.num_e)

    def evaluate(self, episodes: int, seed: int = 12345) -> dict[str, float]:
        """SUC/COL/AST/REW of the current policy: self-play (all slots) or with the zoo."""
        policy = self.policy()
        partners = self.partners or [policy]
        records = run_episodes(policy, self.task, partners, episodes, seed=seed)
        return metrics(records)

    def update_once(self) -> dict[str, float]:
        """One rollout and one learner update; returns train/ and perf/ metrics."""
        t0 = time.perf_counter()
        self.worker.set_weights(self.learner.get_weights())
        frag = self.worker.collect(self.ppo.rollout_steps)
        torch.set_num_threads(self.cfg.update_threads)  # the rollout is idle while the update runs
        out = self.learner.update(frag)
        torch.set_num_threads(self.cfg.torch_threads)
        self.env_steps += frag.dones.size
        out["perf/pursuer_steps_per_s"] = frag.samples / (time.perf_counter() - t0)
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

    run_dir = Path(cfg.out_dir) / cfg.name
    if resume and (run_dir / "config.json").exists():
        check_resume(run_dir, asdict(cfg), RESUME_MAY_CHANGE, saved_ppo_document)
    elif not resume and ((run_dir / STATE_FILE).exists() or (run_dir / "trainer_state.pt").exists()):
        refuse_existing(run_dir)
    trainer = Trainer(cfg)
    if resume and not trainer.resume():
        log.info("nothing to resume in %s: starting fresh", trainer.run_dir)
    tracker = Tracker(uri)
    trainer.tracker = tracker
    experiment = cfg.experiment or cfg.name
    with tracker.run(experiment, f"{cfg.name}-seed{cfg.seed}", run_id=trainer.run_id) as run_id:
        trainer.run_id = run_id
        from atdrone.policies.manifest import task_version

        zoo_version = task_version(trainer.task.name)  # the partners its evaluations (best response) play
        tracker.log_params({"config": asdict(cfg), "ppo": asdict(trainer.ppo), "task": trainer.task.name})
        tracker.set_tags({"atdrone.zoo_version": zoo_version})
        if cfg.protocol:  # the team events and split its training drew, as the document stood
            protocol = load_protocol(cfg.protocol)
            tracker.set_tags({"atdrone.protocol": protocol.name})
            tracker.log_dict(protocol.to_dict(), "protocol.json")
        trainer.run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_bytes(trainer.run_dir / "config.json", json.dumps(asdict(cfg), indent=2).encode())
        trainer.train(progress=progress)
        trainer.write_history()
        for name in ("config.json", "last.pt", "history.csv", "curve.png"):
            tracker.log_artifact(trainer.run_dir / name)
    return trainer
