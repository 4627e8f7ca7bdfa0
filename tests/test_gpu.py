"""The PPO update on a GPU (``device`` auto or cuda; skipped where torch sees none): the CPU's update to float
precision. Run on a machine with CUDA torch: ``pytest tests/test_gpu.py``."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from atdrone.config import load_task
from atdrone.learn.learner import Learner, LearnerSpec
from atdrone.learn.ppo import ppo_config
from atdrone.learn.rollout import RolloutWorker

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU that torch sees")
TASK = load_task("4p2e1o")


def _flat(weights: dict[str, torch.Tensor]) -> torch.Tensor:
    return torch.cat([v.reshape(-1).float() for v in weights.values()])


def test_an_update_on_cuda_is_the_cpus_to_float_precision() -> None:
    # 8 x 32 steps x 4 learners = one minibatch of 1,024 samples, one epoch: a single Adam step, which moves
    # every parameter by about lr in its gradient's direction, so the two steps can be compared sign by sign
    ppo = ppo_config({"entity_dim": 8, "hidden": 16, "num_envs": 8, "rollout_steps": 32, "epochs": 1})
    ppo = dataclasses.replace(ppo, minibatch_size=1024)
    spec = LearnerSpec(ppo=ppo, num_e=TASK.players.num_e, num_p=TASK.players.num_p, seed=3, total_updates=2)
    cpu, gpu = Learner(dataclasses.replace(spec, device="cpu")), Learner(dataclasses.replace(spec, device="auto"))
    assert cpu.device.type == "cpu" and gpu.device.type == "cuda"
    assert all(p.is_cuda for p in gpu.model.parameters())
    worker = RolloutWorker(TASK, 7, cpu.model.architecture(), ppo)
    worker.set_weights(cpu.get_weights())
    fragment = worker.collect(ppo.rollout_steps)
    before = _flat(cpu.get_weights())
    assert torch.equal(before, _flat(gpu.get_weights()))  # the same seeded start on both devices
    on_cpu, on_gpu = cpu.update(fragment), gpu.update(fragment)
    for key in ("train/policy_loss", "train/value_loss", "train/entropy", "train/approx_kl"):
        assert on_gpu[key] == pytest.approx(on_cpu[key], rel=1e-3, abs=1e-6), key
    step_cpu, step_gpu = _flat(cpu.get_weights()) - before, _flat(gpu.get_weights()) - before
    moved = step_cpu.abs() > ppo.lr / 2  # the components whose gradient is clear of Adam's epsilon
    assert moved.float().mean() > 0.5  # (the rest: gradients near zero or none from this fragment)
    agree = (torch.sign(step_cpu[moved]) == torch.sign(step_gpu[moved])).float().mean()
    assert agree > 0.99, f"only {agree:.3f} of the parameters moved the same way on the GPU"
    close = ((step_gpu[moved] - step_cpu[moved]).abs() <= 0.01 * ppo.lr).float().mean()
    assert close > 0.99, f"only {close:.3f} of the parameters moved as far on the GPU (the learning rate, the step)"
