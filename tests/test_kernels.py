"""The networks' fast kernels (issue 26): numpy's tanh in an update, the transposed weight gradient of Linear.

Each is pinned against torch's own kernel: values within float32 rounding, gradients equal to autograd's,
torch's tanh bit for bit wherever no gradient is taken (rollouts, evaluation, published weights), and a
whole PPO update that lands where the plain kernels' does.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.nn import functional as F

from atdrone.learn.ppo import PPOConfig, ppo_update
from atdrone.models import networks
from atdrone.models.networks import ActorCritic, Linear, NetConfig, tanh


def _ulps(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Distance in float32 units in the last place (same-sign values)."""
    return (a.view(torch.int32).long() - b.view(torch.int32).long()).abs()


def test_tanh_in_an_update_is_numpys_within_two_ulps_of_torchs_and_its_gradient_is_1_minus_y_squared():
    x = torch.cat([torch.linspace(-12.0, 12.0, 1_000_001), torch.logspace(-30, 0, 10_001)]).requires_grad_()
    y = tanh(x)
    assert type(y.grad_fn).__name__ == "_NumpyTanhBackward"
    ref = torch.tanh(x.detach())
    assert int(_ulps(y.detach(), ref).max()) <= 2
    assert not torch.equal(y.detach(), ref)  # a different kernel: the bound above is what holds them together
    y.backward(torch.ones_like(y))
    assert x.grad is not None
    torch.testing.assert_close(x.grad, 1 - ref**2, rtol=0, atol=3e-7)


def test_tanh_without_gradients_is_torchs_bit_for_bit():
    x = torch.randn(100_000) * 3
    with torch.no_grad():
        assert torch.equal(tanh(x.clone().requires_grad_()), torch.tanh(x))
    assert torch.equal(tanh(x), torch.tanh(x))  # no tensor to differentiate
    assert torch.equal(tanh(x.double()), torch.tanh(x.double()))


@pytest.mark.parametrize(
    ("shape", "n_out", "input_grad"),
    [((4096, 194), 128, True), ((4096, 3, 4), 64, False), ((7, 5), 3, True), ((2, 9, 6), 4, True)],
)
def test_linear_gradients_are_autograds(shape, n_out, input_grad):
    torch.manual_seed(0)
    layer = Linear(shape[-1], n_out)
    x = torch.randn(*shape, requires_grad=input_grad)
    grad = torch.randn(*shape[:-1], n_out)
    out = layer(x)
    assert type(out.grad_fn).__name__ == "_LinearFnBackward"
    out.backward(grad)
    # the reference: autograd's F.linear in float64, against which float32 rounding is measured
    w = layer.weight.detach().double().requires_grad_()
    b = layer.bias.detach().double().requires_grad_()
    x_ref = x.detach().double().requires_grad_(input_grad)
    ref = F.linear(x_ref, w, b)
    assert torch.equal(out.detach(), F.linear(x.detach(), layer.weight, layer.bias))  # the forward is F.linear's
    ref.backward(grad.double())

    def close(got: torch.Tensor | None, want: torch.Tensor | None) -> None:
        assert got is not None and want is not None
        assert float((got.double() - want).abs().max()) <= 2e-6 * float(want.abs().max())

    close(layer.weight.grad, w.grad)
    close(layer.bias.grad, b.grad)
    if input_grad:
        close(x.grad, x_ref.grad)
    else:
        assert x.grad is None


def _one_update(seed: int) -> dict[str, torch.Tensor]:
    rng = np.random.default_rng(seed)
    n = 8192
    obs = rng.uniform(-1, 1, (n, 24)).astype(np.float32)
    obs[:, ::4] = obs[:, ::4] > -0.5  # the entity masks
    batch = {
        "obs": obs,
        "u": rng.normal(size=n).astype(np.float32),
        "logp": rng.normal(-1, 0.3, size=n).astype(np.float32),
        "adv": rng.normal(size=n).astype(np.float32),
        "ret": rng.normal(size=n).astype(np.float32),
    }
    torch.manual_seed(seed)
    model = ActorCritic(NetConfig())
    optimizer = torch.optim.Adam(model.parameters(), lr=3e-4)
    ppo_update(
        model, optimizer, batch, PPOConfig(epochs=2, minibatch_size=2048), 2, 4, torch.Generator().manual_seed(1)
    )
    return {k: v.detach().clone() for k, v in model.state_dict().items()}


def test_a_ppo_update_lands_where_torchs_plain_kernels_take_it(monkeypatch):
    fast = _one_update(3)
    monkeypatch.setattr(networks, "tanh", torch.tanh)
    monkeypatch.setattr(networks.Linear, "forward", lambda self, x: F.linear(x, self.weight, self.bias))
    plain = _one_update(3)
    start = {k: v.detach() for k, v in ActorCritic(NetConfig()).state_dict().items()}
    moved = 0.0
    for name, value in plain.items():
        torch.testing.assert_close(fast[name], value, rtol=0, atol=2e-6, msg=name)
        moved = max(moved, float((value - start[name]).abs().max()))
    assert moved > 1e-4  # the update moved the weights far more than the kernels' difference


def test_training_kernels_take_numpys_tanh_without_gradients_and_only_inside():
    x = torch.linspace(-6.0, 6.0, 200_001)
    outside = tanh(x)
    with torch.no_grad(), networks.training_kernels():
        inside = tanh(x)
    assert torch.equal(outside, torch.tanh(x))
    assert torch.equal(inside, torch.from_numpy(np.tanh(x.numpy())))
    assert not torch.equal(inside, outside)
    assert torch.equal(tanh(x), outside)  # the context ended
