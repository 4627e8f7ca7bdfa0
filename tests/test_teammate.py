"""Teammate modelling (NAHT-D), MAPPO's decentralised actor and training pools kept apart from the zoos."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
import torch

from atdrone.cli import main
from atdrone.config import CONFIG_DIR, TASK_NAMES, ConfigError, TaskConfig, load_task
from atdrone.learn import rollout
from atdrone.learn.learner import Learner, LearnerSpec
from atdrone.learn.ppo import PPOConfig, architecture
from atdrone.learn.rollout import RolloutWorker
from atdrone.models.teammate import TeammateActorCritic, TeammateConfig
from atdrone.policies.base import DroneBatch, StatelessPolicy
from atdrone.policies.rules import GreedyPolicy
from atdrone.policies.zoo import ZOO_NAMES, checkpoint_path, load_zoo
from atdrone.service.experiment import load_experiment
from atdrone.teams.partners import LEARNER_COPY, VariableCount
from atdrone.teams.pools import check_pool, load_pool, shared_members

TINY_PPO = PPOConfig(num_envs=16, rollout_steps=16, entity_dim=16, hidden=32, minibatch_size=128, epochs=1)


def _naht(decoder: bool = True, **kw: object) -> dict:
    return TeammateActorCritic.header(TeammateConfig(decoder=decoder, entity_dim=16, hidden=32, **kw))  # type: ignore[arg-type]


class NearestMateTurn(StatelessPolicy):
    """A planted partner: turns hard left when another pursuer is within 1 m of it, else hard right.

    With one learner and one partner (:func:`_pair_task`) the partner's only teammate
    is the learner, so its turn is a function of a distance the learner observes. A
    greedy drone's turn is not: it depends on its own heading, which no teammate
    observes (see the algorithms docs for the measurement).
    """

    name = "mate_turn"

    def act(self, batch: DroneBatch) -> np.ndarray:
        poses = batch.need_poses(self.name)
        pursuers = poses.pos[batch.env, : poses.arena.num_p]
        dist = np.linalg.norm(pursuers - batch.pos[:, None], axis=-1)
        dist[np.arange(len(batch)), batch.slot] = np.inf
        return np.where(dist.min(-1) < 1.0, 1.0, -1.0)


def _pair_task() -> TaskConfig:
    """4p2e1o's arena with two pursuers: one learner and one partner."""
    task = load_task("4p2e1o")
    return replace(task, players=replace(task.players, num_p=2, num_ctrl=1, num_unctrl=1))


def _data(worker: RolloutWorker, fragments: int, steps: int) -> tuple[torch.Tensor, torch.Tensor]:
    batches = [worker.collect(steps).batch(0.99, 0.95) for _ in range(fragments)]
    return (
        torch.from_numpy(np.concatenate([b["obs"] for b in batches])),
        torch.from_numpy(np.concatenate([b["mates"] for b in batches])),
    )


def _fit_decoder(model: TeammateActorCritic, x: torch.Tensor, m: torch.Tensor, steps: int) -> None:
    params = list(model.encoder.parameters()) + list(model.decoder.parameters())  # type: ignore[union-attr]
    opt = torch.optim.Adam(params, lr=3e-3)
    g = torch.Generator().manual_seed(0)
    for _ in range(steps):
        idx = torch.randint(len(x), (256,), generator=g)
        loss = model.decoder_loss(x[idx], m[idx])
        opt.zero_grad()
        loss.backward()
        opt.step()


def test_the_rollout_records_each_teammates_executed_turn_and_distribution():
    zoo = load_zoo("zoo3", "4p2e1o").policies()
    worker = RolloutWorker("4p2e1o", 3, _naht(), TINY_PPO, partners=[zoo[0], zoo[2]], num_ctrl=2)
    frag = worker.collect(12)
    assert frag.mates is not None and frag.mates.shape == (12, 16, 2, 3, 3)
    slots, members = frag.extras["learner_slots"], frag.extras["partner_members"]
    for t, b, i in np.ndindex(12, 16, 2):
        others = [s for s in range(4) if s != slots[t, b, i]]  # the observation's teammate order
        other_learner = others.index(slots[t, b, 1 - i])
        turn, mean, std = frag.mates[t, b, i, other_learner]
        assert turn == pytest.approx(np.tanh(frag.u[t, b, 1 - i]), abs=1e-6)
        assert np.isfinite(mean) and std == pytest.approx(np.exp(-0.5), rel=1e-5)
        partners = [j for j, s in enumerate(others) if s != slots[t, b, 1 - i]]
        turns, stds = frag.mates[t, b, i, partners, 0], frag.mates[t, b, i, partners, 2]
        assert sorted(turns) == sorted(frag.extras["partner_actions"][t, b])
        assert np.isfinite(stds).sum() == (members[t, b] == 1).sum()  # sp_high (a network) has a Gaussian, greedy none


def test_the_decoder_learns_a_partners_turn_from_what_the_learner_sees():
    # Worker seed 1: with per-episode draws (issue 26) the fit ends at 0.50 of the mean-turn error on seed 0's
    # data (a local optimum: 600 steps give 0.49), at 0.04-0.17 on seeds 1-9 (before: 0.04-0.12, seeds 0-7).
    torch.manual_seed(0)
    arch = _naht(num_p=2)
    worker = RolloutWorker(_pair_task(), 1, arch, TINY_PPO, partners=[NearestMateTurn()], num_ctrl=1)
    x, m = _data(worker, 8, 32)
    x_test, m_test = _data(worker, 2, 32)
    model = worker.model
    assert isinstance(model, TeammateActorCritic)

    def errors() -> tuple[float, float]:
        with torch.no_grad():
            mean, _ = model.decode(x_test)
        rule = ~torch.isfinite(m_test[..., 2])
        turns = m_test[..., 0][rule]
        return float(((torch.tanh(mean)[rule] - turns) ** 2).mean()), float(((turns - turns.mean()) ** 2).mean())

    before, mean_turn = errors()
    assert before > 0.9 * mean_turn  # untrained: no better than the mean turn
    _fit_decoder(model, x, m, 300)
    after, _ = errors()
    print(f"decoder error {after:.3f}, mean-turn error {mean_turn:.3f}")
    assert after < 0.35 * mean_turn, (after, mean_turn)


def test_without_the_decoder_there_are_no_decoder_parameters_and_no_decoder_loss():
    with_dec, without = (TeammateActorCritic(TeammateConfig(decoder=d)) for d in (True, False))
    assert without.decoder is None and not any("decoder" in n for n, _ in without.named_parameters())
    assert any("decoder" in n for n, _ in with_dec.named_parameters())
    names = {n for n, _ in with_dec.named_parameters()} - {n for n, _ in without.named_parameters()}
    assert names and all(n.startswith("decoder.") for n in names)
    stats = {}
    for decoder in (True, False):
        spec = LearnerSpec(TINY_PPO, num_e=2, num_p=4, seed=0, total_updates=2, architecture=_naht(decoder))
        learner = Learner(spec)
        worker = RolloutWorker("4p2e1o", 0, spec.model_architecture(), TINY_PPO, [GreedyPolicy()], num_ctrl=2)
        worker.set_weights(learner.get_weights())
        stats[decoder] = learner.update(worker.collect(16))
    assert stats[True]["train/decoder_loss"] > 0
    assert "train/decoder_loss" not in stats[False]
    with pytest.raises(ValueError, match="detach_embedding needs the decoder"):
        TeammateConfig(decoder=False, detach_embedding=True)


def test_the_decoder_loss_is_a_kl_for_networks_and_a_log_likelihood_for_rules():
    model = TeammateActorCritic(TeammateConfig(num_p=2, num_e=1, embed_dim=2, decoder_hidden=2))
    x = torch.zeros(1, 4 * 3 * 2 + 1)
    with torch.no_grad():
        mean, log_std = model.decode(x)
    m, s = float(mean[0, 0]), float(log_std[0, 0].exp())
    learned = torch.tensor([[[0.3, 0.5, 0.8]]])  # executed turn (ignored), mean 0.5, std 0.8
    kl = np.log(s / 0.8) + (0.8**2 + (0.5 - m) ** 2) / (2 * s**2) - 0.5
    assert model.decoder_loss(x, learned).item() == pytest.approx(kl, rel=1e-5)
    rule = torch.tensor([[[0.3, float("nan"), float("nan")]]])
    nll = np.log(s) + (0.3 - np.tanh(m)) ** 2 / (2 * s**2) + 0.5 * np.log(2 * np.pi)
    assert model.decoder_loss(x, rule).item() == pytest.approx(nll, rel=1e-5)


def test_the_mappo_actor_never_reads_the_global_state(monkeypatch):
    arch = architecture(TINY_PPO, centralised_critic=True)

    def collect(state_noise: float) -> rollout.Fragment:
        real = rollout.global_state
        rng = np.random.default_rng(7)

        def noisy(*args: object) -> np.ndarray:
            state = real(*args)  # type: ignore[arg-type]
            return (state + state_noise * rng.normal(size=state.shape)).astype(np.float32)

        monkeypatch.setattr(rollout, "global_state", noisy)
        worker = RolloutWorker("4p2e1o", 5, arch, TINY_PPO, [GreedyPolicy()], num_ctrl=2)
        torch.manual_seed(0)
        worker.set_weights(Learner(LearnerSpec(TINY_PPO, 2, 4, 0, 1, architecture=arch)).get_weights())
        return worker.collect(20)

    plain, noisy = collect(0.0), collect(5.0)
    assert plain.state is not None and noisy.state is not None
    assert not np.allclose(plain.state, noisy.state)
    assert np.array_equal(plain.u, noisy.u) and np.array_equal(plain.logp, noisy.logp)  # bit-identical actions
    assert not np.allclose(plain.values, noisy.values)  # the critic does read it


def test_a_pool_sharing_a_member_with_an_evaluation_zoo_is_refused_in_one_line(tmp_path, capsys):
    pool = tmp_path / "overlap.json"
    members = [
        {"name": "wide", "kind": "greedy", "params": {"avoid_range": 0.45}},
        {"name": "same_greedy", "kind": "greedy", "params": {"avoid_range": 0.3, "lookahead": 4}},  # = defaults
    ]
    pool.write_text(json.dumps({"name": "overlap", "members": members}))
    assert shared_members(load_pool(pool)) == ["same_greedy = zoo1:greedy, zoo3:greedy"]
    with pytest.raises(ConfigError, match=r"^naht_d\.pool: training pool 'overlap' shares members"):
        load_experiment({"name": "x", "algorithm": "naht_d", "task": "4p2e1o", "naht_d": {"pool": str(pool)}})
    doc = tmp_path / "exp.json"
    doc.write_text(json.dumps({"name": "x", "algorithm": "mappo", "task": "4p2e1o", "mappo": {"pool": str(pool)}}))
    assert main(["train", str(doc), "--out-dir", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "same_greedy = zoo1:greedy, zoo3:greedy" in err[0] and '"best_response": true' in err[0]
    assert not (tmp_path / "runs").exists()
    ok = {"pool": str(pool), "best_response": True}  # on purpose: then labelled a best response
    cfg = load_experiment({"name": "x", "algorithm": "mappo", "task": "4p2e1o", "mappo": ok})
    assert cfg.algorithm_config().best_response


def test_a_copied_checkpoint_is_the_same_member(tmp_path):
    copy = tmp_path / "copy.pt"
    copy.write_bytes((CONFIG_DIR / "zoos" / "checkpoints" / "4p2e1o" / "sp_high.pt").read_bytes())
    pool = tmp_path / "p.json"
    pool.write_text(
        json.dumps({"name": "p", "members": [{"name": "c", "kind": "checkpoint", "checkpoint": str(copy)}]})
    )
    assert shared_members(load_pool(pool)) == ["c = zoo2:sp_high, zoo3:sp_high"]
    assert check_pool("train_pool", False, "pool").name == "train_pool"  # the shipped pool is disjoint


def test_variable_count_draws_how_many_partners_then_who():
    dist = VariableCount(("a", "b", "c", LEARNER_COPY), min_partners=1)
    draws = dist.draw(np.random.default_rng(0), 20_000, 2)
    copies = (draws == 3).sum(1)
    assert set(np.unique(copies)) == {0, 1}  # one or two partners, never none
    assert abs((copies == 1).mean() - 0.5) < 0.02  # the count is uniform in 1..2
    partners = draws[draws != 3]
    assert np.allclose(np.bincount(partners) / len(partners), 1 / 3, atol=0.02)  # members uniform
    assert (VariableCount(("a", LEARNER_COPY), 0).draw(np.random.default_rng(1), 5000, 2) == 1).all(1).mean() > 0.25
    with pytest.raises(ValueError, match="followed by 'self'"):
        VariableCount(("a", "b"))


def test_a_slot_without_a_partner_is_flown_by_a_sampling_copy_of_the_learner():
    worker = RolloutWorker(
        "4p2e1o",
        4,
        _naht(),
        TINY_PPO,
        partners=[None, GreedyPolicy()],
        num_ctrl=2,
        sampler=lambda rng, n: np.tile([0, 1], (n, 1)),
    )
    frag = worker.collect(8)
    assert frag.u.shape == (8, 16, 2)  # the copy's steps are not the learners' samples
    assert frag.mates is not None
    finite = np.isfinite(frag.mates[..., 2]).sum(-1)
    assert (finite == 2).all()  # the other learner and the copy have Gaussians; the greedy drone none
    stds = frag.mates[..., 2][np.isfinite(frag.mates[..., 2])]
    assert np.allclose(stds, np.exp(-0.5), rtol=1e-5)  # the learner's own exploration noise
    learned = frag.mates[np.isfinite(frag.mates[..., 2])]  # (n, 3): the other learner's and the copy's
    sampled = np.abs(learned[:, 0] - np.tanh(learned[:, 1])) > 1e-4
    assert sampled.mean() > 0.95  # the copy samples like the learners (a mean-playing copy: half would match)
    assert set(worker.drawn) == {"greedy|self"}


def test_teammate_coef_weighs_the_decoder_loss_in_the_update():
    def updated(coef: float, decoder: bool) -> torch.Tensor:
        ppo = replace(TINY_PPO, teammate_coef=coef)
        spec = LearnerSpec(ppo, num_e=2, num_p=4, seed=0, total_updates=2, architecture=_naht(decoder))
        learner = Learner(spec)
        worker = RolloutWorker("4p2e1o", 0, spec.model_architecture(), ppo, [GreedyPolicy()], num_ctrl=2)
        worker.set_weights(learner.get_weights())
        learner.update(worker.collect(16))
        return torch.cat([p.flatten() for p in learner.get_weights().values()])

    assert not torch.equal(updated(1.0, True), updated(0.1, True))
    assert torch.equal(updated(1.0, False), updated(0.1, False))  # no decoder: nothing to weigh


def test_the_committed_validation_zoo_and_training_pool_share_no_drone_with_a_test_zoo():
    """Selection (validation) and training (the default pool) never see a test partner, and the pool is not the
    validation set either: by rule and parameters, and by weights digest for trained drones."""
    assert shared_members(load_zoo("validation")) == []
    assert shared_members(load_pool("train_pool"), (*ZOO_NAMES, "validation")) == []
    assert any(m.kind == "checkpoint" for m in load_zoo("validation").spec.members)  # trained drones, not rules only


def test_zoo4_is_held_out_and_not_made_by_the_zoo2_recipe():
    """Zoo 4 shares no drone with Zoos 1-3, the validation zoo or the default pool; its trained drones each differ
    from Zoo 2's recipe (IPPO self-play, default PPO) in mode, critic or PPO settings."""
    from atdrone.models.checkpoint import read_header

    zoo4 = load_zoo("zoo4")
    assert shared_members(zoo4, ("zoo1", "zoo2", "zoo3", "validation")) == []
    assert shared_members(load_pool("train_pool"), ("zoo4",)) == []
    assert len([m for m in zoo4.spec.members if m.kind == "checkpoint"]) == 6 and len(zoo4.spec.members) == 10
    for task in TASK_NAMES:  # every drone trained so far (tests/test_task_zoos.py names the missing ones)
        for m in zoo4.resolve(task).spec.members:
            if m.kind == "checkpoint" and checkpoint_path(m).is_file():
                cfg = read_header(checkpoint_path(m))["config"]
                assert cfg["mode"] != "self_play" or cfg["ppo"] or cfg.get("centralised_critic"), (m.name, cfg)
    vicsek = [m for m in zoo4.spec.members if m.kind == "vicsek"]
    assert len(vicsek) == 3 and all(m.params for m in vicsek)  # none is Zoo 3's default VICSEK drone
    assert sum(m.params.get("noise", 0.0) > 0 for m in vicsek) == 2  # two noisy ones


def test_the_encoder_reads_the_nearest_teammates_in_range_of_a_bigger_team_and_masks_a_smaller_ones_gaps():
    from atdrone.models.teammate import fit_blocks

    # 2 frames (newest first) x 5 teammates x [mask, distance / 5, sin, cos]; feature 2 names the teammate
    blocks = torch.zeros(1, 2, 5, 4)
    blocks[..., 2] = torch.arange(5.0)
    blocks[0, 0, :, 0] = torch.tensor([1.0, 0.0, 1.0, 1.0, 1.0])  # teammate 1 beyond range now
    blocks[0, 0, :, 1] = torch.tensor([0.16, 0.01, 0.04, 0.10, 0.18])  # in range, nearest first: 2, 3, 0, 4
    blocks[0, 1, :, 0] = 1.0
    blocks[0, 1, :, 1] = torch.tensor([0.5, 0.0, 0.5, 0.5, 0.01])  # the past frame does not choose
    three = fit_blocks(blocks, 3)
    assert three.shape == (1, 2, 3, 4)
    assert three[0, :, :, 2].tolist() == [[0.0, 2.0, 3.0], [0.0, 2.0, 3.0]]  # index order, every frame
    assert torch.equal(fit_blocks(blocks, 5), blocks)
    seven = fit_blocks(blocks, 7)
    assert torch.equal(seven[..., :5, :], blocks) and not seven[..., 5:, :].any()  # masked: all zeros


def _team_inputs(mates: int, in_range: list[float], distance: list[float]) -> torch.Tensor:
    """Inputs (1, width) of a NAHT-D network with history 1 and one evader in a team with ``mates`` teammates: the
    current frame's teammate blocks with these in-range flags and distances, the past frame and action zeros."""
    D = 4 * (1 + 1 + mates)
    x = torch.zeros(1, 2 * D + 1)
    blocks = x[0, :D].view(1 + 1 + mates, 4)  # the current frame (first): evader, own, teammates
    blocks[2:, 0], blocks[2:, 1] = torch.tensor(in_range), torch.tensor(distance)
    return x


def test_the_decoder_predicts_the_teammates_the_encoder_reads_in_a_team_of_another_size():
    """Built for 4 pursuers (3 teammates): in a team of 6 its targets are the 3 nearest in range now (index
    order), as the encoder reads them; in a team of 3 the missing teammate is left out of the mean."""
    torch.manual_seed(0)
    model = TeammateActorCritic(TeammateConfig(num_p=4, num_e=1, history=1, embed_dim=2, decoder_hidden=2))
    six = _team_inputs(5, [1.0, 0.0, 1.0, 1.0, 1.0], [0.16, 0.01, 0.04, 0.10, 0.18])  # nearest in range: 2, 3, 0
    mates = torch.tensor([[[0.1 * j, 0.2 * j - 0.3, 0.5 + 0.1 * j] for j in range(5)]])  # teammate j's target
    assert model.fit_mates(six, mates)[0, :, 0].tolist() == pytest.approx([0.0, 0.2, 0.3])
    assert model.decoder_loss(six, mates).item() == model.decoder_loss(six, mates[:, [0, 2, 3]]).item()
    three = _team_inputs(2, [1.0, 1.0], [0.1, 0.2])
    with torch.no_grad():
        mean, log_std = model.decode(three)
    s = log_std.exp()
    kl = [
        float(
            torch.log(s[0, j] / mates[0, j, 2])
            + (mates[0, j, 2] ** 2 + (mates[0, j, 1] - mean[0, j]) ** 2) / (2 * s[0, j] ** 2)
            - 0.5
        )
        for j in range(2)
    ]
    loss = model.decoder_loss(three, mates[:, :2])
    assert loss.item() == pytest.approx(sum(kl) / 2, rel=1e-5)  # the two present teammates' mean, not over 3
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


@pytest.mark.parametrize("task", ["configs/tasks/3p2e1o.json", "configs/tasks/6p2e1o.json"])
def test_a_naht_d_network_built_for_four_pursuers_flies_in_a_team_of_another_size(task):
    from atdrone.policies.neural import NeuralPolicy
    from atdrone.teams.evaluation import evaluate

    torch.manual_seed(0)
    model = TeammateActorCritic(TeammateConfig(entity_dim=16, hidden=32))
    policy = NeuralPolicy(model, name="naht-4p", task="4p2e1o")
    result = evaluate(policy, task, "zoo1", episodes=2, cross_task=True)
    assert len(result.records) == 2 and result.task == task.split("/")[-1].removesuffix(".json")
