"""The model layer: the architectures table, per-drone memory, checkpoint format 2 and its legacy path."""

from __future__ import annotations

import hashlib
import io
import json
import pickle
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch
from torch import nn

from atdrone.envs import BatchedPursuit
from atdrone.envs.core import OBS_LAYOUT_VERSION
from atdrone.models import ARCHITECTURES, CheckpointError, DroneMemory, PolicyModel, build_model
from atdrone.models.checkpoint import MAGIC, load_checkpoint, read_header, save_checkpoint, sign_header
from atdrone.models.history import ObsHistory, StatelessMemory
from atdrone.models.networks import ActorCritic, NetConfig
from atdrone.policies.base import PolicyError
from atdrone.policies.neural import PAD_ROWS, NeuralPolicy, load_policy

ZOO = Path(__file__).resolve().parents[1] / "configs" / "zoos" / "checkpoints" / "4p2e1o"
D = 24  # 4p2e observation width: 4 features x (2 evaders + 1 obstacle + 3 teammates)


class LinearActorCritic(nn.Module):
    """A new architecture known only to this file: a linear actor and critic on the observation."""

    def __init__(self, obs_dim: int = D) -> None:
        super().__init__()
        self.obs_dim = obs_dim
        self.actor = nn.Linear(obs_dim, 1)
        self.critic = nn.Linear(obs_dim, 1)
        self.log_std = nn.Parameter(torch.zeros(1))

    @classmethod
    def from_architecture(cls, config: Mapping[str, Any]) -> LinearActorCritic:
        return cls(**config)

    @property
    def centralised(self) -> bool:
        return False

    def architecture(self) -> dict[str, Any]:
        return {"class": "LinearActorCritic", "obs_dim": self.obs_dim}

    def memory(self, num_envs: int, num_keys: int, obs_dim: int) -> DroneMemory:
        return StatelessMemory(obs_dim)

    def dist(self, inputs: torch.Tensor, num_e: int) -> torch.distributions.Normal:
        mu = self.actor(inputs).squeeze(-1)
        return torch.distributions.Normal(mu, self.log_std.exp().expand_as(mu))

    def value(
        self, inputs: torch.Tensor, num_e: int, state: torch.Tensor | None = None, num_p: int = 0
    ) -> torch.Tensor:
        return self.critic(inputs).squeeze(-1)

    def parameter_groups(self) -> tuple[list[nn.Parameter], list[nn.Parameter]]:
        return [*self.actor.parameters(), self.log_std], list(self.critic.parameters())

    def widen_from(self, other: PolicyModel) -> None:
        raise ValueError("a linear actor-critic does not widen")


def _model(history: int = 0, seed: int = 0) -> ActorCritic:
    torch.manual_seed(seed)
    model = ActorCritic(NetConfig(entity_dim=16, hidden=32, history=history))
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn_like(p))
    return model.eval()


def _header(**extra: Any) -> dict[str, Any]:
    return {"task": "4p2e1o", "num_p": 4, "num_e": 2, "seed": 0, "step": 7, **extra}


def _observations(n: int, seed: int = 0) -> np.ndarray:
    """Observations of a 4p2e task, drawn from a seeded simulator run."""
    env = BatchedPursuit("4p2e1o", num_envs=n, seed=seed)
    return env.reset().reshape(-1, D)


def _actions(model: PolicyModel, obs: np.ndarray, num_e: int = 2) -> np.ndarray:
    """The network's mean actions on ``obs``, run on a batch padded as NeuralPolicy pads it (the same rounding)."""
    padded = np.zeros((-len(obs) // PAD_ROWS * -PAD_ROWS, obs.shape[1]), obs.dtype)
    padded[: len(obs)] = obs
    with torch.no_grad():
        return torch.tanh(model.dist(torch.from_numpy(padded), num_e).mean).numpy()[: len(obs)]


def test_a_new_architecture_plugs_in_through_the_table(tmp_path, monkeypatch):
    monkeypatch.setitem(ARCHITECTURES, "LinearActorCritic", LinearActorCritic)
    torch.manual_seed(1)
    model = LinearActorCritic()
    path = tmp_path / "linear.pt"
    header = save_checkpoint(path, model, _header(name="linear"))
    assert header["architecture"] == {"class": "LinearActorCritic", "obs_dim": D}
    policy = load_policy(path)
    assert isinstance(policy.model, LinearActorCritic) and policy.name == "linear"
    env = BatchedPursuit("4p2e1o", num_envs=3, seed=2)
    obs = env.reset()
    keys = np.tile(np.arange(4), 3)
    rows = np.repeat(np.arange(3), 4)
    for _ in range(5):  # flies in the simulator, acting on observations and memory keys
        flat = obs.reshape(-1, D)
        actions = policy.act_obs(flat, rows, keys)
        np.testing.assert_array_equal(actions, _actions(model, flat))
        obs, _, done, _ = env.step(actions.reshape(3, 4))
        policy.reset(done)


def test_an_unknown_architecture_is_refused_naming_the_known_ones(tmp_path, monkeypatch):
    with pytest.raises(CheckpointError, match=r"'Transformer'.*ActorCritic"):
        build_model({"class": "Transformer", "layers": 2})
    monkeypatch.setitem(ARCHITECTURES, "LinearActorCritic", LinearActorCritic)
    path = tmp_path / "linear.pt"
    save_checkpoint(path, LinearActorCritic(), _header())
    monkeypatch.delitem(ARCHITECTURES, "LinearActorCritic")
    with pytest.raises(CheckpointError, match="LinearActorCritic"):
        load_checkpoint(path)
    with pytest.raises(CheckpointError, match="cannot be built"):
        build_model({"class": "ActorCritic", "width": 3})


def test_actor_critic_is_a_policy_model_and_builds_from_its_header_entry():
    model = _model(history=2)
    assert isinstance(model, PolicyModel)
    twin = build_model(model.architecture())
    assert isinstance(twin, ActorCritic) and twin.cfg == model.cfg and not twin.centralised
    assert isinstance(model.memory(2, 4, D), ObsHistory) and isinstance(_model().memory(2, 4, D), StatelessMemory)
    assert model.memory(2, 4, D).input_dim == 3 * D + 2


def test_checkpoint_round_trip_gives_identical_actions(tmp_path):
    model = _model(history=1)
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, _header(name="m"))
    loaded, header = load_checkpoint(path, expect_task="4p2e1o")
    assert header["format"] == 2 and header["architecture"]["history"] == 1
    for name, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], value)
    inputs = model.memory(8, 4, D).inputs(_observations(2), np.repeat(np.arange(2), 4), np.tile(np.arange(4), 2))
    np.testing.assert_array_equal(_actions(loaded, inputs), _actions(model, inputs))
    head = path.read_bytes().split(b"\n", 2)
    assert head[0] + b"\n" == MAGIC and json.loads(head[1]) == header == read_header(path)


def test_format_2_loads_without_unpickling(tmp_path, monkeypatch):
    model = _model()
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, _header())

    def refuse(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("unpickling while loading a format 2 checkpoint")

    monkeypatch.setattr(torch, "load", refuse)
    monkeypatch.setattr(pickle, "Unpickler", refuse)
    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    policy = load_policy(path)
    obs = _observations(2)
    np.testing.assert_array_equal(policy.act_obs(obs, np.zeros(8, int), np.arange(8)), _actions(model, obs))


@pytest.mark.parametrize("damage", ["flip", "truncate"])
def test_damaged_payload_is_refused_naming_sha256(tmp_path, damage):
    path = tmp_path / "m.pt"
    save_checkpoint(path, _model(), _header())
    data = bytearray(path.read_bytes())
    if damage == "flip":
        data[-10] ^= 0xFF
    else:
        del data[-100:]
    path.write_bytes(bytes(data))
    with pytest.raises(CheckpointError, match="sha256"):
        load_checkpoint(path)


def _write_format_1(path: Path, model: ActorCritic) -> None:
    """A checkpoint as atdrone wrote it before format 2: torch.save behind the same header."""
    buf = io.BytesIO()
    torch.save(model.state_dict(), buf)
    payload = buf.getvalue()
    header = {
        "format": 1,
        "architecture": model.architecture(),
        "obs_layout_version": OBS_LAYOUT_VERSION,
        **_header(),
        "sha256": hashlib.sha256(payload).hexdigest(),
    }
    path.write_bytes(MAGIC + json.dumps(header).encode() + b"\n" + payload)


def test_format_1_legacy_file_still_loads(tmp_path):
    model = _model()
    path = tmp_path / "old.pt"
    _write_format_1(path, model)
    with pytest.warns(UserWarning, match="not covered by a digest"):
        loaded, header = load_checkpoint(path)
    assert header["format"] == 1
    obs = _observations(2)
    np.testing.assert_array_equal(_actions(loaded, obs), _actions(model, obs))


def test_an_unknown_format_is_refused(tmp_path):
    path = tmp_path / "m.pt"
    save_checkpoint(path, _model(), _header())
    sign_header(path, format=7)
    with pytest.raises(CheckpointError, match="format 7"):
        load_checkpoint(path)


@pytest.mark.parametrize(
    "edit", [(b'"task": "4p2e1o"', b'"task": "4p2e3o"'), (b'"eval/SUC": 10.0', b'"eval/SUC": 99.0')]
)
def test_an_edited_header_is_refused(tmp_path, edit):
    path = tmp_path / "m.pt"
    save_checkpoint(path, _model(), _header(metrics={"eval/SUC": 10.0}))
    data = path.read_bytes()
    assert edit[0] in data
    path.write_bytes(data.replace(*edit, 1))
    with pytest.raises(CheckpointError, match="header was changed"):
        load_checkpoint(path)


def test_a_directory_is_not_a_checkpoint(tmp_path):
    with pytest.raises(CheckpointError, match="is a directory"):
        load_checkpoint(tmp_path)


def test_a_crafted_header_declaring_a_huge_network_is_refused_before_allocating(tmp_path):
    path = tmp_path / "huge.pt"
    save_checkpoint(path, _model(), _header())
    sign_header(path, architecture={"class": "ActorCritic", "entity_dim": 10**6, "hidden": 10**6})
    assert path.stat().st_size < 400_000
    with pytest.raises(CheckpointError, match="entity_dim must be an integer between 1 and 1024"):
        load_checkpoint(path)


def test_memory_grows_for_new_environments_and_keys():
    mem = ObsHistory(history=1, num_envs=1, num_keys=1, obs_dim=2)
    a = np.array([[1.0, 2.0]], np.float32)
    mem.record(a, np.array([0]), np.array([0]), np.array([0.5]))
    b = np.array([[3.0, 4.0], [5.0, 6.0], [7.0, 8.0]], np.float32)
    env, key = np.array([0, 2, 0]), np.array([0, 0, 3])
    # drone (0, 0) remembers its frame and action; the new drones (2, 0) and (0, 3) start fresh
    np.testing.assert_array_equal(mem.inputs(b, env, key), [[3, 4, 1, 2, 0.5], [5, 6, 5, 6, 0], [7, 8, 7, 8, 0]])
    assert mem.shape == (3, 4, 2)
    mem.record(b, env, key, np.array([0.1, 0.2, 0.3], np.float32))
    mem.reset(np.array([False, False, True, True, True]))  # rows beyond the memory hold nothing to forget
    np.testing.assert_array_equal(mem.inputs(b, env, key)[:, 2:], np.float32([[3, 4, 0.1], [5, 6, 0], [7, 8, 0.3]]))
    stateless = StatelessMemory(2)
    assert stateless.input_dim == 2 and np.array_equal(stateless.inputs(b, env, key), b)


def test_neural_policy_acts_on_observations_and_keys_with_the_header_task_shape(tmp_path):
    model = _model(history=1)
    path = tmp_path / "m.pt"
    save_checkpoint(path, model, _header(task="4p2e3o", name="remembers"))
    policy = load_policy(path)
    assert (policy.num_p, policy.num_e, policy.name) == (4, 2, "remembers")
    rng = np.random.default_rng(0)
    obs = rng.uniform(-1, 1, (3, D)).astype(np.float32)
    env, key = np.array([0, 7, 7]), np.array([2, 0, 9])  # any keys: the memory grows to hold them
    first = policy.act_obs(obs, env, key)
    fresh = np.concatenate([obs, obs, np.zeros((3, 1), np.float32)], -1)
    np.testing.assert_array_equal(first, _actions(model, fresh))
    later = rng.uniform(-1, 1, (3, D)).astype(np.float32)
    remembered = np.concatenate([later, obs, first[:, None].astype(np.float32)], -1)
    second = policy.act_obs(later, env, key)
    np.testing.assert_array_equal(second, _actions(model, remembered))
    done = np.zeros(8, bool)
    done[7] = True  # env 7's episode ended: its drones start over, env 0's keeps its past
    policy.reset(done)
    inputs = policy.inputs_of(later, env, key)
    np.testing.assert_array_equal(inputs[0, D : 2 * D], later[0])
    np.testing.assert_array_equal(inputs[1:, D : 2 * D], later[1:])
    np.testing.assert_array_equal(inputs[:, -1], [np.float32(second[0]), 0.0, 0.0])
    with pytest.raises(PolicyError, match="width 10"):
        policy.act_obs(np.zeros((1, 10), np.float32), np.array([0]), np.array([0]))


def test_neural_policy_reads_another_evader_count_off_the_observation_width():
    model = _model()
    policy = NeuralPolicy(model, num_p=4, num_e=2)
    obs = np.random.default_rng(1).uniform(-1, 1, (4, 28)).astype(np.float32)  # 4p3e: 7 entity blocks
    np.testing.assert_array_equal(policy.act_obs(obs, np.zeros(4, int), np.arange(4)), _actions(model, obs, 3))


@pytest.mark.parametrize("name", ["sp_high", "sp_low"])
def test_zoo_checkpoints_are_format_2_with_their_provenance(name):
    header = read_header(ZOO / f"{name}.pt")
    assert header["format"] == 2 and header["task"] == "4p2e1o" and header["algorithm"] == "SP-IPPO"
    assert header["name"] == name and (header["num_p"], header["num_e"]) == (4, 2)
    model, _ = load_checkpoint(ZOO / f"{name}.pt")
    assert isinstance(model, ActorCritic) and model.cfg.history == 0
